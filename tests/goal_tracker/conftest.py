"""Fixtures of the goal tracker's integration tests (helpers in ``gt_procs``)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.supervisor import free_port

from .gt_procs import Procs, wait_until


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[Procs]:
    """A Zenoh router on 127.0.0.1:<free port> plus a process starter; all stopped at the end."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = Procs(tmp_path, endpoint)
    router = procs.start(
        "router", "services.bus.cli", "serve", "router", "--listen", endpoint, "--no-multicast"
    )

    def listening() -> bool:
        if router.poll() is not None:
            pytest.fail(f"router exited: {procs.log(router)}")
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", port)) == 0

    wait_until(listening, 20.0, "the router to listen")
    try:
        yield procs
    finally:
        procs.stop_all()


@pytest.fixture
def session(bus: Procs) -> Iterator[object]:
    """A Zenoh client session of the test process, on the test router."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{bus.endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(conf)
    try:
        yield s
    finally:
        s.close()
