"""Fixtures for the bus tests (helpers live in :mod:`helpers`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from services.supervisor import free_port

from .helpers import Proc, port_open, wait_for


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Callable[..., Proc]]:
    """Factory starting processes that are stopped (by PID) at teardown."""
    started: list[Proc] = []

    def start(args: list[str], name: str, env: dict | None = None) -> Proc:
        p = Proc(args, tmp_path, name, env)
        started.append(p)
        return p

    yield start
    for p in reversed(started):
        p.stop()


@pytest.fixture
def router(procs: Callable[..., Proc]) -> Iterator[str]:
    """A ``psm serve router`` process on a free loopback port; yields its endpoint."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    p = procs(["-m", "services.bus.cli", "serve", "router", "--listen", ep, "--no-multicast"],
              "router")
    ok = wait_for(lambda: port_open(port) or not p.alive(), 15.0)
    assert ok and p.alive(), f"router did not start: {p.stderr()}"
    yield ep
