"""The arm's bus protocol: ``psm.ArmState`` / ``psm.ArmCommand`` ↔ numpy, for both ends of the
loop.

* the arm side: :func:`state_message` (publish a state), :func:`command_from_message` (decode a
  command into a :class:`Command`, not yet range-checked), :func:`frame_transforms` (link frames
  for Foxglove);
* the controller side (planner, probe, tests): :func:`state_from_message` (an ``ArmState`` as an
  :class:`ArmStateData` of numpy arrays), :func:`cartesian_command`, :func:`joint_command`;
* every follower of the arm's states (planner, obstacle monitor, the synthetic camera's clock):
  :class:`StateStream`, which states continue the arm's stream.

Units and frames: joint vectors ``(n,)`` in rad, rad/s, rad/s²; Cartesian quantities ``(3,)``
in the base frame ``frame_id`` at the end-effector origin (m, m/s, m/s², rad/s, rad/s²);
quaternions ``(4,)`` ``(x, y, z, w)``. A command echoes the ``tick`` and ``stamp_ns`` of the
state it answers.

Free of Zenoh, of Pinocchio and of the arm simulator: the teach mode (which writes MCAP
directly), the arm service and any controller share it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, Protocol

import numpy as np
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf.timestamp_pb2 import Timestamp

from services.bus.messages import ArmCommand, ArmState, FrameTransforms
from services.robot.rotations import matrix_from_quat_xyzw

if TYPE_CHECKING:
    from services.robot.model import RobotModel


class CommandMode(Enum):
    """What a command asks for."""

    CARTESIAN = "cartesian"  #: EE linear acceleration + orientation reference (IK inside)
    JOINT = "joint"  #: raw joint accelerations


@dataclass
class Command:
    """A command for the arm, decoded from the bus (:func:`command_from_message`).

    Attributes:
        tick: tick of the arm state this command answers (echoed from ``ArmState.tick``).
        mode: :class:`CommandMode`.
        linear_acceleration: desired EE linear acceleration ``(3,)`` m/s² (Cartesian mode).
        orientation_xyzw: orientation reference ``(4,)`` ``(x, y, z, w)`` or ``None`` to hold
            the orientation captured when Cartesian control started (Cartesian mode).
        angular_velocity: optional angular velocity reference ``(3,)`` rad/s (Cartesian mode).
        joint_acceleration: joint accelerations ``(n,)`` rad/s² (joint mode).
    """

    tick: int
    mode: CommandMode
    linear_acceleration: np.ndarray | None = None
    orientation_xyzw: np.ndarray | None = None
    angular_velocity: np.ndarray | None = None
    joint_acceleration: np.ndarray | None = None


class CommandRejectedError(ValueError):
    """A command failed decoding or validation; ``reason`` is a short counter key
    (``malformed``, ``non_finite``, ``out_of_range``, ``tick``)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class EEState:
    """End-effector state in the base frame, at the end-effector origin.

    ``position (3,)`` m, ``quat_xyzw (4,)`` with ``w >= 0``, ``rotation (3, 3)``,
    ``linear_velocity (3,)`` m/s, ``angular_velocity (3,)`` rad/s, ``linear_acceleration (3,)``
    m/s² (classical: the second derivative of the position), ``angular_acceleration (3,)``
    rad/s².
    """

    position: np.ndarray
    quat_xyzw: np.ndarray
    rotation: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    angular_acceleration: np.ndarray


class StateLike(Protocol):
    """What :func:`state_message` reads: the arm simulator's snapshot or an
    :class:`ArmStateData`."""

    tick: int  #: control tick
    time_ns: int  #: sim time, ns
    q: np.ndarray  #: joint positions (n,) rad
    dq: np.ndarray  #: joint velocities (n,) rad/s
    ddq: np.ndarray  #: joint accelerations (n,) rad/s²
    ee: EEState  #: end-effector state in the base frame
    braking: bool  #: the arm is braking


