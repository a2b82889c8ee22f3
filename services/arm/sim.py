"""The simulated arm: fixed-step integration, command handling, watchdog brake (bus-free).

:class:`ArmSim` owns the joint state and advances it one tick at a time::

    sim = ArmSim(robot, ArmSimConfig(dt_s=0.002))
    snap = sim.snapshot()          # state k: publish it
    sim.submit(command)            # the command answering state k (validated, maybe rejected)
    sim.step()                     # integrate to state k+1

Time is the simulation's own: ``time_ns = time_origin_ns + tick * dt_ns`` (origin 0 unless set
with :meth:`ArmSim.set_time_origin`, e.g. to the UNIX epoch at start for a realtime arm). The
watchdog is in sim time too: a command answering tick ``c`` is used while
``(tick - c) * dt_ns <= watchdog_timeout_ns``; after that the arm brakes to zero velocity within
its limits and never re-uses the old command.
Integration is semi-implicit Euler: ``dq += ddq dt; q += dq dt`` (compiled with the controller's
arithmetic: :mod:`services.arm.kernel`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace

import numpy as np
import pinocchio as pin
from pydantic import Field

from services.arm import kernel
from services.arm.controller import (
    POSITION_GUARD,
    AccelBounds,
    AccelBoundsKernel,
    ClampReport,
    ControllerGains,
    IKController,
    ValidationLimits,
    validate_command,
)
from services.bus.config import ConfigError, Section
from services.robot.model import RobotModel
from services.robot.protocol import Command, CommandMode, CommandRejectedError, EEState
from services.robot.rotations import matrix_from_quat_xyzw


class ArmSimConfig(Section):
    """Parameters of the simulated arm (the simulator's part of the ``[arm]`` table)."""

    dt_s: float = Field(0.002, gt=0.0, le=0.1, description="control period [s] (500 Hz)")
    start_pose: str | list[float] = Field(
        "ready", description="named start pose (ready, home, neutral, middle) or joints (n,) [rad]"
    )
    posture: str | list[float] | None = Field(
        None, description="null-space posture, named or (n,) [rad]; unset = the start pose"
    )
    watchdog_timeout_s: float = Field(
        0.02, ge=0.0, le=10.0, description="sim time without a valid command before braking [s]"
    )
    gains: ControllerGains = Field(default_factory=ControllerGains)
    validation: ValidationLimits = Field(default_factory=ValidationLimits)
    brake_fraction: float = Field(
        0.5, gt=0.0, le=1.0,
        description="share of the acceleration limits used by position-limit braking",
    )

    def check(self) -> None:
        """The period is whole nanoseconds; the watchdog is at least one period."""
        if abs(round(self.dt_s * 1e9) - self.dt_s * 1e9) > 1e-3:
            raise ConfigError("dt_s", "must be a whole number of nanoseconds")
        if self.watchdog_timeout_s < self.dt_s:
            raise ConfigError("watchdog_timeout_s", "must be at least one control period dt_s")

    @property
    def dt_ns(self) -> int:
        """Control period [ns]."""
        return round(self.dt_s * 1e9)

    @property
    def watchdog_timeout_ns(self) -> int:
        """Watchdog timeout [ns]."""
        return round(self.watchdog_timeout_s * 1e9)


_CHAIN_KINDS = {
    "JointModelRX": kernel.REVOLUTE_X, "JointModelRY": kernel.REVOLUTE_Y,
    "JointModelRZ": kernel.REVOLUTE_Z, "JointModelRevoluteUnaligned": kernel.REVOLUTE,
    "JointModelPX": kernel.PRISMATIC, "JointModelPY": kernel.PRISMATIC,
    "JointModelPZ": kernel.PRISMATIC, "JointModelPrismaticUnaligned": kernel.PRISMATIC,
}
_AXIS_OF = {"X": 0, "Y": 1, "Z": 2}


@dataclass(frozen=True)
class SerialChain:
    """A robot model that is a serial chain of 1-DoF revolute or prismatic joints, as the
    arguments of :func:`services.arm.kernel.chain_kinematics`: joint ``i`` (model joint
    ``i + 1``) has ``kind[i]``, unit ``axis[i]`` (3,) in its own frame and its placement
    ``joint_rotation[i]`` (3, 3), ``joint_translation[i]`` (3,) [m] in its parent's frame; the
    end-effector frame is ``ee_rotation``, ``ee_translation`` in the frame of joint ``n_ee - 1``.
    """

    kind: np.ndarray
    axis: np.ndarray
    joint_rotation: np.ndarray
    joint_translation: np.ndarray
    ee_rotation: np.ndarray
    ee_translation: np.ndarray
    n_ee: int
    size: int  #: length of the kernel's output (34 + 6 n)

    @classmethod
    def from_robot(cls, robot: RobotModel) -> SerialChain | None:
        """The chain of ``robot``'s model up to its end-effector frame, or ``None`` when the
        model is not such a chain (a tree, a multi-DoF or mimic joint: Pinocchio then)."""
        model = robot.model
        n = int(model.nv)
        if model.nq != n or model.njoints != n + 1:
            return None
        kind = np.zeros(n, dtype=np.int64)
        axis = np.zeros((n, 3))
        rot = np.zeros((n, 3, 3))
        trans = np.zeros((n, 3))
        for i in range(1, model.njoints):
            joint = model.joints[i]
            name = joint.shortname()
            serial = model.parents[i] == i - 1 and joint.idx_q == joint.idx_v == i - 1
            if name not in _CHAIN_KINDS or not serial:
                return None
            kind[i - 1] = _CHAIN_KINDS[name]
            if name.endswith("Unaligned"):
                axis[i - 1] = np.asarray(joint.extract().axis, dtype=float)
            else:
                axis[i - 1, _AXIS_OF[name[-1]]] = 1.0
            placement = model.jointPlacements[i]
            rot[i - 1] = placement.rotation
            trans[i - 1] = placement.translation
        frame = model.frames[robot.ee_frame_id]
        return cls(
            kind, axis, rot, trans, np.ascontiguousarray(frame.placement.rotation, dtype=float),
            np.ascontiguousarray(frame.placement.translation, dtype=float),
            int(frame.parentJoint), kernel.CHAIN_JACOBIAN + 6 * n,
        )


@dataclass(frozen=True)
class ArmSnapshot:
    """State of the arm at one tick (everything a state message carries).

    ``q``, ``dq``, ``ddq`` are ``(n,)`` (rad, rad/s, rad/s²; ``ddq`` is the acceleration applied
    over the last step), ``ee`` the end-effector state at this tick with the accelerations that
    ``ddq`` produces at this state.
    """

    tick: int
    time_ns: int
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    ee: EEState
    braking: bool
    #: ``(19,)`` the EE's position, quaternion, twist and acceleration back to back (``ee``'s
    #: arrays are views of it), when the compiled kinematics made the snapshot; else ``None``.
    ee_packed: np.ndarray | None = None


class ArmSim:
    """Simulated fixed-base arm with a Cartesian-acceleration interface (see module docstring)."""

    def __init__(self, robot: RobotModel, config: ArmSimConfig | None = None) -> None:
        self.robot = robot
        self.config = config or ArmSimConfig()
        cfg = self.config
        self.dt = cfg.dt_ns * 1e-9
        self._dt_ns = cfg.dt_ns  # the config's derived values, read every tick
        self._watchdog_ns = cfg.watchdog_timeout_ns
        self.q = robot.resolve_pose(cfg.start_pose)
        self.dq = np.zeros(robot.n)
        self.ddq = np.zeros(robot.n)
        posture = cfg.start_pose if cfg.posture is None else cfg.posture
        self.controller = IKController(robot, cfg.gains, robot.resolve_pose(posture))
        self.tick = 0
        #: Sim time of tick 0, ns (0, or the UNIX epoch at start for a realtime arm).
        self.time_origin_ns = 0
        self.counters: Counter[str] = Counter()
        self.clamp = ClampReport()
        self.braking = True
        self._command: Command | None = None
        #: Commands answering a tick below this are refused (set when the planner is lost).
        self._min_command_tick = 0
        self._hold_rotation: np.ndarray | None = None
        self._ref_rotation: np.ndarray | None = None
        self._ref_quat: list[float] | None = None  # the quaternion _ref_rotation was made from
        self._snapshot: ArmSnapshot | None = None
        self._bounds: AccelBounds | None = None
        #: (J (6, n), drift (6,), twist (6,), rotation (3, 3)) of the current state (_refresh).
        self._kin: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._bounds_kernel = AccelBoundsKernel(robot.limits, self.dt, cfg.brake_fraction)
        self.last_rejection = ""
        self.last_rejection_reason = ""  #: malformed, non_finite, out_of_range, tick, stamp
        #: True once a held command expired (watchdog), until a fresh command is accepted.
        self.watchdog_tripped = False
        # Compiled (or loaded from numba's cache) here rather than at the first tick, which
        # would then take ~0.2 s (2 s on a first start after an install).
        kernel.warm_up()
        #: The compiled kinematics when the model is a serial chain of 1-DoF joints, else None
        #: (Pinocchio's calls then).
        self._chain = SerialChain.from_robot(robot)
        self._refresh()

    # ------------------------------------------------------------------ state
    @property
    def time_ns(self) -> int:
        """Sim time of the current tick, ns: ``time_origin_ns + tick * dt_ns``."""
        return self.time_origin_ns + self.tick * self._dt_ns

    def set_time_origin(self, origin_ns: int) -> None:
        """Set the sim time of tick 0 (ns); the current snapshot is re-stamped."""
        self.time_origin_ns = int(origin_ns)
        if self._snapshot is not None:
            self._snapshot = replace(self._snapshot, time_ns=self.time_ns)

    def snapshot(self) -> ArmSnapshot:
        """State at the current tick (cached; recomputed only after :meth:`step`)."""
        assert self._snapshot is not None
        return self._snapshot

    def _refresh(self) -> None:
        chain = self._chain
        if chain is None:
            self._refresh_pinocchio()
            return
        # One compiled pass (placement, quaternion, J, twist, drift, J q̈ + drift) into a fresh
        # buffer: the snapshot's arrays are views of it, never rewritten. The slices are
        # kernel.CHAIN_LAYOUT's, written out (this runs every tick).
        out = np.empty(chain.size)
        kernel.chain_kinematics(
            chain.kind, chain.axis, chain.joint_rotation, chain.joint_translation, chain.ee_rotation,
            chain.ee_translation, chain.n_ee, self.q, self.dq, self.ddq, out,
        )
        twist = out[7:13]
        rotation = out[25:34].reshape(3, 3)
        ee = EEState(
            position=out[0:3],
            quat_xyzw=out[3:7],
            rotation=rotation,
            linear_velocity=out[7:10],
            angular_velocity=out[10:13],
            linear_acceleration=out[13:16],
            angular_acceleration=out[16:19],
        )
        self._snapshot = ArmSnapshot(
            self.tick, self.time_ns, self.q, self.dq, self.ddq, ee, self.braking, out[0:19]
        )
        self._kin = (out[kernel.CHAIN_JACOBIAN:].reshape(6, self.robot.n), out[19:25], twist, rotation)
        self._bounds = None

    def _refresh_pinocchio(self) -> None:
        robot = self.robot
        robot.update(self.q, self.dq)
        # The Jacobian, drift and twist of this state, computed once: the snapshot and the
        # controller's prepare() both use them.
        J = robot.jacobian()
        drift = robot.drift()
        twist = robot.ee_velocity()
        acc = J @ self.ddq
        acc += drift
        M = robot.ee_placement()
        xyzquat = pin.SE3ToXYZQUAT(M)
        quat = xyzquat[3:]
        if quat[3] < 0:
            quat = -quat
        rotation = M.rotation.copy()  # a view into the model data otherwise
        ee = EEState(
            position=xyzquat[:3],
            quat_xyzw=quat,
            rotation=rotation,
            linear_velocity=twist[:3],
            angular_velocity=twist[3:],
            linear_acceleration=acc[:3],
            angular_acceleration=acc[3:],
        )
        # q, dq, ddq are replaced (never mutated in place) by step(), so no copies are needed.
        self._snapshot = ArmSnapshot(self.tick, self.time_ns, self.q, self.dq, self.ddq, ee, self.braking)
        self._kin = (J, drift, twist, rotation)
        self._bounds = None

    def sync_model(self) -> None:
        """Bring the robot model's data (every link's placement) to the current state, for
        readers of the whole model such as :func:`~services.robot.protocol.frame_transforms`:
        the simulation itself computes only the end effector's kinematics per tick."""
        if self._chain is not None:
            self.robot.update(self.q, self.dq)

    def prepare(self) -> None:
        """Do the command-independent work for the current tick (Jacobian, damped inverse,
        posture term, limit interval). Optional: :meth:`step` calls it if needed; the service
        calls it while it waits for the command, to shorten the state→step critical path."""
        if self._bounds is None:
            J, drift, twist, rotation = self._kin
            self.controller.prepare(self.q, self.dq, J=J, drift=drift, twist=twist, rotation=rotation)
            self._bounds = self._bounds_kernel(self.q, self.dq)

    # ------------------------------------------------------------------ commands
    def submit(self, cmd: Command) -> bool:
        """Offer a command. Returns True if accepted (it will drive the next steps).

        Rejected (and counted under ``rejected_<reason>``): malformed, non-finite, out of range,
        or answering a tick that has not happened yet (``tick``). Ignored (counted ``stale``): a
        command older than the one already held, or answering a state published before
        :meth:`drop_command` (a lost planner's last commands still in flight).
        """
        self.counters["commands_received"] += 1
        try:
            if isinstance(cmd.tick, int) and cmd.tick > self.tick:
                raise CommandRejectedError("tick", f"command answers future tick {cmd.tick}")
            valid = validate_command(cmd, self.robot.n, self.config.validation)
        except CommandRejectedError as exc:
            self._count_rejection(exc)
            return False
        return self._accept(valid)

    def submit_validated(self, valid: Command) -> bool:
        """:meth:`submit` for a command that has passed :func:`validate_command` already (or
        its compiled equivalent, :func:`services.arm.kernel.parse_cartesian_command`): the same
        counters and tick checks, without validating it again."""
        self.counters["commands_received"] += 1
        if valid.tick > self.tick:
            self._count_rejection(CommandRejectedError("tick", f"command answers future tick {valid.tick}"))
            return False
        return self._accept(valid)

    def _count_rejection(self, exc: CommandRejectedError) -> None:
        self.counters[f"rejected_{exc.reason}"] += 1
        self.counters["rejected"] += 1
        self.last_rejection = str(exc)
        self.last_rejection_reason = exc.reason

    def _accept(self, valid: Command) -> bool:
        """Hold ``valid`` unless it is stale (counted); True if held."""
        if valid.tick < self._min_command_tick or (
            self._command is not None and valid.tick < self._command.tick
        ):
            self.counters["stale"] += 1
            return False
        self._command = valid
        self.counters["commands_accepted"] += 1
        if self.command_fresh():
            self.watchdog_tripped = False
        return True

    def drop_command(self) -> None:
        """Forget the held command: the arm brakes from the next step on (e.g. the planner's
        liveliness token disappeared). Commands answering the current or an earlier tick are
        refused from now on, so a lost planner's commands that were still in flight (Zenoh
        does not order them against the liveliness event) cannot restart the arm; a planner
        that answers a state published after this call takes control again."""
        self._command = None
        self._min_command_tick = self.tick + 1

    def reject(self, reason: str, message: str) -> None:
        """Count a command that could not even be decoded (reason e.g. ``malformed``)."""
        self.counters["commands_received"] += 1
        self.counters[f"rejected_{reason}"] += 1
        self.counters["rejected"] += 1
        self.last_rejection = message
        self.last_rejection_reason = reason

    def command_fresh(self) -> bool:
        """True if the held command is within the watchdog timeout at the current tick."""
        c = self._command
        return c is not None and (self.tick - c.tick) * self._dt_ns <= self._watchdog_ns

    # ------------------------------------------------------------------ stepping
    def _brake_accel(self) -> np.ndarray:
        """Joint deceleration stopping every joint along the current joint-space direction."""
        amax = self.robot.limits.acceleration
        ddq = -self.dq / self.dt
        ratio = float((np.abs(ddq) / amax).max())
        return ddq / ratio if ratio > 1.0 else ddq

    def compute_accel(self) -> np.ndarray:
        """Joint accelerations ``(n,)`` for the current tick (before limits)."""
        cmd = self._command
        if not self.command_fresh() or cmd is None:
            if not self.braking:
                self.counters["watchdog_trips"] += 1
                self.watchdog_tripped = True
            self.braking = True
            self._hold_rotation = None
            return self._brake_accel()
        self.braking = False
        if cmd.mode is CommandMode.JOINT:
            self._hold_rotation = None
            assert cmd.joint_acceleration is not None
            return cmd.joint_acceleration
        assert cmd.linear_acceleration is not None
        if cmd.orientation_xyzw is None:
            if self._hold_rotation is None:
                self._hold_rotation = self.snapshot().ee.rotation
            R_ref = self._hold_rotation
        else:
            quat = cmd.orientation_xyzw.tolist()
            if quat != self._ref_quat:
                self._ref_quat = quat
                self._ref_rotation = matrix_from_quat_xyzw(quat)
            R_ref = self._ref_rotation
        assert R_ref is not None
        self.prepare()
        return self.controller.finish(cmd.linear_acceleration, R_ref, cmd.angular_velocity)

    def step(self) -> ArmSnapshot:
        """Advance one tick with the held command (or brake) and return the new snapshot."""
        ddq_cmd = self.compute_accel()
        self.prepare()
        b = self._bounds
        assert b is not None
        lim = self.robot.limits
        n = self.robot.n
        # Fresh arrays: the previous snapshot keeps its own q, dq, ddq.
        ddq, dq, q = np.empty(n), np.empty(n), np.empty(n)
        flags = kernel.bound_and_integrate(
            ddq_cmd, self.q, self.dq, self.dt, lim.acceleration, b.lo, b.hi, b.lo_is_velocity,
            b.hi_is_velocity, lim.lower, lim.upper, ddq, dq, q,
        )
        self.clamp.set(flags)
        if flags:
            if self.clamp.acceleration:
                self.counters["clamped_acceleration"] += 1
            if self.clamp.velocity:
                self.counters["clamped_velocity"] += 1
            if self.clamp.position:
                self.counters["clamped_position"] += 1
            # Final guard (never active from a viable state): positions stay inside the limits.
            if flags & POSITION_GUARD:
                self.counters["position_guard"] += 1
        if self.braking:
            self.counters["braking_ticks"] += 1
        self.ddq, self.dq, self.q = ddq, dq, q
        self.tick += 1
        self._refresh()
        return self.snapshot()
