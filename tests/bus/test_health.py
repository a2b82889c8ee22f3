"""The health file (``health_file``) a container healthcheck tests: rewritten at every status
period while the service runs and its client session reaches a router, left to age while the
router is gone, removed at exit."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import pytest

from services.supervisor import free_port

from .helpers import Proc, port_open, wait_for

pytestmark = [pytest.mark.integration]


def _age_s(path: Path) -> float:
    return time.time() - path.stat().st_mtime if path.exists() else float("inf")


def test_the_health_file_follows_the_router_connection(procs: Callable[..., Proc], tmp_path: Path) -> None:
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router_args = ["-m", "services.bus.cli", "serve", "router", "--listen", ep, "--no-multicast"]
    router = procs(router_args, "router")
    assert wait_for(lambda: port_open(port), 15.0), router.stderr()
    health = tmp_path / "health"
    echo = procs(["-m", "services.bus.cli", "echo", "--connect", ep, "--mode", "client", "--no-multicast"],
                 "echo", {"PSM_HEALTH_FILE": str(health), "PSM_STATUS_PERIOD_S": "0.2"})
    assert wait_for(lambda: _age_s(health) < 0.5, 20.0), echo.stderr()
    assert '"service": "echo"' in health.read_text()

    router.stop()
    time.sleep(1.5)
    assert echo.alive()
    assert _age_s(health) > 1.0, "the health file is still rewritten without a router"

    router = procs(router_args, "router2")
    assert wait_for(lambda: _age_s(health) < 0.5, 30.0), "not healthy again after the router came back"

    echo.stop()
    assert not health.exists()