@dataclass(frozen=True)
class ArmStateData:
    """An ``ArmState`` as numpy arrays (:func:`state_from_message`).

    Attributes:
        tick: control tick; a command answering this state echoes it.
        time_ns: sim time of the state, ns (``ArmState.sim_time_ns``).
        stamp_ns: message stamp, ns (equal to ``time_ns`` for the simulated arm).
        q, dq, ddq: joint positions ``(n,)`` rad, velocities rad/s, accelerations rad/s².
        ee: end-effector state in ``frame_id`` (:class:`EEState`).
        braking: the arm is braking (no valid command in time).
        watchdog_tripped: the command watchdog expired since the last command.
        rejected_commands: commands rejected so far.
        joint_names: names of the ``n`` joints.
        frame_id: base frame of the Cartesian quantities.
        dt_s: control period, s.
    """

    tick: int
    time_ns: int
    stamp_ns: int
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    ee: EEState
    braking: bool
    watchdog_tripped: bool
    rejected_commands: int
    joint_names: tuple[str, ...]
    frame_id: str
    dt_s: float


def _set3(v: object, a: Sequence[float] | np.ndarray) -> None:
    v.x, v.y, v.z = float(a[0]), float(a[1]), float(a[2])  # type: ignore[attr-defined]


def _vec3(v: object) -> np.ndarray:
    return np.array([v.x, v.y, v.z])  # type: ignore[attr-defined]


