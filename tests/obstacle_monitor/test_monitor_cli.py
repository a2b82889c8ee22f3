"""``psm obstacle add|move|remove`` against a running ``psm obstacles`` over real Zenoh: the
latched set follows the commands, a bad command is rejected and counted, the monitor keeps
running; a bad start config is one error line."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from services.supervisor import ManagedProcess, free_port, psm_argv, wait_port

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def _bus(port: int, prefix: str) -> list[str]:
    return ["--mode", "client", "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast", "--prefix", prefix]


def _run(args: list[str], timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(psm_argv(args), cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def test_commands_change_the_latched_set_and_bad_ones_are_counted(tmp_path: Path) -> None:
    import zenoh

    from services.bus.messages import Keys, ObstacleSet, ServiceStatus

    port = free_port()
    prefix = f"obst{port}"
    router = ManagedProcess(
        "router", psm_argv(["serve", "router", "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast"]),
        tmp_path / "router.log",
    )
    monitor = None
    session = None
    try:
        wait_port(port, 60, router)
        monitor = ManagedProcess(
            "monitor",
            psm_argv(["obstacles", *_bus(port, prefix), "--set", "obstacle_monitor.clearance=false"]),
            tmp_path / "monitor.log",
        )
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        deadline = time.monotonic() + 60
        while session is None:
            try:
                session = zenoh.open(conf)
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        keys = Keys(prefix)
        sets: list[ObstacleSet] = []
        status: list[ServiceStatus] = []
        session.declare_subscriber(
            keys.obstacles.key, lambda s: sets.append(ObstacleSet.FromString(s.payload.to_bytes()))
        )
        session.declare_subscriber(
            keys.status("obstacle_monitor").key,
            lambda s: status.append(ServiceStatus.FromString(s.payload.to_bytes())),
        )
        deadline = time.monotonic() + 60
        while not status and time.monotonic() < deadline:
            time.sleep(0.1)
        assert status, monitor.log_text()

        def ids() -> list[str]:
            return [o.id for o in sets[-1].obstacles] if sets else []

        def wait_for(pred: Any) -> None:
            end = time.monotonic() + 15
            while not pred() and time.monotonic() < end:
                time.sleep(0.05)

        add = ["obstacle", "add", "post", "--shape", "sphere", "--size", "0.08",
               "--position", "0.4", "0.2", "0.5"]
        r = _run([*add, *_bus(port, prefix)])
        assert r.returncode == 0, r.stderr
        wait_for(lambda: ids() == ["post"])
        assert ids() == ["post"]
        assert sets[-1].obstacles[0].size.x == pytest.approx(0.08)
        r = _run([*add, *_bus(port, prefix)])  # duplicate id: rejected by the monitor
        assert r.returncode == 0
        r = _run(["obstacle", "move", "post", "--position", "0.3", "0.1", "0.5", *_bus(port, prefix)])
        assert r.returncode == 0, r.stderr
        wait_for(lambda: bool(sets) and abs(sets[-1].obstacles[0].position.x - 0.3) < 1e-9)
        assert sets[-1].obstacles[0].position.x == pytest.approx(0.3)
        assert sets[-1].obstacles[0].size.x == pytest.approx(0.08)  # MOVE keeps the size
        r = _run(["obstacle", "remove", "post", *_bus(port, prefix)])
        assert r.returncode == 0, r.stderr
        wait_for(lambda: bool(sets) and ids() == [])
        assert ids() == []
        n = len(status)
        wait_for(lambda: len(status) > n + 1)
        assert status[-1].rejected == 1 and "duplicate_id" in status[-1].last_error, status[-1]
        assert monitor.poll() is None  # it keeps running
    finally:
        if session is not None:
            session.close()
        if monitor is not None:
            monitor.stop()
        router.stop()


def test_a_bad_command_line_or_start_set_is_one_error_line(tmp_path: Path) -> None:
    r = _run(["obstacle", "add", "x", "--shape", "box", "--size", "0.1", "--position", "0", "0", "0"])
    assert r.returncode == 2 and "error: --size: a box takes 3 value(s)" in r.stderr
    assert "Traceback" not in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text(
        '[[obstacles]]\nid = "w"\nshape = "box"\nposition_m = [0, 0, 0]\nsize_m = [0.1, -1, 0.1]\n'
    )
    r = _run(["obstacles", "--set", f'obstacle_monitor.obstacles_file="{bad}"'])
    assert r.returncode == 2 and "size" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
