"""Process helpers for the goal tracker's integration tests: real processes on loopback.

Every process is started with ``sys.executable -m …`` from the repository root, connects as a
Zenoh client to a router on 127.0.0.1 at a random free port with multicast scouting off, and is
stopped by its PID (SIGTERM, then SIGKILL after a bounded wait).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Procs:
    """Starts module processes and guarantees they are stopped."""

    def __init__(self, tmp: Path, endpoint: str) -> None:
        self.tmp = tmp
        self.endpoint = endpoint
        self.procs: list[tuple[subprocess.Popen, Path]] = []

    def bus_args(self, prefix: str = "psm") -> list[str]:
        """Client flags for the test router."""
        return ["--mode", "client", "--connect", self.endpoint, "--no-multicast", "--prefix", prefix]

    def start(self, name: str, module: str, *args: str) -> subprocess.Popen:
        """Start ``python -m module args`` with output in ``<tmp>/<name>.log``."""
        log = self.tmp / f"{name}.log"
        env = {**os.environ, "RUST_LOG": "error", "PYTHONUNBUFFERED": "1"}
        env.pop("PSM_MULTICAST", None)
        with log.open("wb") as fh:
            proc = subprocess.Popen(
                [sys.executable, "-m", module, *args],
                cwd=REPO,
                stdout=fh,
                stderr=subprocess.STDOUT,
                env=env,
            )
        self.procs.append((proc, log))
        return proc

    def log(self, proc: subprocess.Popen) -> str:
        """The output of ``proc`` so far."""
        for p, log in self.procs:
            if p is proc:
                return log.read_text(errors="replace")
        return ""

    @staticmethod
    def stop(proc: subprocess.Popen, timeout_s: float = 15.0) -> int:
        """SIGTERM ``proc`` by PID, wait, SIGKILL if it hangs; returns the exit code."""
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(5)
        return int(proc.returncode)

    def stop_all(self) -> None:
        """Stop everything still running (newest first)."""
        for proc, _ in reversed(self.procs):
            self.stop(proc, 5.0)


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
