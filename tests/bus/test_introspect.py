"""``psm status`` and ``psm topics`` against real services on a loopback router."""

from __future__ import annotations

import threading
import time

import pytest

from services.bus.messages import ArmState
from services.bus.runtime import Service

from .helpers import bus_args, client_config, run_psm

pytestmark = pytest.mark.integration


def _client(router: str) -> list[str]:
    return [*bus_args(router)[:-2], "--mode", "client"]


def test_status_lists_alive_services_with_their_status(router: str) -> None:
    svc = Service("statusprobe", client_config(router)).start()
    try:
        time.sleep(0.5)
        r = run_psm("status", *_client(router), "--wait", "2")
    finally:
        svc.close()
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stdout.splitlines() if "statusprobe" in ln)
    assert "yes" in line and "RUNNING" in line, r.stdout
    assert "router" in r.stdout  # the router process is a service too


def test_status_with_nothing_alive_exits_1(router: str) -> None:
    r = run_psm("status", *_client(router), "--prefix", "emptycell", "--wait", "0.5")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "0 alive" in r.stdout


def test_topics_reports_type_rate_and_bandwidth(router: str) -> None:
    svc = Service("topicsprobe", client_config(router)).start()
    pub = svc.publisher(svc.keys.arm_state)
    stop = threading.Event()

    def publish() -> None:
        k = 0
        while not stop.wait(0.01):  # ~100 Hz
            pub.put(ArmState(stamp_ns=k * 10_000_000, tick=k, q=[0.0] * 7))
            k += 1

    th = threading.Thread(target=publish, daemon=True)
    th.start()
    try:
        time.sleep(0.5)
        r = run_psm("topics", *_client(router), "--window", "2")
    finally:
        stop.set()
        th.join(5)
        svc.close()
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stdout.splitlines() if "psm/arm/state" in ln)
    assert "psm.ArmState" in line, line
    rate = float(line.split("│")[3])
    assert 50 < rate < 150, line  # ~100 Hz on a loaded 2-core machine
    assert "B/s" in line
