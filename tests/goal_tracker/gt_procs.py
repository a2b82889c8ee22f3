"""Process helpers for the goal tracker's integration tests: real processes on loopback.

Every process is started with ``sys.executable -m …`` from the repository root through the
supervisor's :class:`~services.supervisor.ManagedProcess`, connects as a Zenoh client to a
router on 127.0.0.1 at a random free port with multicast scouting off, and is stopped by its PID
(SIGTERM, then SIGKILL after a bounded wait).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from services.supervisor import ManagedProcess

REPO = Path(__file__).resolve().parents[2]


class Procs:
    """Starts module processes and guarantees they are stopped."""

    def __init__(self, tmp: Path, endpoint: str) -> None:
        self.tmp = tmp
        self.endpoint = endpoint
        self.procs: list[ManagedProcess] = []

    def bus_args(self, prefix: str = "psm") -> list[str]:
        """Client flags for the test router."""
        return ["--mode", "client", "--connect", self.endpoint, "--no-multicast", "--prefix", prefix]

    def start(self, name: str, module: str, *args: str) -> ManagedProcess:
        """Start ``python -m module args`` with output in ``<tmp>/<name>.log``."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("PSM_")}
        proc = ManagedProcess(name, [sys.executable, "-m", module, *args], self.tmp / f"{name}.log", env=env)
        self.procs.append(proc)
        return proc

    @staticmethod
    def log(proc: ManagedProcess) -> str:
        """The output of ``proc`` so far."""
        return proc.log_text()

    @staticmethod
    def stop(proc: ManagedProcess, timeout_s: float = 15.0) -> int:
        """SIGTERM ``proc`` by PID, wait, SIGKILL if it hangs; returns the exit code."""
        return proc.stop(timeout_s)

    def stop_all(self) -> None:
        """Stop everything still running (newest first)."""
        for proc in reversed(self.procs):
            proc.stop(5.0)


def wait_until(pred: Callable[[], bool], timeout_s: float, what: str, step_s: float = 0.05) -> None:
    """Poll ``pred`` until true; fail the test after ``timeout_s`` seconds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(step_s)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}")


def alive(session: object, key: str) -> bool:
    """True when a liveliness token matching ``key`` is declared."""
    replies = session.liveliness().get(key, timeout=1.0)  # type: ignore[attr-defined]
    return any(getattr(r, "ok", None) is not None for r in replies)