def state_message(
    snap: StateLike,
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


class StateEncoder:
    """Serialises states like :func:`state_message` into one cached :class:`ArmState` updated
    in place (the per-state constant fields are set once): the arm's per-tick encoder. The
    bytes equal ``state_message(...).SerializeToString()``. Not thread-safe."""

    def __init__(self, joint_names: Sequence[str], frame_id: str, dt_s: float) -> None:
        self._msg = msg = ArmState(joint_names=joint_names, frame_id=frame_id, dt_s=dt_s)
        self._fields = (
            msg.ee_position, msg.ee_linear_velocity, msg.ee_angular_velocity,
            msg.ee_linear_acceleration, msg.ee_angular_acceleration,
        )

    def encode(self, snap: StateLike, *, watchdog_tripped: bool = False, rejected_commands: int = 0) -> bytes:
        """The serialised :class:`ArmState` of ``snap`` (``stamp_ns`` = sim time)."""
        msg, ee = self._msg, snap.ee
        msg.stamp_ns = msg.sim_time_ns = snap.time_ns
        msg.tick = snap.tick
        msg.q[:] = snap.q.tolist()
        msg.dq[:] = snap.dq.tolist()
        msg.ddq[:] = snap.ddq.tolist()
        msg.braking = snap.braking
        msg.watchdog_tripped = watchdog_tripped
        msg.rejected_commands = min(rejected_commands, 2**32 - 1)
        o = msg.ee_orientation
        o.x, o.y, o.z, o.w = ee.quat_xyzw.tolist()
        for v, a in zip(
            self._fields,
            (ee.position, ee.linear_velocity, ee.angular_velocity, ee.linear_acceleration,
             ee.angular_acceleration),
            strict=True,
        ):
            v.x, v.y, v.z = a.tolist()
        return msg.SerializeToString()


def state_from_message(msg: ArmState) -> ArmStateData:
    """Decode an :class:`ArmState` into numpy arrays (:class:`ArmStateData`); ``ee.rotation``
    is computed from the quaternion, which is returned as sent.

    Raises:
        ValueError: ``q``, ``dq``, ``ddq`` and ``joint_names`` differ in length, or the
            orientation quaternion has zero or non-finite norm.
    """
    q, dq, ddq = np.array(msg.q, dtype=float), np.array(msg.dq, dtype=float), np.array(msg.ddq, dtype=float)
    names = tuple(msg.joint_names)
    if not (q.shape == dq.shape == ddq.shape) or (names and len(names) != q.size):
        raise ValueError(
            f"ArmState: q, dq, ddq, joint_names have {q.size}, {dq.size}, {ddq.size}, {len(names)} values"
        )
    o = msg.ee_orientation
    quat = np.array([o.x, o.y, o.z, o.w])
    ee = EEState(
        position=_vec3(msg.ee_position),
        quat_xyzw=quat,
        rotation=matrix_from_quat_xyzw(quat),
        linear_velocity=_vec3(msg.ee_linear_velocity),
        angular_velocity=_vec3(msg.ee_angular_velocity),
        linear_acceleration=_vec3(msg.ee_linear_acceleration),
        angular_acceleration=_vec3(msg.ee_angular_acceleration),
    )
    return ArmStateData(
        tick=int(msg.tick),
        time_ns=int(msg.sim_time_ns),
        stamp_ns=int(msg.stamp_ns),
        q=q,
        dq=dq,
        ddq=ddq,
        ee=ee,
        braking=bool(msg.braking),
        watchdog_tripped=bool(msg.watchdog_tripped),
        rejected_commands=int(msg.rejected_commands),
        joint_names=names,
        frame_id=msg.frame_id,
        dt_s=float(msg.dt_s),
    )


def command_from_message(msg: ArmCommand) -> Command:
    """Decode an :class:`ArmCommand` into a :class:`Command` (not yet range-checked).

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
    """An :class:`ArmCommand` answering ``state`` in Cartesian mode.

    Args:
        state: the state answered (its ``tick``, ``stamp_ns`` and ``frame_id`` are echoed).
        linear_acceleration: desired EE linear acceleration ``(3,)`` m/s², base frame.
        orientation_xyzw: orientation reference ``(4,)``; ``None`` holds the orientation the
            arm had when Cartesian control started.
        angular_velocity: angular velocity reference ``(3,)`` rad/s (default zero).
        seq: the publisher's command counter.
        source: name of the commanding service.
    """
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
    """An :class:`ArmCommand` answering ``state`` with raw joint accelerations ``(n,)`` rad/s²."""
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
    for name, (x, y, z, qx, qy, qz, qw) in robot.link_poses(frame_ids):
        if name == frame_id:
            continue
        tf: FrameTransform = out.transforms.add()
        tf.timestamp.CopyFrom(stamp)
        tf.parent_frame_id = frame_id
        tf.child_frame_id = name
        t, r = tf.translation, tf.rotation
        t.x, t.y, t.z = x, y, z
        r.x, r.y, r.z, r.w = qx, qy, qz, qw
    return out


#: Defaults of the stream checks (the planner's ``max_tick_gap``, ``stamp_tolerance_s`` and
#: ``resync_after``; the obstacle monitor and the synthetic camera's clock use them as they are).
MAX_TICK_GAP = 50
STAMP_TOLERANCE_S = 0.0005
RESYNC_AFTER = 25


class StateStream:
    """Which arm states continue the arm's stream, for the services that follow it.

    A state continues the stream when its tick is after the last accepted one by at most
    ``max_tick_gap`` ticks and its stamp is ``(tick - last tick) * dt_s`` after the last one's
    within ``stamp_tolerance_ns``; the first state starts the stream. Anything else is rejected
    with a reason — ``tick`` (not after the last one, or too far ahead) or ``stamp`` — as a
    stale, replayed, reordered or forged state is. A run of ``resync_after`` rejected states
    that form a stream of their own (each continues the one before it, or re-offers it as a
    lockstep arm does) is followed instead (verdict ``resync``): the arm restarted, or its
    states came back after an outage longer than ``max_tick_gap``. Random or stale states never
    form such a run, so they never move the stream. Not thread-safe (the caller's lock).

    Example::

        stream = StateStream(max_tick_gap=50, stamp_tolerance_ns=500_000, resync_after=25)
        verdict, why = stream.check(state.tick, state.stamp_ns, state.dt_s)
        # "" accepted, "repeat" the last state again, "resync" accepted as a new stream,
        # "tick" or "stamp" rejected
    """

    def __init__(
        self,
        max_tick_gap: int = MAX_TICK_GAP,
        stamp_tolerance_ns: int = round(STAMP_TOLERANCE_S * 1e9),
        resync_after: int = RESYNC_AFTER,
    ) -> None:
        self.max_tick_gap = max_tick_gap
        self.stamp_tolerance_ns = stamp_tolerance_ns
        self.resync_after = resync_after
        self.last_tick = -1  #: tick of the last accepted state (-1: none yet)
        self.last_stamp = 0  #: its stamp [ns]
        self._cand_tick = -1  # the last rejected state (the run of a possible new stream)
        self._cand_stamp = 0
        self._run = 0

    def _follows(self, tick: int, stamp: int, last_tick: int, last_stamp: int, dt_s: float) -> str:
        """``""`` if ``(tick, stamp)`` continues ``(last_tick, last_stamp)``, else why not."""
        gap = tick - last_tick
        if gap <= 0:
            return f"tick {tick} does not follow the last tick {last_tick}"
        if gap > self.max_tick_gap:
            return f"tick jumped from {last_tick} to {tick} (more than {self.max_tick_gap})"
        if abs((stamp - last_stamp) - gap * dt_s * 1e9) > self.stamp_tolerance_ns:
            return (f"tick {tick}: stamp {(stamp - last_stamp) * 1e-9:.4f} s after the last, "
                    f"expected {gap * dt_s:.4f} s")
        return ""

    def check(self, tick: int, stamp_ns: int, dt_s: float) -> tuple[str, str]:
        """``(verdict, why)`` for the state ``(tick, stamp_ns)`` with period ``dt_s`` [s] (a
        positive number: the caller checks it); an accepted state becomes the last one."""
        if tick == self.last_tick and stamp_ns == self.last_stamp:
            return "repeat", ""  # the same state again (a lockstep arm re-offers it)
        if self.last_tick >= 0:
            why = self._follows(tick, stamp_ns, self.last_tick, self.last_stamp, dt_s)
            if why:
                kind = "stamp" if why.startswith(f"tick {tick}: stamp") else "tick"
                again = tick == self._cand_tick and stamp_ns == self._cand_stamp
                if self._cand_tick >= 0 and (
                    again or not self._follows(tick, stamp_ns, self._cand_tick, self._cand_stamp, dt_s)
                ):
                    self._run += 1
                else:
                    self._run = 1
                self._cand_tick, self._cand_stamp = tick, stamp_ns
                if self._run < self.resync_after:
                    return kind, why
                self.last_tick, self.last_stamp, self._run, self._cand_tick = tick, stamp_ns, 0, -1
                return "resync", why
        self.last_tick, self.last_stamp, self._run, self._cand_tick = tick, stamp_ns, 0, -1
        return "", ""

    def follows(self, tick: int, stamp_ns: int, dt_s: float) -> bool:
        """True if a message about state ``(tick, stamp_ns)`` — e.g. a collision prediction —
        fits the stream: its tick is at most ``max_tick_gap`` ahead of the last state's (any
        earlier one: a late message is the caller's to judge by its age) and its stamp is the
        one the stream gives that tick; True while no state is known. Changes nothing."""
        if self.last_tick < 0:
            return True
        gap = tick - self.last_tick
        return gap <= self.max_tick_gap and (
            abs((stamp_ns - self.last_stamp) - gap * dt_s * 1e9) <= self.stamp_tolerance_ns
        )


__all__ = [
    "MAX_TICK_GAP",
    "RESYNC_AFTER",
    "STAMP_TOLERANCE_S",
    "ArmStateData",
    "Command",
    "CommandMode",
    "CommandRejectedError",
    "EEState",
    "StateEncoder",
    "StateLike",
    "StateStream",
    "cartesian_command",
    "command_from_message",
    "frame_transforms",
    "joint_command",
    "state_from_message",
    "state_message",
]
