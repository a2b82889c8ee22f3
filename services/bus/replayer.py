"""``psm replay FILE.mcap``: republish a recording on the bus, same keys, bytes and encodings.

Timing follows the recorded receive times (``log_time``): message *i* is sent at
``start + (log_time_i - log_time_0) / speed``. ``--as-fast-as-possible`` drops the waits,
``--topics`` keeps only matching key expressions (wildcards allowed), ``--exclude`` drops some,
``--remap-prefix OLD=NEW`` moves keys to another cell, ``--loop`` repeats until stopped.
All keys are published on one priority lane without express, with blocking congestion control,
so subscribers see the recorded order and an as-fast-as-possible replay loses nothing; latched
streams (goals, obstacles) go through cached advanced publishers so late joiners get them.

Example::

    psm replay out/run.mcap --speed 2 --topics 'psm/arm/**' --remap-prefix psm=sim
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import Field

from services.bus.config import ConfigError, Section, ServiceConfig, StrList
from services.bus.log import _topic_matcher, read_samples

__all__ = ["ReplayerConfig", "ReplayerSection", "remap_key", "run_replayer"]


class ReplayerSection(Section):
    """``[replayer]`` section."""

    files: StrList = Field(default_factory=list, description="recordings to replay")
    speed: float = Field(1.0, gt=0.0, le=1e6, description="time scale (2 = twice as fast)")
    as_fast_as_possible: bool = Field(False, description="ignore recorded timing")
    topics: StrList = Field(default_factory=list, description="only these key expressions (default all)")
    exclude: StrList = Field(default_factory=list, description="drop these key expressions")
    remap_prefix: str = Field("", description="OLD=NEW key prefix remap")
    loop: bool = Field(False, description="repeat until stopped")
    wait_subscribers_s: float = Field(
        0.0, ge=0.0,
        description="wait up to this long for a matching subscriber before sending, s",
    )
    max_loops: int = Field(0, ge=0, description="stop after this many loops with --loop (0 = unlimited)")

    def check(self) -> None:
        """``remap_prefix`` is ``OLD=NEW``."""
        rp = self.remap_prefix
        if rp:
            old, sep, new = rp.partition("=")
            if not sep or not old or not new:
                raise ConfigError("remap_prefix", f"expected OLD=NEW, got {rp!r}")


class ReplayerConfig(ServiceConfig):
    """Replayer service configuration."""

    replayer: ReplayerSection = Field(default_factory=ReplayerSection)


def remap_key(key: str, remap: str) -> str:
    """Apply an ``OLD=NEW`` prefix remap to ``key`` (keys outside ``OLD`` are unchanged)."""
    if not remap:
        return key
    old, _, new = remap.partition("=")
    old, new = old.rstrip("/"), new.rstrip("/")
    if key == old or key.startswith(old + "/"):
        return new + key[len(old):]
    return key


@dataclass
class ReplayStats:
    """What a replay sent."""

    published: int = 0
    loops: int = 0
    late_max_s: float = 0.0  # worst lateness vs. the recorded schedule, s
    keys: set[str] = field(default_factory=set)


def _keys_in(files: Iterable[str], match: Any, exclude: Any) -> dict[str, str]:
    keys: dict[str, str] = {}
    for f in files:
        for s in read_samples(f):
            if (match is None or match(s.topic)) and not (exclude and exclude(s.topic)):
                keys.setdefault(s.topic, s.encoding)
    return keys


def catalogue_topic(key: str) -> Any:
    """The catalogue :class:`~services.bus.messages.Topic` of a concrete key under any prefix
    (``None`` if the key is not in the catalogue)."""
    from services.bus.messages import InvalidKeyError, Keys

    chunks = key.split("/")
    for i in range(1, len(chunks)):
        try:
            topic = Keys("/".join(chunks[:i])).topic_for_key(key)
        except InvalidKeyError:
            return None
        if topic is not None:
            return topic
    return None


def _declare(session: Any, key: str) -> Any:
    """A publisher for ``key``: one priority lane and no express for every key, so subscribers
    receive the messages in the recorded order even as fast as possible (per-stream priorities
    would let control messages overtake others); blocking congestion control so nothing is
    dropped; for latched streams an advanced publisher with a cache so late joiners get the
    replayed goals/obstacles."""
    import zenoh

    topic = catalogue_topic(key)
    kwargs: dict[str, Any] = {
        "congestion_control": zenoh.CongestionControl.BLOCK,
        "priority": zenoh.Priority.DATA,
        "express": False,
    }
    if topic is not None and topic.qos.history > 0:
        import zenoh.ext as zext

        return zext.declare_advanced_publisher(
            session, key, cache=zext.CacheConfig(max_samples=topic.qos.history),
            publisher_detection=True, **kwargs)
    return session.declare_publisher(key, **kwargs)


def run_replayer(cfg: ReplayerConfig) -> int:
    """Replay ``cfg.replayer.files``; returns the exit code."""
    from services.bus.runtime import Service

    rp = cfg.replayer
    for f in rp.files:
        if not Path(f).is_file():
            raise FileNotFoundError(f"no such recording: {f}")
    match = _topic_matcher(rp.topics) if rp.topics else None
    exclude = _topic_matcher(rp.exclude) if rp.exclude else None
    svc = Service("replayer", cfg)
    svc.start()
    svc.install_signal_handlers()
    stats = ReplayStats()
    pubs: dict[str, Any] = {}
    try:
        for key in _keys_in(rp.files, match, exclude):
            pubs[key] = _declare(svc.session, remap_key(key, rp.remap_prefix))
        if rp.wait_subscribers_s > 0 and pubs:
            deadline = time.monotonic() + rp.wait_subscribers_s
            while time.monotonic() < deadline and not svc.stop_event.is_set():
                if any(getattr(p, "matching_status", False) for p in pubs.values()):
                    break
                time.sleep(0.01)
        svc.log.info("replaying", extra={"files": rp.files, "keys": len(pubs),
                                         "speed": rp.speed, "afap": rp.as_fast_as_possible})
        while not svc.stop_event.is_set():
            t_wall0 = time.monotonic()
            t_log0: int | None = None
            for f in rp.files:
                for s in read_samples(f):
                    if svc.stop_event.is_set():
                        break
                    pub = pubs.get(s.topic)
                    if pub is None:
                        continue
                    if not rp.as_fast_as_possible:
                        if t_log0 is None:
                            t_log0 = s.log_time_ns
                        due = t_wall0 + (s.log_time_ns - t_log0) / 1e9 / rp.speed
                        delay = due - time.monotonic()
                        if delay > 0.05:
                            svc.stop_event.wait(delay)
                        elif delay > 0:
                            time.sleep(delay)
                        else:
                            stats.late_max_s = max(stats.late_max_s, -delay)
                    pub.put(s.payload, encoding=s.encoding)
                    svc.counters.add("published")
                    stats.published += 1
            stats.loops += 1
            if not rp.loop or (rp.max_loops and stats.loops >= rp.max_loops):
                break
        svc.log.info("replay done", extra={"published": stats.published, "loops": stats.loops,
                                           "late_max_s": round(stats.late_max_s, 6)})
    finally:
        for p in pubs.values():
            p.undeclare()
        svc.close()
    return 0
