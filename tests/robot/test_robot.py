"""The shared robot package: quaternion helpers against Pinocchio, the protocol's builders and
parsers (round trips), and the import boundary (the protocol loads neither Pinocchio nor the
arm simulator)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from services.bus.messages import ArmCommand
from services.robot import (
    ArmStateData,
    CommandMode,
    CommandRejectedError,
    EEState,
    RobotModel,
    cartesian_command,
    command_from_message,
    frame_transforms,
    joint_command,
    matrix_from_quat_xyzw,
    quat_xyzw_from_matrix,
    state_from_message,
    state_message,
)


def _pin_quat(R: np.ndarray) -> np.ndarray:
    q = pin.Quaternion(R)
    q.normalize()
    c = np.array([q.x, q.y, q.z, q.w])
    return -c if c[3] < 0 else c


def test_quaternions_match_pinocchio() -> None:
    rng = np.random.default_rng(7)
    Rs = np.stack([pin.exp3(rng.normal(size=3) * 2.0) for _ in range(200)])
    Q = quat_xyzw_from_matrix(Rs)
    assert Q.shape == (200, 4) and np.all(Q[:, 3] >= 0)
    for R, q in zip(Rs, Q, strict=True):
        np.testing.assert_allclose(q, _pin_quat(R), atol=1e-12)
        np.testing.assert_allclose(quat_xyzw_from_matrix(R), q, atol=0)
        np.testing.assert_allclose(matrix_from_quat_xyzw(q), R, atol=1e-12)
        # Not normalised, sign flipped: the same rotation.
        np.testing.assert_allclose(matrix_from_quat_xyzw(-2.5 * q), R, atol=1e-12)
        ref = pin.Quaternion(q[3], q[0], q[1], q[2]).toRotationMatrix()
        np.testing.assert_allclose(matrix_from_quat_xyzw(q), ref, atol=1e-12)
    for bad in ([0.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 1.0], [np.inf, 0.0, 0.0, 1.0]):
        with pytest.raises(ValueError, match="norm"):
            matrix_from_quat_xyzw(bad)


def _state(n: int = 7) -> ArmStateData:
    rng = np.random.default_rng(1)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    q = q if q[3] >= 0 else -q
    ee = EEState(rng.normal(size=3), q, matrix_from_quat_xyzw(q), *(rng.normal(size=3) for _ in range(4)))
    return ArmStateData(
        tick=42, time_ns=84_000_000, stamp_ns=84_000_000,
        q=rng.normal(size=n), dq=rng.normal(size=n), ddq=rng.normal(size=n), ee=ee,
        braking=True, watchdog_tripped=True, rejected_commands=3,
        joint_names=tuple(f"j{i}" for i in range(n)), frame_id="base", dt_s=0.002,
    )


def test_matrix_from_quaternion_is_scipys() -> None:
    """The closed-form conversion (the arm runs it every tick) equals scipy's to the last bits:
    the same operations in the same order, but scipy's compiled path may contract them into
    fused multiply-adds on a CPU that has them (seen: up to 3.3e-16 apart)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    for i in range(2000):
        q = rng.normal(size=4) * (1.0 if i % 2 else 1e-3)
        if i % 3 == 0:
            q /= np.linalg.norm(q)
        n = float(np.sqrt(q @ q))
        np.testing.assert_allclose(matrix_from_quat_xyzw(q), Rotation.from_quat(q / n).as_matrix(),
                                   rtol=0.0, atol=4 * np.finfo(float).eps)


