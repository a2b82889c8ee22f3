"""End-effector orientation as a function of the time to completion (the paper's coupling).

The paper couples the hand's orientation to the time to completion ``t_e`` of the z component:
the orientation is not a PSM dimension of its own but follows the progress of the motion.
:class:`OrientationProfile` learns it from a demonstration — the recorded orientations
``R(τ)`` over the demonstration time ``τ ∈ [0, T]`` — and gives, on the way, the reference for a
phase ``s ∈ [0, 1]`` (``τ = s T``) by spherical linear interpolation (scipy's ``Slerp``, sampled
once into a table so the control path does plain float arithmetic).

At run time (:class:`OrientationTracker`) the phase comes from ``t_e``: ``s = 1 − t_e / t_e0``
with ``t_e0`` the time to completion at the step's first tick, kept monotonic (a goal that
jumps away raises ``t_e`` but never turns the hand back). A start orientation different from the
demonstrated one (the arm ends the previous step slightly turned) is blended out over the motion:
``R_ref(s) = exp((1 − s) log ΔR) R(s T)`` with ``ΔR = R_start R(0)ᵀ``, so the reference starts at
the arm's own orientation and ends at the demonstrated final one.

Quaternions are ``(x, y, z, w)`` with ``w ≥ 0`` (the bus convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["OrientationProfile", "OrientationTracker"]

#: Samples of the phase table (a 3.5 s demonstration: one per 7 ms; Slerp is exact in between).
TABLE_SIZE = 501


@dataclass(frozen=True)
class OrientationProfile:
    """A demonstration's orientation over its phase, tabulated.

    ``quats (N, 4)`` xyzw at the phases ``s = linspace(0, 1, N)``; ``omega (N, 3)`` [rad/s] the
    demonstration's angular velocity there (base frame) at the demonstrated pace; ``duration``
    [s] the demonstration's length ``T``.
    """

    quats: NDArray[np.float64]
    omega: NDArray[np.float64]
    duration: float

    @cached_property
    def _quat_rows(self) -> list[list[float]]:
        """``quats`` as nested lists of floats (read by :meth:`at` every tick)."""
        return self.quats.tolist()

    @cached_property
    def _omega_rows(self) -> list[list[float]]:
        """``omega`` [rad/s] as nested lists of floats (read by :meth:`at` every tick)."""
        return self.omega.tolist()

    @classmethod
    def fit(cls, t: ArrayLike, quats_xyzw: ArrayLike, size: int = TABLE_SIZE) -> OrientationProfile:
        """Learn from a demonstration: ``t (T,)`` [s] increasing, ``quats_xyzw (T, 4)``.

        Raises:
            ValueError: shapes disagree, fewer than two samples, times not increasing, or a
                quaternion of zero or non-finite norm.
        """
        t = np.asarray(t, dtype=float)
        Q = np.asarray(quats_xyzw, dtype=float)
        if t.ndim != 1 or Q.shape != (t.size, 4) or t.size < 2:
            raise ValueError(f"orientation demo: t (T,) and quats (T, 4) needed, got {t.shape}, {Q.shape}")
        norms = np.linalg.norm(Q, axis=1)
        if not (np.all(np.isfinite(Q)) and np.all(norms > 1e-9)):
            raise ValueError("orientation demo: quaternions must be finite and non-zero")
        if np.any(np.diff(t) <= 0):
            raise ValueError("orientation demo: times must increase")
        rots = Rotation.from_quat(Q / norms[:, None])
        slerp = Slerp(t - t[0], rots)
        T = float(t[-1] - t[0])
        tau = np.linspace(0.0, T, size)
        table = slerp(tau)
        quats = table.as_quat()
        quats[quats[:, 3] < 0] *= -1.0
        # Angular velocity of the table (central differences of the rotation, base frame).
        rv = (table[1:] * table[:-1].inv()).as_rotvec() / np.diff(tau)[:, None]
        omega = np.zeros((size, 3))
        omega[1:-1] = 0.5 * (rv[1:] + rv[:-1])
        omega[0], omega[-1] = rv[0], rv[-1]
        return cls(quats, omega, T)

    @classmethod
    def constant(cls, quat_xyzw: ArrayLike, duration: float = 1.0) -> OrientationProfile:
        """A profile that holds one orientation (a demonstration that does not turn the hand)."""
        q = np.asarray(quat_xyzw, dtype=float)
        q = q / np.linalg.norm(q)
        if q[3] < 0:
            q = -q
        return cls(np.tile(q, (2, 1)), np.zeros((2, 3)), float(duration))

    def at(self, s: float, omega_scale: float = 1.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(quat (4,), omega (3,))`` at phase ``s`` (clamped to [0, 1]); omega at the
        demonstrated pace [rad/s] times ``omega_scale``."""
        n = self.quats.shape[0] - 1
        u = min(max(s, 0.0), 1.0) * n
        i = min(int(u), n - 1)
        w = u - i
        # Plain floats on the two table rows (a per-tick path: numpy costs ~1 µs per call on
        # 4-vectors in a warm loop, ~10 µs in the control loop's cold caches), with numpy's
        # elementwise operations in the same order.
        a0, a1, a2, a3 = self._quat_rows[i]
        b0, b1, b2, b3 = self._quat_rows[i + 1]
        dot = a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3
        u0, wb = 1.0 - w, (w if dot >= 0 else -w)  # nlerp: exact to 1e-6 at table steps
        q0, q1, q2, q3 = u0 * a0 + wb * b0, u0 * a1 + wb * b1, u0 * a2 + wb * b2, u0 * a3 + wb * b3
        n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        q0, q1, q2, q3 = q0 / n, q1 / n, q2 / n, q3 / n
        if q3 < 0:
            q0, q1, q2, q3 = -q0, -q1, -q2, -q3
        o0, o1 = self._omega_rows[i], self._omega_rows[i + 1]
        omega = (
            (u0 * o0[0] + w * o1[0]) * omega_scale,
            (u0 * o0[1] + w * o1[1]) * omega_scale,
            (u0 * o0[2] + w * o1[2]) * omega_scale,
        )
        return np.array([q0, q1, q2, q3]), np.array(omega)

    @property
    def turns(self) -> bool:
        """True if the demonstration turns the hand by more than 0.1°."""
        q0 = self.quats[0]
        return bool(np.min(np.abs(self.quats @ q0)) < math.cos(math.radians(0.05)))


