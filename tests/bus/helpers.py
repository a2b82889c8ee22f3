"""Helpers for the bus tests: service processes started with ``sys.executable -m ...`` through
the supervisor's process class and cleaned up by PID, an in-process bus client."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from services.supervisor import ManagedProcess

ROOT = Path(__file__).resolve().parents[2]


def wait_for(pred: Callable[[], bool], timeout_s: float = 10.0, period_s: float = 0.02) -> bool:
    """Poll ``pred`` until true or ``timeout_s``; returns the last result."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period_s)
    return bool(pred())


class Proc(ManagedProcess):
    """A child process (the supervisor's :class:`~services.supervisor.ManagedProcess`) with
    stdout and stderr captured to separate files and no ``PSM_*`` variable of the test's
    environment."""

    def __init__(self, args: list[str], workdir: Path, name: str, env: dict | None = None):
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("PSM_")}
        full_env.update(env or {})
        super().__init__(name, [sys.executable, *args], workdir / f"{name}.out", env=full_env,
                         stderr_path=workdir / f"{name}.err")

    def stderr(self) -> str:
        """What the process wrote to stderr so far."""
        return self.stderr_text()

    def stdout(self) -> str:
        """What the process wrote to stdout so far."""
        return self.log_text()


def bus_args(endpoint: str) -> list[str]:
    """CLI flags joining the test bus: connect to ``endpoint``, multicast off."""
    return ["--connect", endpoint, "--no-multicast", "--mode", "peer"]


def port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def client_config(endpoint: str, **overrides: object):  # type: ignore[no-untyped-def]
    """An in-process :class:`ServiceConfig` connected to ``endpoint`` with multicast off."""
    from services.bus.config import ServiceConfig, load_config

    ov = {"zenoh.connect": [endpoint], "zenoh.multicast": False, "status_period_s": 0.2}
    ov.update(overrides)
    return load_config(ServiceConfig, env={}, overrides=ov)


def run_psm(*args: str, timeout_s: float = 60.0,
            env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m services.cli ARGS`` to completion (the real ``psm`` entry point) with
    the repository on ``PYTHONPATH`` and no ``PSM_*`` variables from the caller."""
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("PSM_")}
    full_env["PYTHONPATH"] = str(ROOT) + os.pathsep + full_env.get("PYTHONPATH", "")
    full_env.update(env or {})
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=ROOT,
                          env=full_env, capture_output=True, text=True, timeout=timeout_s)


_LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\dT\S+Z (DEBUG|INFO|WARNING) \S+: ")


def one_error_line(result: subprocess.CompletedProcess, command: str) -> str:
    """Assert ``result`` failed the way every CLI error does (exit code 2, exactly one stderr
    line ``<command>: error: ...`` besides the service's own INFO/WARNING log lines, no
    traceback); returns the message after ``error: ``."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = [ln for ln in result.stderr.splitlines() if not _LOG_LINE.match(ln)]
    assert len(lines) == 1 and result.stderr.endswith("\n"), result.stderr
    assert "Traceback" not in result.stderr
    head = f"{command}: error: "
    assert lines[0].startswith(head), lines[0]
    return lines[0][len(head):]