def test_state_round_trip() -> None:
    s = _state()
    msg = state_message(s, s.joint_names, s.frame_id, s.dt_s, watchdog_tripped=True, rejected_commands=3)
    back = state_from_message(type(msg).FromString(msg.SerializeToString()))
    for name in ("tick", "time_ns", "stamp_ns", "braking", "watchdog_tripped", "rejected_commands",
                 "joint_names", "frame_id", "dt_s"):
        assert getattr(back, name) == getattr(s, name), name
    for name in ("q", "dq", "ddq"):
        np.testing.assert_array_equal(getattr(back, name), getattr(s, name))
    for name in ("position", "quat_xyzw", "linear_velocity", "angular_velocity", "linear_acceleration",
                 "angular_acceleration"):
        np.testing.assert_array_equal(getattr(back.ee, name), getattr(s.ee, name))
    np.testing.assert_allclose(back.ee.rotation, s.ee.rotation, atol=1e-12)
    # An ArmStateData is itself a StateLike: encoding it again gives the same message.
    assert state_message(back, back.joint_names, back.frame_id, back.dt_s, watchdog_tripped=True,
                         rejected_commands=3) == msg
    bad = type(msg)()
    bad.CopyFrom(msg)
    del bad.dq[-1]
    with pytest.raises(ValueError, match="q, dq, ddq"):
        state_from_message(bad)


def test_commands_round_trip() -> None:
    s = _state()
    msg = state_message(s, s.joint_names, s.frame_id, s.dt_s)
    c = command_from_message(cartesian_command(msg, [0.1, -0.2, 0.3], [0.0, 0.0, 0.0, 1.0], [0.0, 0.5, 0.0]))
    assert c.tick == 42 and c.mode is CommandMode.CARTESIAN
    np.testing.assert_array_equal(c.linear_acceleration, [0.1, -0.2, 0.3])
    np.testing.assert_array_equal(c.orientation_xyzw, [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(c.angular_velocity, [0.0, 0.5, 0.0])
    c = command_from_message(cartesian_command(msg, [0.0, 0.0, 1.0]))
    assert c.orientation_xyzw is None and c.angular_velocity is None
    j = command_from_message(joint_command(msg, range(7), seq=5, source="t"))
    assert j.mode is CommandMode.JOINT
    np.testing.assert_array_equal(j.joint_acceleration, np.arange(7.0))
    with pytest.raises(CommandRejectedError) as err:
        command_from_message(ArmCommand(tick=1))
    assert err.value.reason == "malformed"


def test_frame_transforms_match_the_link_placements() -> None:
    robot = RobotModel.load()
    frames = robot.body_frame_ids()
    rng = np.random.default_rng(7)
    poses = rng.uniform(robot.limits.lower, robot.limits.upper, (20, robot.n))
    for q in [robot.resolve_pose("ready"), *poses]:
        robot.fk(q)
        tf = frame_transforms(robot, frames, 1_500_000_001, "base")
        placements = {robot.model.frames[f].name: robot.data.oMf[f] for f in frames}
        assert len(tf.transforms) == len([n for n in placements if n != "base"])
        for t in tf.transforms:
            M = placements[t.child_frame_id]
            assert t.parent_frame_id == "base"
            assert t.timestamp.seconds == 1 and t.timestamp.nanos == 500_000_001
            np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z], M.translation)
            r = t.rotation
            assert r.w >= 0.0
            # scipy as the independent reference (the transforms use Pinocchio's conversion)
            ref = Rotation.from_matrix(M.rotation).as_quat()
            ref = -ref if ref[3] < 0 else ref
            np.testing.assert_allclose([r.x, r.y, r.z, r.w], ref, atol=1e-12)


def test_protocol_imports_neither_pinocchio_nor_the_arm() -> None:
    code = (
        "import sys; from services.robot import cartesian_command, state_from_message, Command; "
        "import services.robot.protocol; "
        "print(sorted(m for m in sys.modules if m == 'pinocchio' or m.startswith('services.arm')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_robot_with_own_data_shares_the_model_not_the_state() -> None:
    robot = RobotModel.load()
    other = robot.with_own_data()
    assert other.model is robot.model and other.data is not robot.data
    q0, q1 = robot.resolve_pose("ready"), robot.resolve_pose("home")
    robot.update(q0, np.zeros(robot.n))
    J0 = robot.jacobian().copy()
    other.update(q1, np.zeros(robot.n))
    assert np.array_equal(robot.jacobian(), J0)  # untouched by the other's update
    assert not np.allclose(other.jacobian(), J0)
