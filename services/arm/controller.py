"""Command validation, the inverse-kinematics controller and the joint-limit clamps (the
command types themselves are the protocol's: :mod:`services.robot.protocol`).

The controller turns a Cartesian command into joint accelerations (paper Fig. 6)::

    α_des = Kp_R · log(R_ref Rᵀ) + Kd_R · (ω_ref − ω)                  orientation PD (rad/s²)
    a     = [ẍ_des; α_des]                                            (6,)
    q̈_task = J⁺_λ (a − J̇q̇)                                            damped least squares
    q̈     = q̈_task + (I − J⁺_λ J) (Kp_n (q_posture − q) − Kd_n q̇)     null-space posture

``J⁺_λ = Jᵀ (J Jᵀ + λ² I)⁻¹`` with λ² = 0 away from singularities and growing smoothly to
``λ_max²`` as the smallest singular value of ``J`` drops below ``ε``. Then :func:`clamp_joint_accel`
bounds q̈ so that the next state respects the acceleration, velocity and position limits.
The arithmetic of the controller and of the limits is compiled (:mod:`services.arm.kernel`);
this module holds their configuration, state and Python interface. The kernels (and numba) are
imported by the classes and functions that run them, so that reading the configuration models
(the planner reads the gains' defaults) does not load the compiler.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from services.bus.config import Section
from services.robot.model import JointLimits, RobotModel
from services.robot.protocol import Command, CommandMode, CommandRejectedError

#: Bits of the compiled clamps' result (:func:`services.arm.kernel.apply_bounds`): which limits
#: changed the commanded acceleration, and the integrator's final position guard.
CLAMP_ACCELERATION = 1
CLAMP_VELOCITY = 2
CLAMP_POSITION = 4
POSITION_GUARD = 8


class ValidationLimits(Section):
    """Plausibility bounds (the ``[arm.validation]`` table): a command outside them is
    rejected, never applied (values inside them but beyond the arm's joint limits are clamped
    instead)."""

    max_linear_acceleration: float = Field(
        50.0, gt=0.0, description="commands above this EE acceleration norm are rejected [m/s^2]"
    )
    max_angular_velocity: float = Field(
        10.0, gt=0.0, description="commands above this angular velocity norm are rejected [rad/s]"
    )
    max_joint_acceleration: float = Field(
        100.0, gt=0.0, description="joint-mode commands above this magnitude are rejected [rad/s^2]"
    )
    quat_norm_tolerance: float = Field(
        0.1, gt=0.0, description="quaternions with | |q| - 1 | above this are rejected"
    )


def _vector_sq(value: object, size: int, name: str) -> tuple[np.ndarray, float]:
    """``value`` as a finite float array ``(size,)`` and its squared norm ``v · v``.

    The squared norm doubles as the finiteness check: it is finite iff every element is,
    unless the squares overflow, in which case the elements are checked one by one. It is
    summed on plain floats (``tolist`` is the one numpy call per vector on the arm's per-tick
    path, whose caches are cold at every tick: there a numpy reduction costs ~10 µs).
    """
    if isinstance(value, np.ndarray) and value.dtype == np.float64:
        arr = value
    else:
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError) as exc:
            raise CommandRejectedError("malformed", f"{name} is not numeric") from exc
    if arr.shape != (size,):
        raise CommandRejectedError("malformed", f"{name} must have {size} values, got {arr.size}")
    sq = 0.0
    for e in arr.tolist():
        sq += e * e
    if not math.isfinite(sq) and not np.isfinite(arr).all():
        raise CommandRejectedError("non_finite", f"{name} contains NaN or inf")
    return arr, sq


def _vector(value: object, size: int, name: str) -> np.ndarray:
    return _vector_sq(value, size, name)[0]


def validate_command(cmd: Command, n: int, bounds: ValidationLimits) -> Command:
    """Check a command's shape, finiteness and plausibility.

    Returns a normalised copy (float arrays, unit quaternion with ``w >= 0``).

    Raises:
        CommandRejectedError: with ``reason`` one of ``malformed``, ``non_finite``,
            ``out_of_range``.
    """
    if not isinstance(cmd.tick, int) or cmd.tick < 0:
        raise CommandRejectedError("malformed", "tick must be a non-negative integer")
    if cmd.mode is CommandMode.JOINT:
        if cmd.joint_acceleration is None:
            raise CommandRejectedError("malformed", "joint command without joint_acceleration")
        ddq = _vector(cmd.joint_acceleration, n, "joint_acceleration")
        if np.abs(ddq).max() > bounds.max_joint_acceleration:
            raise CommandRejectedError(
                "out_of_range",
                f"joint acceleration above {bounds.max_joint_acceleration} rad/s²",
            )
        return Command(cmd.tick, CommandMode.JOINT, joint_acceleration=ddq)
    if cmd.mode is not CommandMode.CARTESIAN:
        raise CommandRejectedError("malformed", f"unknown command mode {cmd.mode!r}")
    if cmd.linear_acceleration is None:
        raise CommandRejectedError("malformed", "Cartesian command without linear_acceleration")
    acc, sq = _vector_sq(cmd.linear_acceleration, 3, "linear_acceleration")
    if math.sqrt(sq) > bounds.max_linear_acceleration:
        raise CommandRejectedError(
            "out_of_range", f"linear acceleration above {bounds.max_linear_acceleration} m/s²"
        )
    quat = None
    if cmd.orientation_xyzw is not None:
        quat, sq = _vector_sq(cmd.orientation_xyzw, 4, "orientation")
        norm = math.sqrt(sq)
        if abs(norm - 1.0) > bounds.quat_norm_tolerance:
            raise CommandRejectedError("out_of_range", f"orientation quaternion norm {norm:.3g} != 1")
        unit = [e / norm for e in quat.tolist()]
        if unit[3] < 0:
            unit = [-e for e in unit]
        quat = np.array(unit)
    omega = None
    if cmd.angular_velocity is not None:
        omega, sq = _vector_sq(cmd.angular_velocity, 3, "angular_velocity")
        if math.sqrt(sq) > bounds.max_angular_velocity:
            raise CommandRejectedError(
                "out_of_range", f"angular velocity above {bounds.max_angular_velocity} rad/s"
            )
    return Command(cmd.tick, CommandMode.CARTESIAN, acc, quat, omega)


class ControllerGains(Section):
    """Gains of the IK controller (the ``[arm.gains]`` table)."""

    orientation_kp: float = Field(100.0, ge=0.0, description="orientation PD stiffness [1/s^2]")
    orientation_kd: float = Field(20.0, ge=0.0, description="orientation PD damping [1/s]")
    nullspace_kp: float = Field(10.0, ge=0.0, description="null-space posture stiffness [1/s^2]")
    nullspace_kd: float = Field(6.0, ge=0.0, description="null-space joint damping [1/s]")
    singular_epsilon: float = Field(
        0.04, gt=0.0, description="smallest singular value of J below which DLS damping starts"
    )
    damping_max: float = Field(
        0.05, ge=0.0, description="maximum DLS damping lambda (units of J's singular values)"
    )


@dataclass
class ClampReport:
    """Which limits were active in the last :func:`clamp_joint_accel` call (per tick)."""

    acceleration: bool = False
    velocity: bool = False
    position: bool = False

    @property
    def any(self) -> bool:
        """True if any clamp changed the commanded acceleration."""
        return self.acceleration or self.velocity or self.position

    def set(self, flags: int) -> None:
        """Set from the clamp bits of :mod:`services.arm.kernel`."""
        self.acceleration = bool(flags & CLAMP_ACCELERATION)
        self.velocity = bool(flags & CLAMP_VELOCITY)
        self.position = bool(flags & CLAMP_POSITION)


@dataclass
class AccelBounds:
    """State-dependent joint-acceleration interval ``[lo, hi]`` (each ``(n,)``, rad/s²) and,
    per side, whether the bound comes from the velocity limit (else from a position limit or
    the acceleration limit)."""

    lo: np.ndarray
    hi: np.ndarray
    lo_is_velocity: np.ndarray
    hi_is_velocity: np.ndarray


class AccelBoundsKernel:
    """:func:`joint_accel_bounds` for fixed ``limits``, ``dt`` and ``brake_fraction`` (the arm's
    per-tick path: one compiled call, :func:`services.arm.kernel.accel_bounds`)."""

    def __init__(self, limits: JointLimits, dt: float, brake_fraction: float = 0.5) -> None:
        from services.arm.kernel import accel_bounds

        self.limits, self.dt = limits, dt
        self._brake = brake_fraction * limits.acceleration
        self._kernel = accel_bounds

    def __call__(self, q: np.ndarray, dq: np.ndarray) -> AccelBounds:
        """The bounds for state ``q`` (n,) rad, ``dq`` (n,) rad/s (see :func:`joint_accel_bounds`)."""
        lim = self.limits
        n = q.shape[0]
        out = AccelBounds(np.empty(n), np.empty(n), np.empty(n, dtype=bool), np.empty(n, dtype=bool))
        self._kernel(
            q, dq, lim.lower, lim.upper, lim.velocity, lim.acceleration, self._brake, self.dt,
            out.lo, out.hi, out.lo_is_velocity, out.hi_is_velocity,
        )
        return out


def joint_accel_bounds(
    q: np.ndarray,
    dq: np.ndarray,
    limits: JointLimits,
    dt: float,
    brake_fraction: float = 0.5,
) -> AccelBounds:
    """The interval of joint accelerations that keeps the next state within every limit.

    The next velocity ``dq + ddq·dt`` must stay within the velocity limit and below the speed
    from which the joint can still stop (at ``brake_fraction`` of its acceleration limit) before
    its position limits; ``|ddq|`` must stay within the acceleration limit. If a joint is
    already outside that viable set, the interval collapses to the hardest allowed deceleration
    toward it.

    Discrete braking from speed v at deceleration a covers at most v·dt + v²/(2a) + v·dt/2
    with the semi-implicit Euler integrator; the stop speed for a distance d solves that for v:
    ``v = a (sqrt(2.25 dt² + 2 d / a) − 1.5 dt)``.
    """
    return AccelBoundsKernel(limits, dt, brake_fraction)(q, dq)


def apply_accel_bounds(
    ddq: np.ndarray,
    acceleration_limits: np.ndarray,
    bounds: AccelBounds,
    report: ClampReport | None = None,
) -> np.ndarray:
    """Scale ``ddq`` (n,) uniformly into the acceleration limits (keeps the Cartesian direction),
    then clip each joint into ``bounds``; fills ``report`` with the active clamps."""
    from services.arm.kernel import apply_bounds

    ddq = np.ascontiguousarray(ddq, dtype=float)
    out = np.empty_like(ddq)
    flags = apply_bounds(
        ddq, acceleration_limits, bounds.lo, bounds.hi, bounds.lo_is_velocity, bounds.hi_is_velocity, out
    )
    if report is not None:
        report.set(flags)
    return out


def clamp_joint_accel(
    ddq: np.ndarray,
    q: np.ndarray,
    dq: np.ndarray,
    limits: JointLimits,
    dt: float,
    report: ClampReport | None = None,
    brake_fraction: float = 0.5,
) -> np.ndarray:
    """Bound joint accelerations so the next state stays within every limit
    (:func:`joint_accel_bounds` + :func:`apply_accel_bounds`).

    Args:
        ddq: requested joint accelerations ``(n,)`` rad/s².
        q, dq: current joint positions ``(n,)`` rad and velocities ``(n,)`` rad/s.
        limits: the joint limits.
        dt: integration step, s.
        report: filled with which clamps were active.
        brake_fraction: share of the acceleration limit the position-limit braking may use.

    Returns:
        Clamped accelerations ``(n,)``: ``|ddq| <= limits.acceleration`` always holds.
    """
    bounds = joint_accel_bounds(q, dq, limits, dt, brake_fraction)
    return apply_accel_bounds(ddq, limits.acceleration, bounds, report)


@dataclass
class IKController:
    """Cartesian-acceleration → joint-acceleration controller (see module docstring).

    Split in two so the command-independent work can run while the arm waits for the command:
    :meth:`prepare` (after ``robot.update(q, dq)``: Jacobian, drift, damped inverse, posture
    term) and :meth:`finish` (with the command). :meth:`compute` does both. Not thread-safe.

    With ``p = Kp_n (q_posture − q) − Kd_n q̇`` the law is evaluated as
    ``q̈ = J⁺_λ (a − J̇q̇ − J p) + p``, which equals ``J⁺_λ (a − J̇q̇) + (I − J⁺_λ J) p``.
    """

    robot: RobotModel
    gains: ControllerGains = field(default_factory=ControllerGains)
    posture: np.ndarray | None = None  #: null-space posture ``(n,)``; default the start pose
    last_damping: float = 0.0  #: λ used in the last call
    last_sigma_min: float = 0.0  #: smallest singular value of J in the last call

    def __post_init__(self) -> None:
        from services.arm.kernel import ik_finish, ik_prepare

        self._ik_prepare, self._ik_finish = ik_prepare, ik_finish
        n = self.robot.n
        if self.posture is None:
            self.posture = self.robot.resolve_pose("middle")
        self._posture = np.ascontiguousarray(self.posture, dtype=float)
        self._J = np.zeros((6, n))
        self._K = np.eye(6)
        self._b0 = np.zeros(6)
        self._p = np.zeros(n)
        self._R = np.eye(3)
        self._omega = np.zeros(3)
        self._zero3 = np.zeros(3)

    def prepare(
        self,
        q: np.ndarray,
        dq: np.ndarray,
        *,
        J: np.ndarray | None = None,
        drift: np.ndarray | None = None,
        twist: np.ndarray | None = None,
        rotation: np.ndarray | None = None,
    ) -> None:
        """Command-independent part for state ``(q, dq)``; ``robot.update(q, dq)`` first.

        ``J`` (6, n), ``drift`` (6,) m/s², rad/s², ``twist`` (6,) m/s, rad/s and the EE
        ``rotation`` (3, 3) of this state may be passed when already computed (they are read
        from the robot model otherwise).

        ``(J Jᵀ)⁻¹`` comes from its Cholesky factor; the damping uses ``σ_min(J)² ≈
        1/‖(J Jᵀ)⁻¹‖_F``, a lower bound of the smallest eigenvalue of ``J Jᵀ`` (tight within
        √6), so damping starts at or slightly before ``σ_min = ε``: λ² = (1 − σ²/ε²) λ_max²
        below ε, else 0 (:func:`services.arm.kernel.ik_prepare`).
        """
        robot, g = self.robot, self.gains
        if J is None:
            J = robot.jacobian()
        sigma, lam = self._ik_prepare(
            J, robot.drift() if drift is None else drift, q, dq, self._posture,
            g.nullspace_kp, g.nullspace_kd, g.singular_epsilon, g.damping_max,
            self._K, self._b0, self._p,
        )
        self.last_sigma_min = sigma
        self.last_damping = lam
        self._J = J
        self._R = np.ascontiguousarray(robot.ee_placement().rotation) if rotation is None else rotation
        self._omega = (robot.ee_velocity() if twist is None else twist)[3:]

    def finish(
        self,
        linear_acceleration: np.ndarray,
        rotation_ref: np.ndarray,
        angular_velocity_ref: np.ndarray | None = None,
    ) -> np.ndarray:
        """Joint accelerations ``(n,)`` rad/s² for the command, after :meth:`prepare`.

        Args:
            linear_acceleration: desired EE linear acceleration ``(3,)`` m/s², base frame.
            rotation_ref: orientation reference ``(3, 3)``.
            angular_velocity_ref: angular velocity reference ``(3,)`` rad/s (default zero).
        """
        g = self.gains
        out = np.empty(self._p.shape[0])
        self._ik_finish(
            self._J, self._K, self._b0, self._p, self._omega, self._R, linear_acceleration,
            rotation_ref, self._zero3 if angular_velocity_ref is None else angular_velocity_ref,
            g.orientation_kp, g.orientation_kd, out,
        )
        return out

    def compute(
        self,
        q: np.ndarray,
        dq: np.ndarray,
        linear_acceleration: np.ndarray,
        rotation_ref: np.ndarray,
        angular_velocity_ref: np.ndarray | None = None,
    ) -> np.ndarray:
        """:meth:`prepare` + :meth:`finish` (``robot.update(q, dq)`` must have been called)."""
        self.prepare(q, dq)
        return self.finish(linear_acceleration, rotation_ref, angular_velocity_ref)


__all__ = [
    "CLAMP_ACCELERATION",
    "CLAMP_POSITION",
    "CLAMP_VELOCITY",
    "POSITION_GUARD",
    "AccelBounds",
    "AccelBoundsKernel",
    "ClampReport",
    "ControllerGains",
    "IKController",
    "ValidationLimits",
    "apply_accel_bounds",
    "clamp_joint_accel",
    "joint_accel_bounds",
    "validate_command",
]
