"""The simulated arm's per-tick arithmetic, compiled (numba, nopython mode).

The arm runs one tick every 1–2 ms for as long as the stack runs. Written with numpy, the
controller and the limit clamps were ~60 calls a tick on 6- and 7-element arrays, each paying
numpy's dispatch; after every 1–2 ms sleep that code ran from cold caches and cost several
times its warm time. Here each phase of the tick is one compiled call on plain loops:

* :func:`ik_prepare`: ``J Jᵀ``, its Cholesky inverse with the damping of the singular-value
  estimate, the null-space posture term and the command-independent part of the right-hand side;
* :func:`ik_finish`: the orientation PD (``log₃(R_ref Rᵀ)``) and ``q̈ = Jᵀ K b + p``;
* :func:`accel_bounds`: the joint-acceleration interval that keeps the next state within the
  position, velocity and acceleration limits;
* :func:`bound_and_integrate`: the clamps and one semi-implicit Euler step.

The equations are documented where they are used (:mod:`services.arm.controller`). Every
function takes its outputs as preallocated arrays. IEEE semantics are kept (no fast-math):
the results differ from the numpy formulation only by the rounding of sums taken in another
order (~1e-16 relative).

Compiled code is cached next to this file (``__pycache__``; numba falls back to
``$NUMBA_CACHE_DIR`` or the user's cache directory where that is not writable), so only the
first start after an install compiles (~2–5 s); :func:`warm_up` compiles every kernel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from services.arm.controller import CLAMP_ACCELERATION, CLAMP_POSITION, CLAMP_VELOCITY, POSITION_GUARD

# cache: compiled once per install; error_model numpy: a division by zero gives inf/nan as in
# numpy (the callers check finiteness) instead of raising.
_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

@njit(**_JIT)
def spd_inverse(A: np.ndarray, K: np.ndarray) -> float:
    """``K = A⁻¹`` for a symmetric positive-definite ``A (m, m)`` by Cholesky; returns
    ``1/‖A⁻¹‖_F`` (a lower bound of ``A``'s smallest eigenvalue, within a factor √m), or 0 with
    ``K = I`` if ``A`` is not positive definite."""
    m = A.shape[0]
    L = np.zeros((m, m))
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:  # also NaN
            K[:, :] = 0.0
            for i in range(m):
                K[i, i] = 1.0
            return 0.0
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, m):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    # Li = L⁻¹ (lower triangular), then A⁻¹ = Liᵀ Li.
    Li = np.zeros((m, m))
    for j in range(m):
        Li[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, m):
            t = 0.0
            for k in range(j, i):
                t -= L[i, k] * Li[k, j]
            Li[i, j] = t / L[i, i]
    fro2 = 0.0
    for i in range(m):
        for j in range(i + 1):
            t = 0.0
            for k in range(i, m):
                t += Li[k, i] * Li[k, j]
            K[i, j] = t
            K[j, i] = t
            fro2 += t * t if i == j else 2.0 * t * t
    return 1.0 / math.sqrt(fro2)


@njit(**_JIT)
def ik_prepare(
    J: np.ndarray, drift: np.ndarray, q: np.ndarray, dq: np.ndarray, posture: np.ndarray,
    kp_n: float, kd_n: float, eps: float, lam_max: float,
    K: np.ndarray, b0: np.ndarray, p: np.ndarray,
) -> tuple[float, float]:
    """The command-independent part of the IK law for ``J (6, n)``, ``drift = J̇q̇ (6,)``,
    ``q, dq, posture (n,)``: fills ``K = (J Jᵀ + λ² I)⁻¹ (6, 6)``, ``p = Kp_n (posture − q) −
    Kd_n q̇ (n,)`` and ``b0 = −J̇q̇ − J p (6,)``; returns ``(σ, λ)``: the estimate of ``J``'s
    smallest singular value and the damping used (λ² = (1 − σ²/ε²) λ_max² below ε, else 0)."""
    m, n = J.shape
    A = np.empty((m, m))
    for i in range(m):
        for j in range(i + 1):
            t = 0.0
            for k in range(n):
                t += J[i, k] * J[j, k]
            A[i, j] = t
            A[j, i] = t
    sigma = math.sqrt(spd_inverse(A, K))
    lam2 = 0.0 if sigma >= eps else (1.0 - (sigma / eps) ** 2) * lam_max * lam_max
    if lam2 > 0.0:
        for i in range(m):
            A[i, i] += lam2
        spd_inverse(A, K)
    for k in range(n):
        p[k] = kp_n * (posture[k] - q[k]) - kd_n * dq[k]
    for i in range(m):
        t = 0.0
        for k in range(n):
            t += J[i, k] * p[k]
        b0[i] = -drift[i] - t
    return sigma, math.sqrt(lam2)


@njit(**_JIT)
def log3(R: np.ndarray, out: np.ndarray) -> None:
    """``out (3,)`` = the rotation vector of ``R (3, 3)`` (angle θ ∈ [0, π] times the unit
    axis): the antisymmetric part scaled by θ / (2 sin θ) (1/2 near θ = 0), and, within 0.01 rad
    of π where that loses precision, the axis from the diagonal with the signs of the
    antisymmetric part."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr >= 3.0:
        tr, theta = 3.0, 0.0
    elif tr <= -1.0:
        tr, theta = -1.0, math.pi
    else:
        theta = math.acos((tr - 1.0) / 2.0)
    if theta >= math.pi - 1e-2:
        cphi = -(tr - 1.0) / 2.0
        beta = theta * theta / (1.0 + cphi)
        t0 = (R[0, 0] + cphi) * beta
        t1 = (R[1, 1] + cphi) * beta
        t2 = (R[2, 2] + cphi) * beta
        out[0] = (1.0 if R[2, 1] > R[1, 2] else -1.0) * (math.sqrt(t0) if t0 > 0.0 else 0.0)
        out[1] = (1.0 if R[0, 2] > R[2, 0] else -1.0) * (math.sqrt(t1) if t1 > 0.0 else 0.0)
        out[2] = (1.0 if R[1, 0] > R[0, 1] else -1.0) * (math.sqrt(t2) if t2 > 0.0 else 0.0)
        return
    # θ / sin θ = 1 + θ²/6 + …: 1 to double precision below ~1e-4 rad (θ² / 6 < 2e-9, and the
    # antisymmetric part is itself ~θ there).
    t = (theta / math.sin(theta) if theta > 1e-4 else 1.0) / 2.0
    out[0] = t * (R[2, 1] - R[1, 2])
    out[1] = t * (R[0, 2] - R[2, 0])
    out[2] = t * (R[1, 0] - R[0, 1])


@njit(**_JIT)
def ik_finish(
    J: np.ndarray, K: np.ndarray, b0: np.ndarray, p: np.ndarray, omega: np.ndarray,
    R: np.ndarray, linear_acceleration: np.ndarray, R_ref: np.ndarray,
    angular_velocity_ref: np.ndarray, kp_r: float, kd_r: float, ddq: np.ndarray,
) -> None:
    """``ddq (n,) = Jᵀ K b + p`` with ``b = b0 + [ẍ_des; Kp_R log₃(R_ref Rᵀ) + Kd_R (ω_ref −
    ω)]`` (after :func:`ik_prepare`); ``omega`` (3,) the measured angular velocity, ``R`` the
    measured rotation, ``angular_velocity_ref`` (3,) (zeros when none)."""
    m, n = J.shape
    E = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            E[i, j] = R_ref[i, 0] * R[j, 0] + R_ref[i, 1] * R[j, 1] + R_ref[i, 2] * R[j, 2]
    w = np.empty(3)
    log3(E, w)
    b = np.empty(m)
    for i in range(3):
        b[i] = b0[i] + linear_acceleration[i]
        b[3 + i] = b0[3 + i] + (kp_r * w[i] + kd_r * (angular_velocity_ref[i] - omega[i]))
    y = np.empty(m)
    for i in range(m):
        t = 0.0
        for j in range(m):
            t += K[i, j] * b[j]
        y[i] = t
    for k in range(n):
        t = 0.0
        for i in range(m):
            t += J[i, k] * y[i]
        ddq[k] = t + p[k]


@njit(**_JIT)
def accel_bounds(
    q: np.ndarray, dq: np.ndarray, lower: np.ndarray, upper: np.ndarray, vmax: np.ndarray,
    amax: np.ndarray, brake: np.ndarray, dt: float,
    lo: np.ndarray, hi: np.ndarray, lo_is_velocity: np.ndarray, hi_is_velocity: np.ndarray,
) -> None:
    """The joint-acceleration interval ``[lo, hi]`` (n,) rad/s² for the state ``q`` (n,) rad,
    ``dq`` (n,) rad/s: the next velocity within ``±vmax`` and below the stop speed for the
    distance to each position limit at the deceleration ``brake`` (n,) rad/s², ``|ddq| ≤
    amax``; a joint already outside that set gets the hardest allowed deceleration toward it.
    ``*_is_velocity``: that side's bound comes from the velocity limit.

    Stop speed for a distance d: ``v = a (sqrt(2.25 dt² + 2 d / a) − 1.5 dt)`` (discrete braking
    with the semi-implicit Euler integrator covers v·dt + v²/(2a) + v·dt/2)."""
    c0 = 2.25 * dt * dt
    c2 = 1.5 * dt
    for j in range(q.shape[0]):
        d_up = max(upper[j] - q[j], 0.0)
        d_lo = max(q[j] - lower[j], 0.0)
        s_up = (math.sqrt(d_up * (2.0 / brake[j]) + c0) - c2) * brake[j]
        s_lo = (math.sqrt(d_lo * (2.0 / brake[j]) + c0) - c2) * brake[j]
        v_up = min(vmax[j], s_up)
        v_lo = -min(vmax[j], s_lo)
        h = min(amax[j], (v_up - dq[j]) / dt)
        l_ = max(-amax[j], (v_lo - dq[j]) / dt)
        if l_ > h:
            v = min(max(dq[j], v_lo), v_up)
            l_ = h = min(max((v - dq[j]) / dt, -amax[j]), amax[j])
        lo[j] = l_
        hi[j] = h
        lo_is_velocity[j] = s_lo >= vmax[j]
        hi_is_velocity[j] = s_up >= vmax[j]


@njit(**_JIT)
def apply_bounds(
    ddq_in: np.ndarray, amax: np.ndarray, lo: np.ndarray, hi: np.ndarray,
    lo_is_velocity: np.ndarray, hi_is_velocity: np.ndarray, ddq: np.ndarray,
) -> int:
    """``ddq`` (n,) = ``ddq_in`` scaled uniformly into ``±amax`` (keeps the Cartesian
    direction), then clipped into ``[lo, hi]``; returns the active clamps
    (:data:`CLAMP_ACCELERATION`, :data:`CLAMP_VELOCITY`, :data:`CLAMP_POSITION`)."""
    n = ddq_in.shape[0]
    ratio = 0.0
    for j in range(n):
        r = abs(ddq_in[j]) / amax[j]
        if r > ratio or r != r:
            ratio = r
    flags = 0
    if ratio > 1.0:
        flags |= CLAMP_ACCELERATION
        for j in range(n):
            ddq[j] = ddq_in[j] / ratio
    else:
        for j in range(n):
            ddq[j] = ddq_in[j]
    for j in range(n):
        if ddq[j] < lo[j]:
            ddq[j] = lo[j]
            flags |= CLAMP_VELOCITY if lo_is_velocity[j] else CLAMP_POSITION
        elif ddq[j] > hi[j]:
            ddq[j] = hi[j]
            flags |= CLAMP_VELOCITY if hi_is_velocity[j] else CLAMP_POSITION
    return flags


@njit(**_JIT)
def bound_and_integrate(
    ddq_in: np.ndarray, q: np.ndarray, dq: np.ndarray, dt: float, amax: np.ndarray,
    lo: np.ndarray, hi: np.ndarray, lo_is_velocity: np.ndarray, hi_is_velocity: np.ndarray,
    lower: np.ndarray, upper: np.ndarray, ddq: np.ndarray, dq_next: np.ndarray, q_next: np.ndarray,
) -> int:
    """:func:`apply_bounds`, then one semi-implicit Euler step ``dq_next = dq + ddq dt``,
    ``q_next = q + dq_next dt`` (all (n,)); a joint that would still leave its position limits
    (never from a viable state) is held at the limit with zero velocity
    (:data:`POSITION_GUARD`). Returns the clamp bits."""
    flags = apply_bounds(ddq_in, amax, lo, hi, lo_is_velocity, hi_is_velocity, ddq)
    for j in range(q.shape[0]):
        v = dq[j] + ddq[j] * dt
        x = q[j] + v * dt
        if x < lower[j] or x > upper[j]:
            flags |= POSITION_GUARD
            x = min(max(x, lower[j]), upper[j])
            v = 0.0
        dq_next[j] = v
        q_next[j] = x
    return flags


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the arm's argument types."""
    n = 7
    J = np.eye(6, n)
    v6, vn = np.zeros(6), np.zeros(n)
    K = np.empty((6, 6))
    ik_prepare(J, v6, vn, vn, vn, 1.0, 1.0, 0.04, 0.05, K, np.empty(6), np.empty(n))
    ik_finish(J, K, v6, vn, np.zeros(3), np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), 1.0, 1.0,
              np.empty(n))
    ones = np.ones(n)
    flags_lo, flags_hi = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    lo, hi = np.empty(n), np.empty(n)
    accel_bounds(vn, vn, -ones, ones, ones, ones, ones, 0.002, lo, hi, flags_lo, flags_hi)
    apply_bounds(vn, ones, lo, hi, flags_lo, flags_hi, np.empty(n))
    bound_and_integrate(vn, vn, vn, 0.002, ones, lo, hi, flags_lo, flags_hi, -ones, ones,
                        np.empty(n), np.empty(n), np.empty(n))


__all__ = [
    "accel_bounds",
    "apply_bounds",
    "bound_and_integrate",
    "ik_finish",
    "ik_prepare",
    "log3",
    "spd_inverse",
    "warm_up",
]
