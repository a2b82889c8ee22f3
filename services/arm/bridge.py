"""Conversions between the arm core (numpy) and the bus messages of :mod:`services.bus.messages`.

Kept free of Zenoh so the teach mode (which writes MCAP directly) and the service share them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf.timestamp_pb2 import Timestamp

from services.arm.controller import Command, CommandMode, CommandRejectedError
from services.arm.robot import RobotModel, quat_xyzw_from_matrix
from services.arm.sim import ArmSnapshot
from services.bus.messages import ArmCommand, ArmState, FrameTransforms


def _set3(v: object, a: Sequence[float] | np.ndarray) -> None:
    v.x, v.y, v.z = float(a[0]), float(a[1]), float(a[2])  # type: ignore[attr-defined]


def state_message(
    snap: ArmSnapshot,
    joint_names: Sequence[str],
    frame_id: str,
    dt_s: float,
    *,
    watchdog_tripped: bool = False,
    rejected_commands: int = 0,
) -> ArmState:
    """The :class:`ArmState` of a snapshot. ``stamp_ns`` is the sim time (deterministic)."""
    ee = snap.ee
    msg = ArmState(
        stamp_ns=snap.time_ns,
        tick=snap.tick,
        sim_time_ns=snap.time_ns,
        joint_names=joint_names,
        q=snap.q.tolist(),
        dq=snap.dq.tolist(),
        ddq=snap.ddq.tolist(),
        frame_id=frame_id,
        braking=snap.braking,
        watchdog_tripped=watchdog_tripped,
        rejected_commands=min(rejected_commands, 2**32 - 1),
        dt_s=dt_s,
    )
    _set3(msg.ee_position, ee.position)
    o = msg.ee_orientation
    o.x, o.y, o.z, o.w = (float(c) for c in ee.quat_xyzw)
    _set3(msg.ee_linear_velocity, ee.linear_velocity)
    _set3(msg.ee_angular_velocity, ee.angular_velocity)
    _set3(msg.ee_linear_acceleration, ee.linear_acceleration)
    _set3(msg.ee_angular_acceleration, ee.angular_acceleration)
    return msg


def command_from_message(msg: ArmCommand) -> Command:
    """Decode an :class:`ArmCommand` into a core :class:`Command` (not yet range-checked).

    Raises:
        CommandRejectedError: ``malformed`` for an unspecified mode or a missing required field.
    """
    tick = int(msg.tick)
    if msg.mode == ArmCommand.CARTESIAN_ACCELERATION:
        if not msg.HasField("linear_acceleration"):
            raise CommandRejectedError("malformed", "Cartesian command without linear_acceleration")
        a = msg.linear_acceleration
        quat = None
        if msg.HasField("orientation_reference"):
            o = msg.orientation_reference
            quat = np.array([o.x, o.y, o.z, o.w])
        omega = None
        if msg.has_angular_velocity_reference:
            w = msg.angular_velocity_reference
            omega = np.array([w.x, w.y, w.z])
        return Command(tick, CommandMode.CARTESIAN, np.array([a.x, a.y, a.z]), quat, omega)
    if msg.mode == ArmCommand.JOINT_ACCELERATION:
        return Command(tick, CommandMode.JOINT, joint_acceleration=np.array(msg.joint_accelerations))
    raise CommandRejectedError("malformed", f"unsupported command mode {int(msg.mode)}")


def cartesian_command(
    state: ArmState,
    linear_acceleration: Sequence[float],
    orientation_xyzw: Sequence[float] | None = None,
    angular_velocity: Sequence[float] | None = None,
    *,
    seq: int = 0,
    source: str = "",
) -> ArmCommand:
    """An :class:`ArmCommand` answering ``state`` in Cartesian mode (helper for clients)."""
    msg = ArmCommand(
        stamp_ns=state.stamp_ns,
        seq=seq,
        tick=state.tick,
        mode=ArmCommand.CARTESIAN_ACCELERATION,
        source=source,
        frame_id=state.frame_id,
    )
    _set3(msg.linear_acceleration, linear_acceleration)
    if orientation_xyzw is not None:
        o = msg.orientation_reference
        o.x, o.y, o.z, o.w = (float(c) for c in orientation_xyzw)
    if angular_velocity is not None:
        _set3(msg.angular_velocity_reference, angular_velocity)
        msg.has_angular_velocity_reference = True
    return msg


def joint_command(
    state: ArmState, joint_acceleration: Sequence[float], *, seq: int = 0, source: str = ""
) -> ArmCommand:
    """An :class:`ArmCommand` answering ``state`` with raw joint accelerations (rad/s²)."""
    return ArmCommand(
        stamp_ns=state.stamp_ns,
        seq=seq,
        tick=state.tick,
        mode=ArmCommand.JOINT_ACCELERATION,
        joint_accelerations=[float(v) for v in joint_acceleration],
        source=source,
        frame_id=state.frame_id,
    )


def frame_transforms(
    robot: RobotModel, frame_ids: Sequence[int], time_ns: int, frame_id: str
) -> FrameTransforms:
    """Foxglove ``FrameTransforms`` of the given link frames, each parented to the base frame
    ``frame_id``; valid after ``robot.update``/``robot.fk`` for the state to show."""
    stamp = Timestamp(seconds=time_ns // 1_000_000_000, nanos=time_ns % 1_000_000_000)
    out = FrameTransforms()
    for name, M in robot.link_placements(frame_ids):
        if name == frame_id:
            continue
        tf: FrameTransform = out.transforms.add()
        tf.timestamp.CopyFrom(stamp)
        tf.parent_frame_id = frame_id
        tf.child_frame_id = name
        _set3(tf.translation, M.translation)
        x, y, z, w = quat_xyzw_from_matrix(M.rotation)
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = x, y, z, w
    return out
