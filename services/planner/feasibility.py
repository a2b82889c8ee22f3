"""The planner's commands within the arm's joint acceleration limits.

The arm turns a Cartesian acceleration ``a (3,)`` into joint accelerations by inverse
kinematics, ``q̈ = J⁺ ([a; α] − J̇q̇) + (null-space posture)``, and clamps each joint to its
acceleration limit ``L``: a clamp changes the direction of the motion and, on a real arm, trips
its limit reflex. The PSM law knows nothing of joints: where a generalised motion runs near the
edge of the workspace (the arm stretched towards a far goal), the same Cartesian acceleration
needs far more of some joints than in the demonstration.

:class:`JointAccelerationScaling` therefore scales each PSM command by the largest
``s ∈ [0, 1]`` for which the joint accelerations that the linear part needs, with the drift,
stay within a fraction ``f`` of each limit::

    |J⁺ [s a; 0] − J⁺ J̇q̇|ᵢ ≤ f Lᵢ   for every joint i

with ``J⁺ = Jᵀ (J Jᵀ)⁻¹`` at the measured ``(q, q̇)``; a joint whose share the drift alone
exceeds sets no bound, and near a singular pose (``σ_min(J)`` below :data:`SINGULAR_SIGMA`,
where the arm's damped inverse bounds the joint accelerations) nothing is scaled. The rest of
each limit, ``(1 − f) L``, is left to what the planner does not model: the arm's orientation and
posture terms. Scaling keeps the command's direction; the PSM re-solves its law from the state it
gets at the next tick, so a scaled motion passes the same via-points a little later. Collision
braking (eq. 15) is never scaled (:class:`~services.planner.sequencer.TaskRunner` only scales
the motion itself).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from services.arm.controller import ControllerGains
from services.robot.model import RobotModel

__all__ = ["JointAccelerationScaling"]

#: Below this smallest singular value of ``J`` [m] (a lower bound, ``1/‖(J Jᵀ)⁻¹‖_F``) the
#: commands are not scaled: near a singular pose the undamped estimate of the joint accelerations
#: grows without bound, while the arm's damped inverse kinematics bounds them. It is where the
#: arm's damping starts by default (``[arm.gains] singular_epsilon``).
SINGULAR_SIGMA: float = ControllerGains.model_fields["singular_epsilon"].default


#: The joint accelerations per unit command (``J⁺`` and the drift's share) are recomputed at
#: least this often [ticks] ...
REFRESH_TICKS = 10
#: ... and whenever the cached ones put a command above this fraction of each joint's share: a
#: command below it is passed as it is (over 10 ticks at 500 Hz the joints move by at most their
#: velocity limit × 20 ms, which changes ``J⁺`` far less than the 25 % margin).
QUICK_FRACTION = 0.75

Joints = Callable[[], "tuple[NDArray[np.float64], NDArray[np.float64]] | None"]


class JointAccelerationScaling:
    """Scale factors of Cartesian commands for the robot ``robot`` (its own model data: it must
    not be the arm simulation's instance), using the fraction ``fraction`` ∈ (0, 1] of each joint
    acceleration limit (the planner counts the scaled commands per step).

    The joint accelerations per unit command ``M = J⁺[:, :3]`` (n, 3) and of the drift
    ``d₀ = −J⁺ J̇q̇`` (n,) are cached: recomputed every :data:`REFRESH_TICKS` ticks and whenever
    the cached ones put the command above :data:`QUICK_FRACTION` of a joint's share, so every
    command that is scaled is scaled with the current joints' values (and the kinematics, ~25 µs,
    run on few ticks)."""

    def __init__(self, robot: RobotModel, fraction: float) -> None:
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        self.robot = robot
        self.fraction = float(fraction)
        self._limit = fraction * np.asarray(robot.limits.acceleration, dtype=float)
        self._quick = QUICK_FRACTION * self._limit
        self._M = np.zeros((robot.n, 3))
        self._d0 = np.zeros(robot.n)
        self._singular = False
        self._quick_norm_sq = 0.0
        self._tick_at: int | None = None

    def _refresh(self, tick: int, joints: Joints) -> bool:
        """Recompute ``M`` and ``d₀`` at the joints ``joints()`` gives (``(q, dq)`` (n,) [rad,
        rad/s], or None when unknown: False, nothing cached)."""
        state = joints()
        if state is None:
            self._tick_at = None
            return False
        robot = self.robot
        robot.update(state[0], state[1])
        J = robot.jacobian()
        self._tick_at = tick
        try:
            K = np.linalg.inv(J @ J.T)
        except np.linalg.LinAlgError:
            self._singular = True
            return True
        # σ_min(J) may be below SINGULAR_SIGMA: the arm damps there
        self._singular = float((K * K).sum()) * SINGULAR_SIGMA**4 > 1.0
        JK = J.T @ K
        self._M = JK[:, :3].copy()
        self._d0 = -(JK @ robot.drift())
        # The largest |a| that keeps every joint below the quick share whatever a's direction:
        # |d₀ᵢ + Mᵢ·a| ≤ |d₀ᵢ| + ‖Mᵢ‖ |a| (one dot product per tick instead of the joint vector).
        room = (self._quick - np.abs(self._d0)) / np.maximum(np.linalg.norm(self._M, axis=1), 1e-12)
        r = max(0.0, float(room.min()))
        self._quick_norm_sq = r * r
        return True

    def scale(self, a: NDArray[np.float64], tick: int, joints: Joints) -> float:
        """The factor ``s ∈ [0, 1]`` for the command ``a (3,)`` [m/s²] at control tick ``tick``;
        ``joints()`` gives the state's ``(q, dq)`` (n,) [rad, rad/s] (called only when the cache
        is refreshed; None: unknown, the command passes). 1 when the command is within the
        limits as it is."""
        fresh = self._tick_at is not None and 0 <= tick - self._tick_at < REFRESH_TICKS
        if not fresh and not self._refresh(tick, joints):
            return 1.0
        if self._singular:
            return 1.0
        if fresh and float(a @ a) <= self._quick_norm_sq:
            return 1.0
        d_a = self._M @ a
        total = np.abs(d_a + self._d0)
        if fresh:
            if (total <= self._quick).all():
                return 1.0
            if self._tick_at != tick:
                self._refresh(tick, joints)
                if self._singular:
                    return 1.0
                d_a = self._M @ a
                total = np.abs(d_a + self._d0)
        lim = self._limit
        if (total <= lim).all():
            return 1.0
        # Per joint the factors s with |d_0 + s d_a| <= L form an interval; the command keeps
        # the largest s in [0, 1] that every joint allows. A joint whose share the drift alone
        # exceeds (a fast joint motion, not the command) sets no bound.
        d_0 = self._d0
        s = 1.0
        for i in np.flatnonzero(total > lim).tolist():
            da, d0, L = float(d_a[i]), float(d_0[i]), float(lim[i])
            if da == 0.0 or abs(d0) > L:
                continue
            hi = (L - d0) / da if da > 0.0 else (-L - d0) / da
            s = min(s, hi)
        return max(0.0, s)
