"""Fixtures for the arm's integration tests: a Zenoh router on a random loopback port (in the
test process, multicast off) and helpers to run the real arm / probe / recorder processes."""

from __future__ import annotations

import contextlib
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from services.supervisor import ManagedProcess, free_port

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def robot() -> Any:
    """The default robot model (the reduced Panda)."""
    from services.robot.model import RobotModel

    return RobotModel.load()


class Bus:
    """An in-process Zenoh router that the spawned processes connect to as clients."""

    def __init__(self) -> None:
        from services.bus.config import ZenohConfig
        from services.bus.runtime import open_session

        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = open_session(
            ZenohConfig(mode="router", listen=[self.endpoint], multicast=False, gossip=False)
        )
        self.procs: list[ManagedProcess] = []
        self._logdir = tempfile.TemporaryDirectory()

    @property
    def client_args(self) -> list[str]:
        """Bus flags for a spawned service."""
        return ["--mode", "client", "--connect", self.endpoint, "--no-multicast", "--log-level", "WARNING"]

    def spawn(self, module: str, *args: str) -> ManagedProcess:
        """Start ``python -m module args`` (connected to this bus) and remember it."""
        name = f"{module.rsplit('.', 1)[-1]}-{len(self.procs)}"
        proc = ManagedProcess(
            name,
            [sys.executable, "-m", module, *args, *self.client_args],
            Path(self._logdir.name) / f"{name}.log",
        )
        self.procs.append(proc)
        return proc

    def stderr(self, proc: ManagedProcess) -> str:
        """What the process wrote so far."""
        return proc.log_text()

    def collect(self, key: str, decode: bool = True) -> tuple[list[Any], Any]:
        """Subscribe ``key`` on the router session; returns (list being filled, subscriber)."""
        from services.bus.messages import decode as decode_msg

        out: list[Any] = []
        lock = threading.Lock()

        def cb(sample: Any) -> None:
            payload = sample.payload.to_bytes()
            item = decode_msg(payload, str(sample.encoding)) if decode else payload
            with lock:
                out.append(item)

        sub = self.session.declare_subscriber(key, cb)
        return out, sub

    def wait_alive(self, names: set[str], timeout_s: float = 20.0) -> None:
        """Block until the liveliness tokens of ``names`` are visible (bounded)."""
        from services.bus.messages import Keys

        base = Keys("psm").liveliness_all.key[:-1]
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            seen = set()
            for reply in self.session.liveliness().get(Keys("psm").liveliness_all.key, timeout=1.0):
                with contextlib.suppress(Exception):
                    seen.add(str(reply.ok.key_expr)[len(base) :])
            if names <= seen:
                return
            time.sleep(0.1)
        raise TimeoutError(f"services {names} not alive after {timeout_s} s")

    def close(self) -> None:
        for p in self.procs:
            p.stop()
        self._logdir.cleanup()
        self.session.close()


def stop(proc: ManagedProcess, timeout_s: float = 10.0) -> int:
    """Stop a spawned process by PID (SIGTERM; stacks dumped and SIGKILL if it hangs)."""
    return proc.stop(timeout_s)


def wait_until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll ``pred`` every 20 ms for at most ``timeout_s``; fail the test on timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.02)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}")


@pytest.fixture
def bus() -> Iterator[Bus]:
    b = Bus()
    try:
        yield b
    finally:
        b.close()
