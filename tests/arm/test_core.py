"""Bus-free tests of the arm core: kinematics against Pinocchio, the IK controller, limits,
watchdog brake and command validation."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.arm.controller import (
    ClampReport,
    ValidationLimits,
    clamp_joint_accel,
    validate_command,
)
from services.arm.sim import ArmSim, ArmSimConfig
from services.robot.model import RobotModel, panda_urdf_path
from services.robot.protocol import Command, CommandMode, CommandRejectedError
from services.robot.rotations import matrix_from_quat_xyzw, quat_xyzw_from_matrix


@pytest.fixture(scope="module")
def full_panda() -> tuple[pin.Model, pin.Data]:
    """Independent reference: the unreduced Panda (9 joints incl. fingers)."""
    m = pin.buildModelFromUrdf(str(panda_urdf_path()))
    return m, m.createData()


def _random_q(robot: RobotModel, rng: np.random.Generator) -> np.ndarray:
    lo, hi = robot.limits.lower, robot.limits.upper
    return lo + (hi - lo) * rng.uniform(0.1, 0.9, robot.n)


def test_model_is_reduced_panda(robot: RobotModel) -> None:
    assert robot.n == 7
    assert robot.ee_frame == "panda_hand_tcp"
    assert robot.joint_names[0] == "panda_joint1" and robot.joint_names[-1] == "panda_joint7"
    assert np.all(robot.limits.acceleration > 0)
    p, R = robot.fk(robot.resolve_pose("ready"))
    # SRDF ready pose: hand 0.307 m in front of the base, pointing down.
    np.testing.assert_allclose(p, [0.307, 0.0, 0.487], atol=2e-3)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-3)


def test_fk_matches_full_pinocchio_model(robot: RobotModel, full_panda) -> None:
    m, d = full_panda
    fid = m.getFrameId("panda_hand_tcp")
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = _random_q(robot, rng)
        pin.framesForwardKinematics(m, d, np.concatenate([q, [0.0, 0.0]]))
        p, R = robot.fk(q)
        np.testing.assert_allclose(p, d.oMf[fid].translation, atol=1e-12)
        np.testing.assert_allclose(R, d.oMf[fid].rotation, atol=1e-12)
    Q = np.array([_random_q(robot, rng) for _ in range(5)])
    np.testing.assert_allclose(robot.fk_positions(Q), [robot.fk(q)[0] for q in Q], atol=1e-12)


def test_jacobian_and_drift_match_full_pinocchio_model(robot: RobotModel, full_panda) -> None:
    m, d = full_panda
    fid = m.getFrameId("panda_hand_tcp")
    rng = np.random.default_rng(4)
    for _ in range(10):
        q = _random_q(robot, rng)
        dq = rng.uniform(-1.0, 1.0, robot.n)
        qf, vf = np.concatenate([q, [0.0, 0.0]]), np.concatenate([dq, [0.0, 0.0]])
        J_ref = pin.computeFrameJacobian(m, d, qf, fid, pin.LOCAL_WORLD_ALIGNED)[:, :7]
        pin.forwardKinematics(m, d, qf, vf, np.zeros(m.nv))
        a_ref = pin.getFrameClassicalAcceleration(m, d, fid, pin.LOCAL_WORLD_ALIGNED).vector
        robot.update(q, dq)
        np.testing.assert_allclose(robot.jacobian(), J_ref, atol=1e-12)
        np.testing.assert_allclose(robot.drift(), a_ref, atol=1e-10)


def test_jacobian_and_drift_match_finite_differences(robot: RobotModel) -> None:
    rng = np.random.default_rng(2)
    q = _random_q(robot, rng)
    dq = rng.uniform(-0.5, 0.5, robot.n)
    robot.update(q, dq)
    J = robot.jacobian().copy()
    drift = robot.drift().copy()
    v = robot.ee_velocity().copy()
    np.testing.assert_allclose(v, J @ dq, atol=1e-12)
    # Position second derivative along q(t) = q + dq t (zero joint acceleration) is J̇q̇.
    h = 1e-4
    p = [robot.fk(q + dq * t)[0] for t in (-h, 0.0, h)]
    acc_fd = (p[0] - 2 * p[1] + p[2]) / h**2
    np.testing.assert_allclose(drift[:3], acc_fd, atol=1e-5)


def test_ik_solver_reaches_target(robot: RobotModel) -> None:
    target = np.array([0.45, 0.2, 0.3])
    q = robot.solve_ik(target)
    p, R = robot.fk(q)
    np.testing.assert_allclose(p, target, atol=1e-5)
    assert robot.limits.contains(q)
    # The default keeps the ready pose's orientation (hand down).
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-4)
    with pytest.raises(ValueError, match="IK did not converge"):
        robot.solve_ik(np.array([3.0, 0.0, 0.0]), iters=50)


def test_quaternion_roundtrip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        R = pin.exp3(rng.normal(size=3))
        qx = quat_xyzw_from_matrix(R)
        assert qx[3] >= 0
        np.testing.assert_allclose(matrix_from_quat_xyzw(qx), R, atol=1e-12)


@pytest.mark.parametrize("dt_ns", [2_000_000, 1_000_000])
def test_constant_cartesian_acceleration_is_produced(robot: RobotModel, dt_ns: int) -> None:
    sim = ArmSim(robot, ArmSimConfig(dt_s=dt_ns * 1e-9, start_pose="ready"))
    a = np.array([0.4, -0.3, 0.5])
    start = sim.snapshot().ee.position
    T = 0.4
    steps = round(T / sim.dt)
    for _ in range(steps):
        assert sim.submit(Command(sim.tick, CommandMode.CARTESIAN, a))
        s = sim.step()
        assert not s.braking
    # Measured (Pinocchio classical) acceleration at the end, and kinematic consistency.
    np.testing.assert_allclose(s.ee.linear_acceleration, a, atol=0.01 * np.linalg.norm(a))
    np.testing.assert_allclose(s.ee.linear_velocity, a * T, atol=0.01)
    np.testing.assert_allclose(s.ee.position - start, 0.5 * a * T**2, atol=2e-3)
    assert sim.controller.last_damping == 0.0
    assert sim.counters["clamped_acceleration"] == 0


def test_orientation_converges(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig(start_pose="ready"))
    R0 = sim.snapshot().ee.rotation
    R_ref = pin.exp3(np.array([0.3, -0.2, 0.25])) @ R0
    quat = quat_xyzw_from_matrix(R_ref)
    p0 = sim.snapshot().ee.position
    for _ in range(1000):  # 2 s of sim time
        vel = sim.snapshot().ee.linear_velocity
        pos = sim.snapshot().ee.position
        hold = 100.0 * (p0 - pos) - 20.0 * vel  # PD on position, so only orientation changes
        sim.submit(Command(sim.tick, CommandMode.CARTESIAN, hold, quat))
        sim.step()
    R = sim.snapshot().ee.rotation
    assert np.linalg.norm(pin.log3(R_ref @ R.T)) < 1e-3
    assert np.linalg.norm(sim.snapshot().ee.angular_velocity) < 1e-2
    np.testing.assert_allclose(sim.snapshot().ee.position, p0, atol=1e-3)


def test_orientation_held_without_reference(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig(start_pose="home"))
    R0 = sim.snapshot().ee.rotation
    for _ in range(300):
        sim.submit(Command(sim.tick, CommandMode.CARTESIAN, np.array([0.0, 0.5, 0.0])))
        sim.step()
    assert np.linalg.norm(pin.log3(sim.snapshot().ee.rotation @ R0.T)) < 5e-3


def test_damped_least_squares_near_singularity(robot: RobotModel) -> None:
    # Stretched-out arm: joint 4 near its upper limit (-0.07 rad) is close to the elbow
    # singularity; the damping must engage and keep joint accelerations bounded.
    q = np.array([0.0, 0.3, 0.0, -0.08, 0.0, 1.0, 0.8])
    sim = ArmSim(robot, ArmSimConfig(start_pose=list(q)))
    for _ in range(100):
        sim.submit(Command(sim.tick, CommandMode.CARTESIAN, np.array([5.0, 0.0, 0.0])))
        s = sim.step()
        assert np.all(np.abs(s.ddq) <= robot.limits.acceleration + 1e-9)
        assert np.all(np.isfinite(s.q))
    assert sim.controller.last_damping > 0.0


def test_joint_acceleration_mode(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig(start_pose="home"))
    ddq = np.array([0.5, -0.3, 0.2, 0.4, -0.1, 0.3, 0.6])
    for _ in range(50):
        sim.submit(Command(sim.tick, CommandMode.JOINT, joint_acceleration=ddq))
        s = sim.step()
    np.testing.assert_allclose(s.ddq, ddq)
    np.testing.assert_allclose(s.dq, ddq * 50 * sim.dt, atol=1e-12)


def test_watchdog_brakes_to_zero_velocity(robot: RobotModel) -> None:
    cfg = ArmSimConfig(start_pose="home", watchdog_timeout_s=0.02)
    sim = ArmSim(robot, cfg)
    a = np.array([0.0, 1.0, 0.0])
    for _ in range(100):
        sim.submit(Command(sim.tick, CommandMode.CARTESIAN, a))
        sim.step()
    v_before = np.linalg.norm(sim.snapshot().ee.linear_velocity)
    assert v_before > 0.15
    last_tick = sim.tick
    # No further commands: the held command is used for 20 ms of sim time (10 ticks), then brake.
    speeds = []
    for _ in range(300):
        s = sim.step()
        speeds.append(np.linalg.norm(s.dq))
        assert np.all(np.abs(s.ddq) <= robot.limits.acceleration + 1e-9)
        assert robot.limits.contains(s.q, s.dq)
    assert (sim.tick - last_tick) * cfg.dt_ns > cfg.watchdog_timeout_ns
    assert sim.counters["watchdog_trips"] == 1
    assert s.braking
    assert speeds[-1] == 0.0
    # Never kept integrating the last acceleration: speed is monotone once braking starts.
    brake_start = cfg.watchdog_timeout_ns // cfg.dt_ns + 1
    assert np.all(np.diff(speeds[brake_start:]) <= 1e-12)
    assert sim.command_fresh() is False
    # A fresh command resumes control.
    assert sim.submit(Command(sim.tick, CommandMode.CARTESIAN, a))
    assert not sim.step().braking


def test_starts_braked_without_commands(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig(start_pose="ready"))
    q0 = sim.snapshot().q
    for _ in range(20):
        s = sim.step()
    assert s.braking
    np.testing.assert_array_equal(s.q, q0)


@pytest.mark.parametrize(
    ("cmd", "reason"),
    [
        (Command(0, CommandMode.CARTESIAN, np.array([np.nan, 0, 0])), "non_finite"),
        (Command(0, CommandMode.CARTESIAN, np.array([np.inf, 0, 0])), "non_finite"),
        (Command(0, CommandMode.CARTESIAN, np.array([0.0, 0.0])), "malformed"),
        (Command(0, CommandMode.CARTESIAN, None), "malformed"),
        (Command(0, CommandMode.CARTESIAN, np.array([100.0, 0, 0])), "out_of_range"),
        # Squares that overflow: finite values, so out of range (not non-finite).
        (Command(0, CommandMode.CARTESIAN, np.array([1e200, 0, 0])), "out_of_range"),
        (Command(0, CommandMode.CARTESIAN, np.array([1e200, np.nan, 0])), "non_finite"),
        (
            Command(0, CommandMode.CARTESIAN, np.zeros(3), np.array([0.0, 0.0, np.inf, 1.0])),
            "non_finite",
        ),
        (
            Command(0, CommandMode.CARTESIAN, np.zeros(3), np.array([0.0, 0.0, 0.0, 0.0])),
            "out_of_range",
        ),
        (
            Command(0, CommandMode.CARTESIAN, np.zeros(3), None, np.array([0, 0, 50.0])),
            "out_of_range",
        ),
        (Command(0, CommandMode.JOINT, joint_acceleration=np.zeros(6)), "malformed"),
        (Command(0, CommandMode.JOINT, joint_acceleration=np.full(7, 1e3)), "out_of_range"),
        (Command(0, CommandMode.JOINT, joint_acceleration=["a"] * 7), "malformed"),
        (Command(-1, CommandMode.JOINT, joint_acceleration=np.zeros(7)), "malformed"),
    ],
)
def test_invalid_commands_rejected_and_not_applied(robot: RobotModel, cmd, reason) -> None:
    with pytest.raises(CommandRejectedError) as info:
        validate_command(cmd, robot.n, ValidationLimits())
    assert info.value.reason == reason
    sim = ArmSim(robot, ArmSimConfig(start_pose="home"))
    q0 = sim.snapshot().q
    assert not sim.submit(cmd)
    assert sim.counters["rejected"] == 1
    assert sim.counters[f"rejected_{reason}"] == 1
    s = sim.step()
    np.testing.assert_array_equal(s.q, q0)
    np.testing.assert_array_equal(s.dq, np.zeros(robot.n))


def test_future_and_stale_commands(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig())
    assert not sim.submit(Command(5, CommandMode.JOINT, joint_acceleration=np.zeros(7)))
    assert sim.counters["rejected_tick"] == 1
    for _ in range(3):
        sim.step()
    assert sim.submit(Command(2, CommandMode.JOINT, joint_acceleration=np.zeros(7)))
    assert not sim.submit(Command(1, CommandMode.JOINT, joint_acceleration=np.ones(7)))
    assert sim.counters["stale"] == 1


def test_commands_in_flight_when_the_planner_is_lost_are_refused(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig(start_pose="home"))
    a = np.array([0.0, 1.0, 0.0])
    for _ in range(50):
        assert sim.submit(Command(sim.tick, CommandMode.CARTESIAN, a))
        sim.step()
    lost_at = sim.tick
    sim.drop_command()  # the planner's liveliness token is gone
    # Its last commands arrive afterwards: answering states up to the current tick, refused.
    assert not sim.submit(Command(lost_at, CommandMode.CARTESIAN, a))
    assert not sim.submit(Command(lost_at - 1, CommandMode.CARTESIAN, a))
    assert sim.counters["stale"] == 2
    s = sim.step()
    assert s.braking
    for _ in range(200):
        s = sim.step()
    assert not np.any(s.dq)
    # A (restarted) planner answering a state published after the loss takes control again.
    assert sim.submit(Command(sim.tick, CommandMode.CARTESIAN, a))
    assert not sim.step().braking


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    scale=st.floats(0.5, 60.0),
    dt_ns=st.sampled_from([1_000_000, 2_000_000]),
)
def test_limits_never_exceeded_under_random_joint_commands(seed: int, scale: float, dt_ns: int):
    robot = _ROBOT
    rng = np.random.default_rng(seed)
    sim = ArmSim(robot, ArmSimConfig(dt_s=dt_ns * 1e-9, start_pose="home"))
    lim = robot.limits
    ddq = rng.uniform(-1, 1, robot.n) * scale
    for k in range(400):
        if k % 40 == 0:
            ddq = rng.uniform(-1, 1, robot.n) * scale
        sim.submit(Command(sim.tick, CommandMode.JOINT, joint_acceleration=ddq))
        s = sim.step()
        assert np.all(s.q >= lim.lower) and np.all(s.q <= lim.upper)
        assert np.all(np.abs(s.dq) <= lim.velocity + 1e-9)
        assert np.all(np.abs(s.ddq) <= lim.acceleration + 1e-9)
    assert sim.counters["position_guard"] == 0


_ROBOT = RobotModel.load()


def test_position_limit_clamp_stops_before_limit(robot: RobotModel) -> None:
    sim = ArmSim(robot, ArmSimConfig(start_pose="home"))
    push = np.zeros(robot.n)
    push[0] = 15.0  # joint 1 at its acceleration limit toward +2.8973 rad
    for _ in range(3000):
        sim.submit(Command(sim.tick, CommandMode.JOINT, joint_acceleration=push))
        s = sim.step()
        assert s.q[0] <= robot.limits.upper[0]
        assert abs(s.dq[0]) <= robot.limits.velocity[0] + 1e-9
    assert s.q[0] > robot.limits.upper[0] - 0.01
    assert abs(s.dq[0]) < 1e-6
    assert sim.counters["clamped_velocity"] > 0 and sim.counters["clamped_position"] > 0
    assert sim.counters["position_guard"] == 0


def test_clamp_scales_acceleration_uniformly(robot: RobotModel) -> None:
    q = robot.resolve_pose("home")
    ddq = robot.limits.acceleration * np.linspace(-3, 3, robot.n)
    report = ClampReport()
    out = clamp_joint_accel(ddq, q, np.zeros(robot.n), robot.limits, 0.002, report)
    assert report.acceleration and not report.position
    assert np.max(np.abs(out) / robot.limits.acceleration) == pytest.approx(1.0)
    # Direction preserved.
    np.testing.assert_allclose(out / np.linalg.norm(out), ddq / np.linalg.norm(ddq))


def test_custom_urdf_and_errors(tmp_path) -> None:
    robot = RobotModel.load(
        panda_urdf_path(),
        ee_frame="panda_link8",
        locked_joints=["panda_finger_joint1", "panda_finger_joint2"],
        accel_limits=5.0,
    )
    assert robot.ee_frame == "panda_link8"
    np.testing.assert_array_equal(robot.limits.acceleration, np.full(7, 5.0))
    with pytest.raises(ValueError, match="frame"):
        RobotModel.load(panda_urdf_path(), ee_frame="nope", locked_joints=[])
    with pytest.raises(FileNotFoundError):
        RobotModel.load(tmp_path / "missing.urdf")
    with pytest.raises(ValueError, match="unknown pose"):
        robot.resolve_pose("nope")
    with pytest.raises(ValueError, match="outside"):
        robot.resolve_pose([5.0] * 7)


def test_signal_safe_inbox() -> None:
    """Signals hammering the arm's timed waits never turn them into unbounded ones: the loop
    still sees SIGTERM (``queue.SimpleQueue.get(timeout)`` on CPython 3.11 can block for ever
    after an interrupt near its deadline; that hung the arm at shutdown about once in ten)."""
    child = subprocess.Popen(
        [sys.executable, "-m", "tests.arm.signal_wait_child"],
        cwd=Path(__file__).resolve().parents[2], stdout=subprocess.PIPE, text=True,
    )
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "ready"
        rng = np.random.default_rng(7)
        for _ in range(400):
            child.send_signal(signal.SIGUSR1)
            time.sleep(float(rng.uniform(0.0, 0.001)))
        child.send_signal(signal.SIGTERM)
        assert child.wait(5) == 0
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(5)