class OrientationTracker:
    """The orientation reference of one step: :meth:`update` with the reference dimension's
    ``t_e`` [s] gives ``(quat_xyzw (4,), omega (3,) [rad/s])`` (see the module docstring).

    The start-offset blend is applied to the whole table once, here, so :meth:`update` is a
    table lookup."""

    def __init__(self, profile: OrientationProfile, start_quat_xyzw: ArrayLike) -> None:
        q0 = Rotation.from_quat(np.asarray(start_quat_xyzw, dtype=float))
        delta = (q0 * Rotation.from_quat(profile.quats[0]).inv()).as_rotvec()
        if float(np.linalg.norm(delta)) > 1e-9:
            s = np.linspace(0.0, 1.0, profile.quats.shape[0])
            table = (
                Rotation.from_rotvec((1.0 - s)[:, None] * delta) * Rotation.from_quat(profile.quats)
            ).as_quat()
            table[table[:, 3] < 0] *= -1.0
            profile = OrientationProfile(table, profile.omega, profile.duration)
        self.profile = profile
        self._te0: float | None = None
        self._rate = 0.0
        self.phase = 0.0

    def update(self, time_to_go: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The reference for the current ``t_e`` of the reference dimension [s]."""
        te = max(0.0, float(time_to_go))
        if self._te0 is None:
            self._te0 = te
            self._rate = self.profile.duration / te if te > 1e-9 else 0.0
        s = 1.0 if self._te0 <= 1e-9 else 1.0 - te / self._te0
        if s > self.phase:
            self.phase = min(1.0, s)
        return self.profile.at(self.phase, self._rate if self.phase < 1.0 else 0.0)
