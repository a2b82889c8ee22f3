"""The realtime and lockstep arm's loop statistics: what ``psm arm`` writes to its
``stats_file`` (:meth:`LoopStats.summary`) and what ``psm up`` and the benchmarks read from it.

Numpy only: the supervisor reads these files without loading the arm.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

_RING = 1 << 20  # timing samples kept (about 35 min at 500 Hz)
#: Where a published missed tick's lateness arose (:meth:`LoopStats.add_miss`).
MISS_CAUSES = ("wake", "lock", "step")
#: :data:`MISS_CAUSES` in words, in the same order (the heading of :func:`miss_causes_text`).
MISS_CAUSES_HEAD = "asleep past the deadline / waiting for the step lock / stepping and publishing"
#: Published missed ticks kept with their timing parts (the latest ones).
MISS_RECORDS = 32


def miss_causes_text(missed_by: Mapping[str, int] | None) -> str:
    """The published missed ticks of a statistics file's ``missed_by`` by cause, as
    ``"wake / lock / step"`` counts (:data:`MISS_CAUSES_HEAD`); ``"–"`` without them (a file
    written before the causes were counted)."""
    if not missed_by:
        return "–"
    return " / ".join(str(missed_by.get(cause, 0)) for cause in MISS_CAUSES)


@dataclass
class LoopStats:
    """Timing of the control loop (wall clock, ns) and event counts."""

    ticks: int = 0
    wall_s: float = 0.0
    missed_ticks: int = 0  #: realtime: ticks not published within one dt of their schedule
    skipped_ticks: int = 0  #: realtime: missed ticks stepped through without publication
    reanchors: int = 0  #: realtime: gaps too long to simulate (schedule re-anchored)
    published_ticks: int = 0  #: states published
    late_commands: int = 0  #: command answering tick k arrived after tick k's deadline
    answered_ticks: int = 0  #: ticks for which an answering command arrived
    lockstep_timeouts: int = 0
    jitter_ns: np.ndarray = field(default_factory=lambda: np.zeros(_RING, dtype=np.int64))
    latency_ns: np.ndarray = field(default_factory=lambda: np.zeros(_RING, dtype=np.int64))
    n_jitter: int = 0
    n_latency: int = 0
    #: realtime: the published missed ticks by where their lateness arose (:meth:`add_miss`)
    missed_by: dict[str, int] = field(default_factory=lambda: dict.fromkeys(MISS_CAUSES, 0))
    #: realtime: the latest :data:`MISS_RECORDS` published missed ticks, ``(tick, wake, lock, step)``
    #: [tick, ns, ns, ns]
    misses: deque[tuple[int, int, int, int]] = field(default_factory=lambda: deque(maxlen=MISS_RECORDS))

    def add_miss(self, tick: int, wake_ns: int, lock_ns: int, step_ns: int) -> None:
        """Count a tick published more than one dt after its schedule and where its lateness
        arose [ns]: ``wake`` from the schedule until the loop ran again (the thread asleep past
        its deadline: woken late by the OS or the hypervisor, waiting for the interpreter lock,
        or still busy with the tick before), ``lock`` waiting for the step lock (a command being
        stepped on Zenoh's thread), ``step`` stepping without an answer, encoding and the
        ``put``. The cause counted is the largest part."""
        self.missed_ticks += 1
        parts = (wake_ns, lock_ns, step_ns)
        self.missed_by[MISS_CAUSES[parts.index(max(parts))]] += 1
        self.misses.append((tick, wake_ns, lock_ns, step_ns))

    def add_jitter(self, ns: int) -> None:
        """Record a tick's publication lateness vs. its schedule, ns."""
        self.jitter_ns[self.n_jitter % _RING] = ns
        self.n_jitter += 1

    def add_latency(self, ns: int) -> None:
        """Record a state→command latency, ns."""
        self.latency_ns[self.n_latency % _RING] = ns
        self.n_latency += 1

    def summary(self) -> dict[str, Any]:
        """JSON-able summary with percentiles in µs."""

        def pct(a: np.ndarray, n: int) -> dict[str, float]:
            v = a[: min(n, _RING)]
            if v.size == 0:
                return {}
            p50, p99, p999 = np.percentile(v, [50, 99, 99.9])
            return {
                "p50_us": float(p50) / 1e3,
                "p99_us": float(p99) / 1e3,
                "p99.9_us": float(p999) / 1e3,
                "max_us": float(v.max()) / 1e3,
                "mean_us": float(v.mean()) / 1e3,
                "n": int(v.size),
            }

        return {
            "ticks": self.ticks,
            "wall_s": self.wall_s,
            "ticks_per_s": self.ticks / self.wall_s if self.wall_s > 0 else 0.0,
            "missed_ticks": self.missed_ticks,
            "missed_by": {**self.missed_by, "skipped": self.skipped_ticks},
            "misses": [
                {"tick": k, "wake_us": w / 1e3, "lock_us": lk / 1e3, "step_us": st / 1e3}
                for k, w, lk, st in self.misses
            ],
            "skipped_ticks": self.skipped_ticks,
            "reanchors": self.reanchors,
            "published_ticks": self.published_ticks,
            "published_per_s": self.published_ticks / self.wall_s if self.wall_s > 0 else 0.0,
            "late_commands": self.late_commands,
            "answered_ticks": self.answered_ticks,
            "late_fraction": self.late_commands / self.answered_ticks if self.answered_ticks else 0.0,
            "lockstep_timeouts": self.lockstep_timeouts,
            "jitter": pct(self.jitter_ns, self.n_jitter),
            "state_to_command_latency": pct(self.latency_ns, self.n_latency),
        }
