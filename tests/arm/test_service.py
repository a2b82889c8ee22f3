"""The arm process over real Zenoh on loopback: watchdog brake, limit clamps, rejected
commands, lockstep determinism (recorded with the real recorder) and bad configuration."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from services.bus.messages import ArmState, FrameTransforms, Keys, SceneUpdate, ServiceStatus
from services.robot.model import RobotModel

from .conftest import ROOT, Bus, stop, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

KEYS = Keys("psm")
LIMITS = RobotModel.load().limits


def _states(items: list) -> list[ArmState]:
    by_tick: dict[int, ArmState] = {}
    for m in list(items):
        by_tick.setdefault(m.tick, m)
    return [by_tick[k] for k in sorted(by_tick)]


def _check_limits(states: list[ArmState]) -> None:
    q = np.array([s.q for s in states])
    dq = np.array([s.dq for s in states])
    ddq = np.array([s.ddq for s in states])
    assert np.all(q >= LIMITS.lower) and np.all(q <= LIMITS.upper)
    assert np.all(np.abs(dq) <= LIMITS.velocity + 1e-9)
    assert np.all(np.abs(ddq) <= LIMITS.acceleration + 1e-9)


def test_stopped_planner_brakes_the_arm_lockstep(bus: Bus, tmp_path: Path) -> None:
    states, sub = bus.collect(KEYS.arm_state.key)
    probe = bus.spawn(
        "services.arm.probe", "--pattern", "accel", "--accel", "0,0.8,0", "--stop-after-tick", "150"
    )
    bus.wait_alive({"probe"})
    stats = tmp_path / "stats.json"
    arm = bus.spawn(
        "services.arm",
        "arm",
        "--clock",
        "lockstep",
        "--max-ticks",
        "450",
        "--set",
        "arm.lockstep_timeout_s=0.2",
        "--stats-file",
        str(stats),
    )
    arm.wait(60)
    assert arm.returncode == 0, bus.stderr(arm)
    wait_until(lambda: len(_states(states)) >= 451, 5.0, "all states")
    sub.undeclare()
    stop(probe)
    seq = _states(states)
    assert [s.tick for s in seq] == list(range(451))
    speed = np.array(
        [
            np.linalg.norm([s.ee_linear_velocity.x, s.ee_linear_velocity.y, s.ee_linear_velocity.z])
            for s in seq
        ]
    )
    # Moving under the probe's constant 0.8 m/s² until its last command (tick 149).
    assert speed[150] == pytest.approx(0.8 * 0.3, rel=0.05)
    # The last command stays valid for the 20 ms watchdog (10 ticks), never longer.
    assert not any(s.braking for s in seq[1:160])
    assert all(s.braking and s.watchdog_tripped for s in seq[161:])
    assert np.all(np.diff(speed[161:]) <= 1e-9)  # never accelerates again
    final = seq[-1]
    assert np.all(np.array(final.dq) == 0.0)
    assert speed[-1] < 1e-9
    _check_limits(seq)
    summary = json.loads(stats.read_text())
    assert summary["sim_counters"]["watchdog_trips"] == 1
    assert summary["lockstep_timeouts"] >= 1


def test_killed_planner_realtime_leaves_arm_at_rest(bus: Bus) -> None:
    states, sub = bus.collect(KEYS.arm_state.key)
    arm = bus.spawn("services.arm", "arm", "--clock", "realtime")
    probe = bus.spawn("services.arm.probe", "--pattern", "sine", "--amplitude", "0.1", "--frequency", "1.0")
    # Wait until the arm is really moving under the probe's commands.

    def moving() -> bool:
        seq = list(states)
        return bool(seq) and max(abs(v) for v in seq[-1].dq) > 0.05

    wait_until(moving, 30.0, "the arm to move")
    probe.kill()  # SIGKILL: the planner vanishes without a word
    probe.wait(5)
    n = len(states)
    wait_until(lambda: len(states) > n + 250, 10.0, "0.5 s more of states")
    seq = _states(states)
    last = seq[-1]
    assert last.braking and last.watchdog_tripped
    assert np.all(np.array(last.dq) == 0.0)
    _check_limits(seq)
    sub.undeclare()
    assert stop(arm) == 0, bus.stderr(arm)


def test_invalid_commands_rejected_counted_and_never_applied(bus: Bus, tmp_path: Path) -> None:
    states, sub = bus.collect(KEYS.arm_state.key)
    status, sub2 = bus.collect(KEYS.status("arm").key)
    stats = tmp_path / "stats.json"
    arm = bus.spawn(
        "services.arm",
        "arm",
        "--clock",
        "realtime",
        "--stats-file",
        str(stats),
        "--set",
        "status_period_s=0.2",
    )
    probe = bus.spawn("services.cli", "arm", "probe", "--pattern", "bad")  # the psm arm probe path
    wait_until(lambda: bool(states) and states[-1].rejected_commands >= 100, 30.0, "100 rejected commands")
    assert stop(probe) == 0
    wait_until(lambda: any(s.rejected > 0 for s in status), 5.0, "status with rejections")
    assert stop(arm) == 0, bus.stderr(arm)
    sub.undeclare()
    sub2.undeclare()
    seq = _states(states)
    q0 = np.array(seq[0].q)
    for s in seq:
        np.testing.assert_array_equal(np.array(s.q), q0)
        assert np.all(np.array(s.dq) == 0.0)
        assert s.braking
    counters = json.loads(stats.read_text())["sim_counters"]
    for reason in ("malformed", "non_finite", "out_of_range"):
        assert counters[f"rejected_{reason}"] > 0, counters
    assert counters.get("commands_accepted", 0) == 0
    assert isinstance(status[-1], ServiceStatus)


def test_joint_limits_clamp_over_zenoh(bus: Bus, tmp_path: Path) -> None:
    states, sub = bus.collect(KEYS.arm_state.key)
    probe = bus.spawn("services.arm.probe", "--pattern", "joint", "--joint-accel", "50,0,0,-30,0,0,0")
    bus.wait_alive({"probe"})
    stats = tmp_path / "stats.json"
    arm = bus.spawn(
        "services.arm",
        "arm",
        "--clock",
        "lockstep",
        "--max-ticks",
        "2500",
        "--start-pose",
        "home",
        "--stats-file",
        str(stats),
    )
    arm.wait(120)
    assert arm.returncode == 0, bus.stderr(arm)
    wait_until(lambda: len(_states(states)) >= 2501, 5.0, "all states")
    sub.undeclare()
    seq = _states(states)
    _check_limits(seq)
    last = seq[-1]
    # Joint 1 pushed up, joint 4 pushed down: both end at rest just inside their limits.
    assert LIMITS.upper[0] - 0.02 < last.q[0] <= LIMITS.upper[0]
    assert LIMITS.lower[3] <= last.q[3] < LIMITS.lower[3] + 0.02
    assert abs(last.dq[0]) < 1e-6 and abs(last.dq[3]) < 1e-6
    peak = np.max(np.abs([s.dq for s in seq]), axis=0)
    assert peak[0] == pytest.approx(LIMITS.velocity[0])  # the velocity limit was reached
    counters = json.loads(stats.read_text())["sim_counters"]
    assert counters["clamped_acceleration"] > 0
    assert counters["clamped_velocity"] > 0
    assert counters["clamped_position"] > 0
    assert counters.get("position_guard", 0) == 0
    stop(probe)


def _lockstep_recording(bus: Bus, out: Path, ticks: int) -> None:
    rec = bus.spawn("services.bus.cli", "record", "-o", str(out), "--overwrite")
    probe = bus.spawn("services.arm.probe", "--pattern", "sine", "--amplitude", "0.08", "--frequency", "1.5")
    bus.wait_alive({"recorder", "probe"})
    arm = bus.spawn(
        "services.arm",
        "arm",
        "--clock",
        "lockstep",
        "--max-ticks",
        str(ticks),
        "--set",
        "arm.transforms_rate_hz=50",
    )
    arm.wait(120)
    assert arm.returncode == 0, bus.stderr(arm)
    time.sleep(0.5)  # let the recorder take the last samples
    assert stop(probe) == 0
    assert stop(rec) == 0, bus.stderr(rec)


def test_lockstep_runs_are_byte_identical(bus: Bus, tmp_path: Path) -> None:
    from services.bus.log import read_samples

    ticks = 1500
    runs = []
    for i in range(2):
        out = tmp_path / f"run{i}.mcap"
        _lockstep_recording(bus, out, ticks)
        by_topic: dict[str, list[bytes]] = {}
        for s in read_samples(out, strict=True):
            if s.topic.startswith("psm/arm/") or s.topic == KEYS.arm_model.key:
                by_topic.setdefault(s.topic, []).append(s.payload)
        runs.append(by_topic)
    a, b = runs
    assert len(a[KEYS.arm_state.key]) == ticks + 1
    assert len(a[KEYS.arm_command.key]) == ticks + 1
    assert len(a[KEYS.arm_transforms.key]) == ticks // 10 + 1
    for key in (KEYS.arm_state.key, KEYS.arm_command.key, KEYS.arm_transforms.key):
        assert a[key] == b[key], key
    # The arm's 3-D model: once, latched, stamped with sim time 0, the same in both runs; its
    # links are the transforms' child frames.
    assert len(a[KEYS.arm_model.key]) == 1 and a[KEYS.arm_model.key] == b[KEYS.arm_model.key]
    model = SceneUpdate.FromString(a[KEYS.arm_model.key][0])
    tf = FrameTransforms.FromString(a[KEYS.arm_transforms.key][0])
    children = {t.child_frame_id for t in tf.transforms}
    assert len(model.entities) == 11 and {e.frame_id for e in model.entities} <= children
    assert all(e.timestamp.seconds == e.timestamp.nanos == 0 and e.models for e in model.entities)
    # The arm really moved (the comparison is not between two idle arms).
    y = [ArmState.FromString(p).ee_position.y for p in a[KEYS.arm_state.key]]
    assert max(y) - min(y) > 0.1


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "arm.dt_s=-1"], "arm.dt_s"),
        (["--clock", "lockstep", "--set", "arm.watchdog_timeout_s=0.0001"], "watchdog"),
        (["--start-pose", "nope"], "unknown pose"),
        (["--urdf", "/nonexistent.urdf"], "URDF not found"),
    ],
)
def test_bad_config_is_one_line_error(args: list[str], needle: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "services.arm", "arm", *args, "--no-multicast"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], proc.stderr


def test_lost_planner_liveliness_brakes_before_the_watchdog(bus: Bus) -> None:
    states, sub = bus.collect(KEYS.arm_state.key)
    arm = bus.spawn(
        "services.arm",
        "arm",
        "--clock",
        "realtime",
        "--set",
        "arm.watchdog_timeout_s=10",
        "--set",
        "arm.watch_services=probe",
    )
    probe = bus.spawn("services.arm.probe", "--pattern", "sine", "--amplitude", "0.1", "--frequency", "1.0")

    def moving() -> bool:
        seq = list(states)
        return bool(seq) and max(abs(v) for v in seq[-1].dq) > 0.05

    wait_until(moving, 30.0, "the arm to move")
    assert arm.poll() is None, bus.stderr(arm)
    assert stop(probe) == 0  # graceful: its liveliness token goes away
    t_stop = time.monotonic()
    # With a 10 s watchdog (the maximum) only the liveliness loss can stop the arm this quickly
    # (the margin is for a loaded machine; unloaded it takes well under a second).
    wait_until(lambda: states[-1].braking and not any(states[-1].dq), 6.0, "the arm at rest")
    assert time.monotonic() - t_stop < 6.0
    _check_limits(_states(states))
    sub.undeclare()
    assert stop(arm) == 0, bus.stderr(arm)
