"""``psm replay FILE.mcap``: republish a recording on the bus, same keys, bytes and encodings.

Timing follows the recorded receive times (``log_time``): message *i* is sent at
``start + (log_time_i - log_time_0) / speed``. ``--as-fast-as-possible`` drops the waits,
``--topics`` keeps only matching key expressions (wildcards allowed), ``--exclude`` drops some,
``--remap-prefix OLD=NEW`` moves keys to another cell, ``--loop`` repeats until stopped.
All keys are published on one priority lane without express, with blocking congestion control,
so subscribers see the recorded order and an as-fast-as-possible replay loses nothing; latched
streams (goals, obstacles) go through cached advanced publishers so late joiners get them.

Safety: command streams (catalogue topics with ``Topic.commands``, i.e. ``<prefix>/arm/command``)
are never replayed unless asked for with ``--include-commands``; even then the replay is refused
(:class:`ReplayRefusedError`, before anything is published) while the commanded service is alive on
the target prefix (``<prefix>/alive/arm``), unless ``--force``; an arm that appears during such a
replay stops it. Both switches are command-line arguments only (not config or environment), so
a forgotten setting cannot move an arm.

Damaged files: a file that is not MCAP, or has no readable message, fails before anything is
published. A file truncated (or corrupt) after some complete chunks is replayed up to its last
complete chunk, then :func:`run_replayer` raises :class:`~services.bus.log.LogReadError` naming
how much was replayed (exit code 2 from ``psm replay``): the readable part of a recording
whose recorder was killed is usable, and the exit code still says the file was not whole.

Example::

    psm replay out/run.mcap --speed 2 --topics 'psm/arm/**' --remap-prefix psm=sim
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import Field

from services.bus.config import ConfigError, Section, ServiceConfig, StrList
from services.bus.errors import BusError
from services.bus.log import LogReadError, read_samples, scan_log, topic_matcher
from services.bus.messages import validate_key_expr
from services.bus.runtime import Service, ServiceApp, publisher_matching, run_service

__all__ = ["ReplayRefusedError", "ReplayerConfig", "ReplayerSection", "remap_key", "run_replayer"]

#: After the first subscriber matches, how long the other keys' routes are given to complete [s].
SETTLE_S = 0.3


class ReplayRefusedError(BusError):
    """The replay would command a live service (an arm alive on the target prefix)."""


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


def catalogue_match(key: str) -> tuple[str, Any] | None:
    """``(prefix, Topic)`` of a concrete key under any prefix, e.g. ``cell1/psm/arm/command`` ->
    ``("cell1/psm", Keys("cell1/psm").arm_command)``; ``None`` if not in the catalogue."""
    from services.bus.messages import InvalidKeyError, Keys

    chunks = key.split("/")
    for i in range(1, len(chunks)):
        prefix = "/".join(chunks[:i])
        try:
            topic = Keys(prefix).topic_for_key(key)
        except InvalidKeyError:
            return None
        if topic is not None:
            return prefix, topic
    return None


def catalogue_topic(key: str) -> Any:
    """The catalogue :class:`~services.bus.messages.Topic` of a concrete key under any prefix
    (``None`` if the key is not in the catalogue)."""
    hit = catalogue_match(key)
    return None if hit is None else hit[1]


def _alive(session: Any, keys: list[str], seen: list[str], settle_s: float = 1.0) -> list[str]:
    """The liveliness tokens among ``keys`` that are alive, asked for ``settle_s`` seconds.

    A freshly opened session learns the network's tokens within a few ms; a single query right
    after opening can miss them, so the network is asked every 50 ms until ``settle_s``, and
    ``seen`` (filled by history-enabled liveliness subscribers on ``keys``) is checked too.
    """
    deadline = time.monotonic() + settle_s
    alive: set[str] = set()
    while True:
        alive.update(seen)
        for key in keys:
            for reply in session.liveliness().get(key, timeout=max(0.1, settle_s)):
                if reply.ok is not None:
                    alive.add(str(reply.ok.key_expr))
        if alive or time.monotonic() >= deadline:
            return sorted(alive)
        time.sleep(0.05)


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


def run_replayer(
    cfg: ReplayerConfig, *, include_commands: bool = False, force: bool = False
) -> int:
    """Replay ``cfg.replayer.files``; returns the exit code.

    Args:
        cfg: the replayer configuration.
        include_commands: also replay command streams (``<prefix>/arm/command``).
        force: replay command streams even while the commanded service is alive.

    Raises:
        LogReadError: a file is not MCAP or has no readable message (before publishing), or
            was truncated/corrupt (after replaying its readable part).
        ReplayRefusedError: commands were asked for and an arm is alive on the target prefix
            (before publishing), or one appeared during the replay (the replay stops).
        InvalidKeyError: an invalid ``--topics`` / ``--exclude`` key expression.
    """
    rp = cfg.replayer
    for k in [*rp.topics, *rp.exclude]:
        validate_key_expr(k)
    for f in rp.files:
        if not Path(f).is_file():
            raise FileNotFoundError(f"no such recording: {f}")
    scans = [scan_log(f) for f in rp.files]
    for sc in scans:
        if sc.messages == 0:
            raise LogReadError(f"{sc.path}: {sc.problem or 'no messages'}; nothing to replay")
    match = topic_matcher(rp.topics) if rp.topics else None
    exclude = topic_matcher(rp.exclude) if rp.exclude else None
    keys: dict[str, str] = {}
    for sc in scans:
        for key, enc in sc.keys.items():
            if (match is None or match(key)) and not (exclude and exclude(key)):
                keys.setdefault(key, enc)
    commands: dict[str, str] = {}  # recorded key -> liveliness key of the commanded service
    for key in keys:
        hit = catalogue_match(remap_key(key, rp.remap_prefix))
        if hit is not None and hit[1].is_command:
            from services.bus.messages import Keys

            commands[key] = Keys(hit[0]).liveliness(hit[1].commands).key
    skipped = [] if include_commands else sorted(commands)
    for key in skipped:
        del keys[key]
        del commands[key]
    app = _Replayer(cfg, scans, keys, commands, skipped, force)
    run_service(app)
    damaged = [sc for sc in scans if not sc.complete]
    if damaged:
        sc = damaged[0]
        raise LogReadError(f"{sc.path}: {sc.problem}; replayed {app.stats.published} messages up to "
                           "there")
    return 0


class _Replayer(ServiceApp):
    """Republishes the recorded keys; with command keys, refuses (and stops) while the
    commanded service is alive."""

    name = "replayer"

    def __init__(
        self, cfg: ReplayerConfig, scans: list[Any], keys: dict[str, str],
        commands: dict[str, str], skipped: list[str], force: bool,
    ) -> None:
        super().__init__(cfg)
        self.rp = cfg.replayer
        self.scans, self.keys, self.commands, self.skipped, self.force = scans, keys, commands, skipped, force
        self.stats = ReplayStats()
        self.pubs: dict[str, Any] = {}
        self.appeared: list[str] = []
        self.watchers: list[Any] = []

    def setup(self, svc: Service) -> None:
        commands = self.commands
        if self.skipped:
            svc.log.info("not replaying command keys (use --include-commands)",
                         extra={"keys": self.skipped})
        tokens = sorted(set(commands.values()))
        if tokens and self.force:
            svc.log.warning("--force: replaying commands without checking for a live arm",
                            extra={"keys": sorted(commands)})
        elif tokens:
            import zenoh

            def on_token(sample: Any) -> None:
                if sample.kind == zenoh.SampleKind.PUT:
                    self.appeared.append(str(sample.key_expr))
                    svc.stop()

            self.watchers = [svc.session.liveliness().declare_subscriber(t, on_token, history=True)
                             for t in tokens]
            alive = _alive(svc.session, tokens, self.appeared)
            if alive:
                raise ReplayRefusedError(
                    f"refusing to replay {', '.join(sorted(commands))}: {alive[0]} is alive "
                    "(a live arm would move; stop it, replay onto another prefix with "
                    "--remap-prefix, or add --force)")

    def loop(self, svc: Service) -> None:
        _replay(svc, self.rp, self.scans, self.keys, self.pubs, self.stats)
        if self.appeared:
            raise ReplayRefusedError(
                f"stopped the replay: {self.appeared[0]} appeared while replaying "
                f"{', '.join(sorted(self.commands))} ({self.stats.published} messages sent)")

    def teardown(self, svc: Service) -> None:
        for w in self.watchers:
            w.undeclare()
        for p in self.pubs.values():
            p.undeclare()


def _replay(
    svc: Any, rp: ReplayerSection, scans: list[Any], keys: dict[str, str],
    pubs: dict[str, Any], stats: ReplayStats,
) -> None:
    """Declare a publisher per key, wait for subscribers, then republish the files with the
    recorded timing (or as fast as possible) until done or stopped."""
    for key in keys:
        pubs[key] = _declare(svc.session, remap_key(key, rp.remap_prefix))
    if rp.wait_subscribers_s > 0 and pubs:
        deadline = time.monotonic() + rp.wait_subscribers_s
        while time.monotonic() < deadline and not svc.stop_event.is_set():
            if all(publisher_matching(p) for p in pubs.values()):
                break
            if any(publisher_matching(p) for p in pubs.values()):
                # A subscriber is there; the routes of the other keys through a router complete
                # a little after the first match: let them settle (bounded by the wait).
                svc.stop_event.wait(min(SETTLE_S, max(0.0, deadline - time.monotonic())))
                break
            time.sleep(0.01)
    svc.log.info("replaying", extra={"files": rp.files, "keys": len(pubs),
                                     "speed": rp.speed, "afap": rp.as_fast_as_possible})
    for sc in scans:
        if not sc.complete:
            svc.log.warning("damaged recording: replaying its readable part",
                            extra={"path": str(sc.path), "problem": sc.problem})
    while not svc.stop_event.is_set():
        t_wall0 = time.monotonic()
        t_log0: int | None = None
        for sc in scans:
            for s in read_samples(sc.path, quiet=True):
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
                if svc.stop_event.is_set():
                    break
                pub.put(s.payload, encoding=s.encoding)
                svc.counters.add("published")
                stats.published += 1
        stats.loops += 1
        if not rp.loop or (rp.max_loops and stats.loops >= rp.max_loops):
            break
    svc.log.info("replay done", extra={"published": stats.published, "loops": stats.loops,
                                       "late_max_s": round(stats.late_max_s, 6)})
