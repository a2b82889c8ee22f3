"""Looking at a running bus: ``psm status`` (services alive on a prefix, with their status) and
``psm topics`` (every live key with its type, rate and bandwidth) — what ``ros2 node list``,
``ros2 topic list -v`` and ``ros2 topic hz`` give ROS users.

Both join the bus as a plain session (no liveliness token of their own, nothing published).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from services.bus.config import ServiceConfig

__all__ = [
    "TopicStats",
    "collect_status",
    "collect_topics",
    "human_bandwidth",
    "run_status",
    "run_topics",
    "terminal_console",
]


def collect_status(
    session: Any, prefix: str, wait_s: float, *, with_status: bool = True
) -> tuple[set[str], dict[str, Any]]:
    """The services alive on ``prefix`` (liveliness query, answered within ``min(wait_s, 2)``
    seconds) and, with ``with_status``, the latest ServiceStatus of each one heard within
    ``wait_s`` seconds."""
    from services.bus.messages import Keys, ServiceStatus, decode

    keys = Keys(prefix)
    statuses: dict[str, Any] = {}
    lock = threading.Lock()

    def on_status(sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), str(sample.encoding), ServiceStatus)
        except ValueError:
            return
        with lock:
            statuses[msg.service] = msg

    sub = session.declare_subscriber(keys.status_all.key, on_status)
    try:
        base = keys.liveliness_all.key[:-1]
        alive = set()
        for reply in session.liveliness().get(keys.liveliness_all.key, timeout=min(wait_s, 2.0)):
            ok = getattr(reply, "ok", None)
            if ok is not None:
                alive.add(str(ok.key_expr)[len(base):])
        deadline = time.monotonic() + (wait_s if with_status else 0.0)
        while time.monotonic() < deadline:
            with lock:
                if alive and alive <= set(statuses):
                    break
            time.sleep(0.05)
    finally:
        sub.undeclare()
    with lock:
        return alive, dict(statuses)


def status_table(prefix: str, alive: set[str], statuses: dict[str, Any]) -> Any:
    """A rich Table of the services."""
    from rich.table import Table

    from services.bus.messages import ServiceStatus

    t = Table(title=f"services on {prefix}/ ({len(alive)} alive)")
    for col in ("service", "alive", "state", "uptime s", "received", "published", "rejected",
                "errors", "dropped", "version", "last error"):
        t.add_column(col)
    for name in sorted(alive | set(statuses)):
        st = statuses.get(name)
        if st is None:
            t.add_row(name, "yes" if name in alive else "no", "(no status)", *[""] * 8)
            continue
        t.add_row(name, "yes" if name in alive else "no", ServiceStatus.State.Name(st.state),
                  f"{st.uptime_s:.1f}", str(st.received), str(st.published), rejected_cell(st),
                  str(st.errors), str(st.dropped), st.version, st.last_error[:60])
    return t


def rejected_cell(status: Any) -> str:
    """The rejected count of a ``ServiceStatus`` with its reasons, e.g. ``12 (stamp 7, tick 5)``."""
    by = sorted(status.rejected_by_reason.items(), key=lambda kv: (-kv[1], kv[0]))
    reasons = ", ".join(f"{k} {v}" for k, v in by)
    return f"{status.rejected} ({reasons})" if reasons else str(status.rejected)


def terminal_console() -> Any:
    """A rich console; wide enough for the tables when the output is not a terminal."""
    from rich.console import Console

    console = Console()
    return console if console.is_terminal else Console(width=200)


def run_status(
    cfg: ServiceConfig,
    *,
    watch: bool = False,
    wait_s: float = 1.5,
    services: Sequence[str] = (),
    quiet: bool = False,
) -> int:
    """``psm status``: print the services alive on the prefix. Exit code 1 when none is, or,
    with ``services``, when one of them is not alive (a container healthcheck); ``quiet``
    prints only the missing ones."""
    from services.bus.runtime import open_session

    console = terminal_console()
    session = open_session(cfg.zenoh)
    try:
        while True:
            alive, statuses = collect_status(session, cfg.prefix, wait_s, with_status=not quiet)
            missing = [s for s in services if s not in alive]
            if not quiet:
                table = status_table(cfg.prefix, alive, statuses)
                if watch:
                    console.clear()
                console.print(table)
            if not watch:
                if missing:
                    print(f"not alive on {cfg.prefix}/: {', '.join(missing)}", file=sys.stderr)
                    return 1
                return 0 if alive else 1
    except KeyboardInterrupt:
        return 0
    finally:
        session.close()


@dataclass
class TopicStats:
    """What was seen on one key during a window."""

    key: str
    encoding: str = ""
    count: int = 0
    bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    times: list[int] = field(default_factory=list)

    def rate_hz(self, window_s: float) -> float:
        """Messages per second: from the spacing of the samples when there are several."""
        if self.count >= 3 and self.last_ns > self.first_ns:
            return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)
        return self.count / window_s

    def bandwidth_bps(self, window_s: float) -> float:
        """Bytes per second over the window."""
        return self.bytes / window_s


def collect_topics(session: Any, prefix: str, window_s: float) -> dict[str, TopicStats]:
    """Listen to ``<prefix>/**`` for ``window_s`` seconds; returns the stats per key."""
    from services.bus.messages import Keys

    stats: dict[str, TopicStats] = {}
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        now = time.monotonic_ns()
        key = str(sample.key_expr)
        size = len(sample.payload)
        with lock:
            s = stats.get(key)
            if s is None:
                s = stats[key] = TopicStats(key, str(sample.encoding), first_ns=now)
            s.count += 1
            s.bytes += size
            s.last_ns = now

    sub = session.declare_subscriber(Keys(prefix).all.key, on_sample)
    try:
        time.sleep(window_s)
    finally:
        sub.undeclare()
    with lock:
        return dict(stats)


def _type_of(encoding: str) -> str:
    from services.bus.messages import ENCODING_PREFIX

    return encoding.removeprefix(ENCODING_PREFIX).removeprefix("application/protobuf;")


def human_bandwidth(bps: float) -> str:
    """A bandwidth in bytes per second for people, e.g. ``512 B/s``, ``12.3 KB/s`` (1 KB =
    1000 B)."""
    for unit in ("B/s", "KB/s", "MB/s"):
        if bps < 1000 or unit == "MB/s":
            return f"{bps:.1f} {unit}" if unit != "B/s" else f"{bps:.0f} {unit}"
        bps /= 1000
    return f"{bps:.1f} MB/s"


def topics_table(prefix: str, stats: dict[str, TopicStats], window_s: float) -> Any:
    """A rich Table of the keys seen."""
    from rich.table import Table

    t = Table(title=f"keys on {prefix}/** over {window_s:g} s")
    for col in ("key", "type", "rate Hz", "bandwidth", "messages"):
        t.add_column(col, justify="right" if col in ("rate Hz", "bandwidth", "messages") else "left")
    for key in sorted(stats):
        s = stats[key]
        t.add_row(key, _type_of(s.encoding), f"{s.rate_hz(window_s):.1f}",
                  human_bandwidth(s.bandwidth_bps(window_s)), str(s.count))
    return t


def run_topics(cfg: ServiceConfig, *, window_s: float = 2.0, watch: bool = False) -> int:
    """``psm topics``: print the live keys (exit 1 when nothing was heard)."""
    from services.bus.runtime import open_session

    console = terminal_console()
    session = open_session(cfg.zenoh)
    try:
        while True:
            stats = collect_topics(session, cfg.prefix, window_s)
            if watch:
                console.clear()
            console.print(topics_table(cfg.prefix, stats, window_s))
            if not watch:
                return 0 if stats else 1
    except KeyboardInterrupt:
        return 0
    finally:
        session.close()
