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
posture terms. Scaling
keeps the command's direction; the PSM re-solves its law from the state it gets at the next tick,
so a scaled motion passes the same via-points a little later. Collision braking (eq. 15) is
never scaled (:class:`~services.planner.sequencer.TaskRunner` only scales the motion itself).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.robot.model import RobotModel

__all__ = ["JointAccelerationScaling"]

#: Below this smallest singular value of ``J`` [m] (a lower bound, ``1/‖(J Jᵀ)⁻¹‖_F``) the
#: commands are not scaled: near a singular pose the undamped estimate of the joint accelerations
#: grows without bound, while the arm's damped inverse kinematics bounds them (its
#: ``[arm.gains] singular_epsilon``, 0.04 by default, is where its damping starts).
SINGULAR_SIGMA = 0.04


class JointAccelerationScaling:
    """Scale factors of Cartesian commands for the robot ``robot`` (its own model data: it must
    not be the arm simulation's instance), using the fraction ``fraction`` ∈ (0, 1] of each joint
    acceleration limit. ``scaled_ticks`` counts the commands scaled, ``min_scale`` is the
    smallest factor so far."""

    def __init__(self, robot: RobotModel, fraction: float) -> None:
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        self.robot = robot
        self.fraction = float(fraction)
        self._limit = fraction * np.asarray(robot.limits.acceleration, dtype=float)
        self._b = np.zeros((6, 2))  # columns: [a; 0] and −J̇q̇
        self.scaled_ticks = 0
        self.min_scale = 1.0

    def scale(self, q: NDArray[np.float64], dq: NDArray[np.float64], a: NDArray[np.float64]) -> float:
        """The factor ``s ∈ [0, 1]`` for the command ``a (3,)`` [m/s²] at joints ``q, dq (n,)``
        [rad, rad/s]: 1 when the command is within the limits as it is."""
        robot = self.robot
        robot.update(q, dq)
        J = robot.jacobian()
        try:
            K = np.linalg.inv(J @ J.T)
        except np.linalg.LinAlgError:
            return 1.0
        if float((K * K).sum()) * SINGULAR_SIGMA**4 > 1.0:
            return 1.0  # σ_min(J) may be below SINGULAR_SIGMA: the arm damps there
        b = self._b
        b[:3, 0] = a
        b[:, 1] = robot.drift()
        b[:, 1] *= -1.0
        # (n, 2): the joint accelerations of the command and of the drift
        ddq = J.T @ (K @ b)
        d_a, d_0 = ddq[:, 0], ddq[:, 1]
        lim = self._limit
        total = np.abs(d_a + d_0)
        if (total <= lim).all():
            return 1.0
        # Per joint the factors s with |d_0 + s d_a| <= L form an interval; the command keeps
        # the largest s in [0, 1] that every joint allows. A joint whose share the drift alone
        # exceeds (a fast joint motion, not the command) sets no bound.
        s = 1.0
        for i in np.flatnonzero(total > lim).tolist():
            da, d0, L = float(d_a[i]), float(d_0[i]), float(lim[i])
            if da == 0.0 or abs(d0) > L:
                continue
            hi = (L - d0) / da if da > 0.0 else (-L - d0) / da
            s = min(s, hi)
        s = max(0.0, s)
        self.scaled_ticks += 1
        self.min_scale = min(self.min_scale, s)
        return s
