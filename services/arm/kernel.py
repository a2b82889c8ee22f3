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
* :func:`bound_and_integrate`: the clamps and one semi-implicit Euler step;
* :func:`chain_kinematics`: for a serial chain of 1-DoF joints (the Panda and most arms), the
  end effector's placement, quaternion, Jacobian, twist, drift ``J̇q̇`` and acceleration in one
  pass, where Pinocchio needs six calls and the glue between them
  (:class:`services.arm.sim.SerialChain` extracts the chain from the Pinocchio model).

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


#: Joint kinds of :func:`chain_kinematics` (the Pinocchio joint models they stand for).
REVOLUTE_X, REVOLUTE_Y, REVOLUTE_Z, REVOLUTE, PRISMATIC = 0, 1, 2, 3, 4
#: Slices of :func:`chain_kinematics`'s output (the Jacobian follows at 34).
CHAIN_LAYOUT = {"position": (0, 3), "quat_xyzw": (3, 7), "twist": (7, 13), "acceleration": (13, 19),
                "drift": (19, 25), "rotation": (25, 34)}
CHAIN_JACOBIAN = 34


@njit(**_JIT)
def chain_kinematics(
    kind: np.ndarray, axis: np.ndarray, joint_R: np.ndarray, joint_p: np.ndarray,
    ee_R: np.ndarray, ee_p: np.ndarray, n_ee: int,
    q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, out: np.ndarray,
) -> None:
    """End-effector kinematics of a serial chain of ``n`` 1-DoF joints at ``(q, dq, ddq)`` (n,).

    Joint ``i`` sits at ``joint_R[i] (3, 3), joint_p[i] (3,)`` [m] in the frame of joint
    ``i − 1`` (the base for ``i = 0``) and moves by ``q[i]`` about (``REVOLUTE*``, rad) or along
    (``PRISMATIC``, m) its unit ``axis[i]`` (3,), given in its own frame; the end-effector frame
    is ``ee_R, ee_p`` in the frame of joint ``n_ee − 1`` (joints from ``n_ee`` on do not move it).

    Fills ``out (34 + 6 n,)``: ``[0:3]`` position [m], ``[3:7]`` quaternion (x, y, z, w) with
    ``w ≥ 0``, ``[7:13]`` twist [linear; angular] (m/s, rad/s), ``[13:19]`` the acceleration
    ``J q̈ + J̇q̇`` (m/s², rad/s²), ``[19:25]`` the drift ``J̇q̇``, ``[25:34]`` the rotation ``R``
    (3, 3) and ``[34:]`` the Jacobian ``J`` (6, n), row-major (:data:`CHAIN_LAYOUT`; all in the
    base frame, at the end effector's origin:
    Pinocchio's ``LOCAL_WORLD_ALIGNED``; the accelerations are classical, not spatial).

    The Jacobian's column for a revolute joint with world axis ``z`` at ``o`` is
    ``[z × (p − o); z]``, for a prismatic one ``[z; 0]``; the axis turns with the links before
    it (``ż = ω_before × z``), so ``J̇q̇`` sums ``(ż × (p − o) + z × (ṗ − ȯ)) q̇`` and ``ż q̇``
    (revolute) or ``ż q̇`` (prismatic) over the joints.
    """
    n = q.shape[0]
    z = np.zeros((n, 3))
    o = np.zeros((n, 3))
    Rp = np.eye(3)
    pp = np.zeros(3)
    Rj = np.empty((3, 3))
    for i in range(n_ee):
        # Joint i's frame before its motion: parent placement times the joint placement.
        for r in range(3):
            for c in range(3):
                Rj[r, c] = (Rp[r, 0] * joint_R[i, 0, c] + Rp[r, 1] * joint_R[i, 1, c]
                            + Rp[r, 2] * joint_R[i, 2, c])
        for r in range(3):
            o[i, r] = Rp[r, 0] * joint_p[i, 0] + Rp[r, 1] * joint_p[i, 1] + Rp[r, 2] * joint_p[i, 2] + pp[r]
            z[i, r] = Rj[r, 0] * axis[i, 0] + Rj[r, 1] * axis[i, 1] + Rj[r, 2] * axis[i, 2]
        k = kind[i]
        if k == PRISMATIC:
            for r in range(3):
                pp[r] = o[i, r] + z[i, r] * q[i]
                for c in range(3):
                    Rp[r, c] = Rj[r, c]
            continue
        for r in range(3):
            pp[r] = o[i, r]
        s, cq = math.sin(q[i]), math.cos(q[i])
        if k == REVOLUTE:
            # Rodrigues: R = I + s K + (1 − c) K² for the unit axis a (K = [a]×).
            ax, ay, az = axis[i, 0], axis[i, 1], axis[i, 2]
            v = 1.0 - cq
            M = np.empty((3, 3))
            M[0, 0] = cq + v * ax * ax
            M[0, 1] = v * ax * ay - s * az
            M[0, 2] = v * ax * az + s * ay
            M[1, 0] = v * ax * ay + s * az
            M[1, 1] = cq + v * ay * ay
            M[1, 2] = v * ay * az - s * ax
            M[2, 0] = v * ax * az - s * ay
            M[2, 1] = v * ay * az + s * ax
            M[2, 2] = cq + v * az * az
            for r in range(3):
                for c in range(3):
                    Rp[r, c] = Rj[r, 0] * M[0, c] + Rj[r, 1] * M[1, c] + Rj[r, 2] * M[2, c]
        else:
            # About a coordinate axis: columns a, b of the frame turn by q, the third stays.
            a = (k + 1) % 3
            b = (k + 2) % 3
            for r in range(3):
                ca, cb = Rj[r, a], Rj[r, b]
                Rp[r, a] = cq * ca + s * cb
                Rp[r, b] = cq * cb - s * ca
                Rp[r, k] = Rj[r, k]
    R = np.empty((3, 3))
    p = np.empty(3)
    for r in range(3):
        for c in range(3):
            R[r, c] = Rp[r, 0] * ee_R[0, c] + Rp[r, 1] * ee_R[1, c] + Rp[r, 2] * ee_R[2, c]
        p[r] = Rp[r, 0] * ee_p[0] + Rp[r, 1] * ee_p[1] + Rp[r, 2] * ee_p[2] + pp[r]
    # Jacobian (6, n), base frame at the end effector's origin.
    J = out[34:].reshape(6, n)
    J[:, :] = 0.0
    for i in range(n_ee):
        if kind[i] == PRISMATIC:
            for r in range(3):
                J[r, i] = z[i, r]
        else:
            dx, dy, dz = p[0] - o[i, 0], p[1] - o[i, 1], p[2] - o[i, 2]
            J[0, i] = z[i, 1] * dz - z[i, 2] * dy
            J[1, i] = z[i, 2] * dx - z[i, 0] * dz
            J[2, i] = z[i, 0] * dy - z[i, 1] * dx
            for r in range(3):
                J[3 + r, i] = z[i, r]
    twist = np.zeros(6)
    for r in range(6):
        t = 0.0
        for i in range(n_ee):
            t += J[r, i] * dq[i]
        twist[r] = t
    # Drift J̇q̇: the angular velocity and the velocity of each joint's origin, joint by joint.
    drift = np.zeros(6)
    w = np.zeros(3)  # angular velocity of the link before joint i
    for i in range(n_ee):
        vo = np.zeros(3)  # velocity of joint i's origin (a point of the link before it)
        for j in range(i):
            if kind[j] == PRISMATIC:
                for r in range(3):
                    vo[r] += z[j, r] * dq[j]
            else:
                dx, dy, dz = o[i, 0] - o[j, 0], o[i, 1] - o[j, 1], o[i, 2] - o[j, 2]
                vo[0] += (z[j, 1] * dz - z[j, 2] * dy) * dq[j]
                vo[1] += (z[j, 2] * dx - z[j, 0] * dz) * dq[j]
                vo[2] += (z[j, 0] * dy - z[j, 1] * dx) * dq[j]
        zd0 = w[1] * z[i, 2] - w[2] * z[i, 1]
        zd1 = w[2] * z[i, 0] - w[0] * z[i, 2]
        zd2 = w[0] * z[i, 1] - w[1] * z[i, 0]
        qd = dq[i]
        if kind[i] == PRISMATIC:
            drift[0] += zd0 * qd
            drift[1] += zd1 * qd
            drift[2] += zd2 * qd
            continue
        dx, dy, dz = p[0] - o[i, 0], p[1] - o[i, 1], p[2] - o[i, 2]
        ex, ey, ez = twist[0] - vo[0], twist[1] - vo[1], twist[2] - vo[2]
        drift[0] += (zd1 * dz - zd2 * dy + z[i, 1] * ez - z[i, 2] * ey) * qd
        drift[1] += (zd2 * dx - zd0 * dz + z[i, 2] * ex - z[i, 0] * ez) * qd
        drift[2] += (zd0 * dy - zd1 * dx + z[i, 0] * ey - z[i, 1] * ex) * qd
        drift[3] += zd0 * qd
        drift[4] += zd1 * qd
        drift[5] += zd2 * qd
        for r in range(3):
            w[r] += z[i, r] * qd
    # Quaternion of R (the largest-pivot conversion), w >= 0.
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    quat = np.empty(4)
    if tr > 0.0:
        t = math.sqrt(tr + 1.0)
        quat[3] = 0.5 * t
        t = 0.5 / t
        quat[0] = (R[2, 1] - R[1, 2]) * t
        quat[1] = (R[0, 2] - R[2, 0]) * t
        quat[2] = (R[1, 0] - R[0, 1]) * t
    else:
        a = 0
        if R[1, 1] > R[0, 0]:
            a = 1
        if R[2, 2] > R[a, a]:
            a = 2
        b = (a + 1) % 3
        c = (b + 1) % 3
        t = math.sqrt(R[a, a] - R[b, b] - R[c, c] + 1.0)
        quat[a] = 0.5 * t
        t = 0.5 / t
        quat[3] = (R[c, b] - R[b, c]) * t
        quat[b] = (R[b, a] + R[a, b]) * t
        quat[c] = (R[c, a] + R[a, c]) * t
    if quat[3] < 0.0:
        for r in range(4):
            quat[r] = -quat[r]
    for r in range(3):
        out[r] = p[r]
    for r in range(4):
        out[3 + r] = quat[r]
    for r in range(6):
        out[7 + r] = twist[r]
        t = drift[r]
        for i in range(n_ee):
            t += J[r, i] * ddq[i]
        out[13 + r] = t
        out[19 + r] = drift[r]
    for r in range(3):
        for c in range(3):
            out[25 + 3 * r + c] = R[r, c]


@njit(**_JIT)
def _put_varint(buf: np.ndarray, at: int, value: int) -> int:
    """Write ``value`` (uint64 bits) as a protobuf varint at ``buf[at]``; returns the end."""
    v = np.uint64(value)
    while v >= np.uint64(0x80):
        buf[at] = np.uint8((v & np.uint64(0x7F)) | np.uint64(0x80))
        v >>= np.uint64(7)
        at += 1
    buf[at] = np.uint8(v)
    return at + 1


@njit(**_JIT)
def _put_double(buf: np.ndarray, at: int, x: float) -> int:
    """Write ``x`` as 8 little-endian bytes at ``buf[at]``; returns the end."""
    bits = np.array([x]).view(np.uint64)[0]
    for i in range(8):
        buf[at + i] = np.uint8((bits >> np.uint64(8 * i)) & np.uint64(0xFF))
    return at + 8


@njit(**_JIT)
def _is_set(x: float) -> bool:
    """Whether proto3 serialises a double field holding ``x``: any bit set (``-0.0`` too)."""
    return x != 0.0 or math.copysign(1.0, x) < 0.0


@njit(**_JIT)
def _put_doubles_message(
    buf: np.ndarray, at: int, field: int, values: np.ndarray, start: int, count: int
) -> int:
    """A present sub-message of ``count`` double fields numbered 1… (``Vec3``, ``Quat``) holding
    ``values[start:start + count]``; returns the end."""
    size = 0
    for i in range(count):
        if _is_set(values[start + i]):
            size += 9
    at = _put_varint(buf, at, (field << 3) | 2)
    at = _put_varint(buf, at, size)
    for i in range(count):
        x = values[start + i]
        if _is_set(x):
            buf[at] = np.uint8(((i + 1) << 3) | 1)
            at = _put_double(buf, at + 1, x)
    return at


@njit(**_JIT)
def _put_packed(buf: np.ndarray, at: int, field: int, values: np.ndarray) -> int:
    """A packed ``repeated double`` field (omitted when empty); returns the end."""
    n = values.shape[0]
    if n == 0:
        return at
    at = _put_varint(buf, at, (field << 3) | 2)
    at = _put_varint(buf, at, 8 * n)
    for i in range(n):
        at = _put_double(buf, at, values[i])
    return at


@njit(**_JIT)
def encode_arm_state(
    buf: np.ndarray, names: np.ndarray, frame: np.ndarray, period: np.ndarray, time_ns: int, tick: int,
    q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, ee: np.ndarray,
    braking: bool, watchdog_tripped: bool, rejected_commands: int,
) -> int:
    """Serialise an ``ArmState`` into ``buf`` (uint8); returns its length, or -1 (nothing
    written) when ``buf`` could be too small for these arrays or ``ee`` is not (19,).

    The bytes equal protobuf's ``SerializeToString`` of the same message (fields in number
    order, proto3 scalars at their zero value omitted, every sub-message present):
    ``stamp_ns = sim_time_ns = time_ns`` [ns], ``tick``, the pre-serialised ``joint_names``
    field(s) ``names``, ``q, dq, ddq`` (n,), ``ee (19,)`` = position (3,) [m], quaternion
    (x, y, z, w), linear and angular velocity (3,) each, linear and angular acceleration (3,)
    each (fields 8–13 in that order), the pre-serialised ``frame_id`` field ``frame``, the
    flags and the counter, and the pre-serialised ``dt_s`` field ``period`` (uint8 arrays; empty
    for a field at its zero value).
    """
    # The largest message these arrays give: constant fields, three packed arrays (tag, 2-byte
    # length), six sub-messages of at most 4 doubles (tag, length, 9 bytes each), the varints.
    worst = names.shape[0] + frame.shape[0] + period.shape[0] + 6 * 38 + 48
    worst += (q.shape[0] + dq.shape[0] + ddq.shape[0]) * 8 + 3 * 11
    if worst > buf.shape[0] or ee.shape[0] != 19:
        return -1
    at = 0
    if time_ns != 0:
        at = _put_varint(buf, at, 1 << 3)
        at = _put_varint(buf, at, time_ns)
    if tick != 0:
        at = _put_varint(buf, at, 2 << 3)
        at = _put_varint(buf, at, tick)
    if time_ns != 0:
        at = _put_varint(buf, at, 3 << 3)
        at = _put_varint(buf, at, time_ns)
    for i in range(names.shape[0]):
        buf[at + i] = names[i]
    at += names.shape[0]
    at = _put_packed(buf, at, 5, q)
    at = _put_packed(buf, at, 6, dq)
    at = _put_packed(buf, at, 7, ddq)
    at = _put_doubles_message(buf, at, 8, ee, 0, 3)
    at = _put_doubles_message(buf, at, 9, ee, 3, 4)
    for k in range(4):
        at = _put_doubles_message(buf, at, 10 + k, ee, 7 + 3 * k, 3)
    for i in range(frame.shape[0]):
        buf[at + i] = frame[i]
    at += frame.shape[0]
    if braking:
        buf[at] = 15 << 3
        buf[at + 1] = 1
        at += 2
    if watchdog_tripped:
        at = _put_varint(buf, at, 16 << 3)
        buf[at] = 1
        at += 1
    if rejected_commands != 0:
        at = _put_varint(buf, at, 17 << 3)
        at = _put_varint(buf, at, rejected_commands)
    for i in range(period.shape[0]):
        buf[at + i] = period[i]
    return at + period.shape[0]


#: :func:`parse_cartesian_command` found a command it does not decide: decode it the general way.
COMMAND_SLOW = -1
#: Bits of an accepted command's :func:`parse_cartesian_command` result.
COMMAND_HAS_ORIENTATION, COMMAND_HAS_ANGULAR_VELOCITY = 1, 2
_U63 = np.uint64(1) << np.uint64(63)


@njit(**_JIT)
def _get_varint(buf: np.ndarray, at: int) -> tuple[np.uint64, int]:
    """The varint at ``buf[at]`` and the index after it; index -1 if it runs past the end or
    past 10 bytes."""
    v = np.uint64(0)
    shift = np.uint64(0)
    n = buf.shape[0]
    for _ in range(10):
        if at >= n:
            return np.uint64(0), -1
        b = np.uint64(buf[at])
        at += 1
        v |= (b & np.uint64(0x7F)) << shift
        if b < np.uint64(0x80):
            return v, at
        shift += np.uint64(7)
    return np.uint64(0), -1


@njit(**_JIT)
def _get_doubles(buf: np.ndarray, at: int, end: int, count: int, out: np.ndarray, start: int) -> bool:
    """A ``Vec3``/``Quat`` body ``buf[at:end]`` into ``out[start:start + count]`` (absent fields
    0.0): fields 1…count of wire type 1, each at most once; False for anything else."""
    seen = 0
    for i in range(count):
        out[start + i] = 0.0
    while at < end:
        key, at = _get_varint(buf, at)
        if at < 0:
            return False
        field = int(key >> np.uint64(3))
        if (key & np.uint64(7)) != np.uint64(1) or field < 1 or field > count or (seen >> field) & 1:
            return False
        seen |= 1 << field
        if at + 8 > end:
            return False
        out[start + field - 1] = buf[at:at + 8].view(np.float64)[0]
        at += 8
    return at == end


@njit(**_JIT)
def parse_cartesian_command(
    buf: np.ndarray, max_linear_acceleration: float, max_angular_velocity: float,
    quat_norm_tolerance: float, vals: np.ndarray, ints: np.ndarray,
) -> int:
    """Decode and check a serialised ``ArmCommand`` ``buf`` (uint8) that is a valid Cartesian
    command in its plainest form; anything else returns :data:`COMMAND_SLOW`, for the general
    path (protobuf's parser, ``command_from_message``, ``validate_command``) to decide.

    Decided here: fields 1–8, 10, 11 each at most once with their own wire types; ``mode`` =
    ``CARTESIAN_ACCELERATION``; ``linear_acceleration`` present; the ``Vec3``/``Quat`` bodies
    of plain double fields; ``source`` and ``frame_id`` ASCII; ``tick`` below 2⁶³; and the
    command passing ``validate_command`` (finite, within the bounds, the quaternion's norm
    within the tolerance). The values are those of the general path, bit for bit:
    ``vals (10,)`` = the linear acceleration (3,) [m/s²], the unit quaternion (x, y, z, w) with
    ``w ≥ 0``, the angular velocity reference (3,) [rad/s]; ``ints (2,)`` = ``stamp_ns``,
    ``tick``. Returns the bits :data:`COMMAND_HAS_ORIENTATION` and
    :data:`COMMAND_HAS_ANGULAR_VELOCITY` (which parts of ``vals`` hold a value).
    """
    n = buf.shape[0]
    at = 0
    seen = 0
    stamp = np.uint64(0)
    tick = np.uint64(0)
    mode = np.uint64(0)
    has_w = np.uint64(0)
    omega = np.zeros(3)
    while at < n:
        key, at = _get_varint(buf, at)
        if at < 0:
            return COMMAND_SLOW
        field = int(key >> np.uint64(3))
        wire = int(key & np.uint64(7))
        if field < 1 or field > 11 or field == 9 or (seen >> field) & 1:
            return COMMAND_SLOW
        seen |= 1 << field
        if field <= 4 or field == 8:
            if wire != 0:
                return COMMAND_SLOW
            v, at = _get_varint(buf, at)
            if at < 0:
                return COMMAND_SLOW
            if field == 1:
                stamp = v
            elif field == 3:
                tick = v
            elif field == 4:
                mode = v
            elif field == 8:
                has_w = v
            continue
        if wire != 2:
            return COMMAND_SLOW
        size, at = _get_varint(buf, at)
        if at < 0 or size > np.uint64(n - at):
            return COMMAND_SLOW
        end = at + int(size)
        if field == 5:
            ok = _get_doubles(buf, at, end, 3, vals, 0)
        elif field == 6:
            ok = _get_doubles(buf, at, end, 4, vals, 3)
        elif field == 7:
            ok = _get_doubles(buf, at, end, 3, omega, 0)
        else:  # source, frame_id: a string (ASCII here; UTF-8 is checked by the general path)
            ok = True
            for i in range(at, end):
                if buf[i] >= 0x80:
                    ok = False
                    break
        if not ok:
            return COMMAND_SLOW
        at = end
    if mode != np.uint64(1) or not (seen >> 5) & 1 or tick >= _U63 or has_w > np.uint64(1):
        return COMMAND_SLOW
    # The checks of validate_command, in its order and with its arithmetic.
    sq = vals[0] * vals[0]
    sq += vals[1] * vals[1]
    sq += vals[2] * vals[2]
    if not math.isfinite(sq) or math.sqrt(sq) > max_linear_acceleration:
        return COMMAND_SLOW
    flags = 0
    if (seen >> 6) & 1:
        sq = vals[3] * vals[3]
        sq += vals[4] * vals[4]
        sq += vals[5] * vals[5]
        sq += vals[6] * vals[6]
        if not math.isfinite(sq):
            return COMMAND_SLOW
        norm = math.sqrt(sq)
        if abs(norm - 1.0) > quat_norm_tolerance:
            return COMMAND_SLOW
        for i in range(3, 7):
            vals[i] = vals[i] / norm
        if vals[6] < 0:
            for i in range(3, 7):
                vals[i] = -vals[i]
        flags |= COMMAND_HAS_ORIENTATION
    if has_w == np.uint64(1):
        sq = omega[0] * omega[0]
        sq += omega[1] * omega[1]
        sq += omega[2] * omega[2]
        if not math.isfinite(sq) or math.sqrt(sq) > max_angular_velocity:
            return COMMAND_SLOW
        for i in range(3):
            vals[7 + i] = omega[i]
        flags |= COMMAND_HAS_ANGULAR_VELOCITY
    ints[0] = np.int64(stamp)
    ints[1] = np.int64(tick)
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
    kind = np.full(n, REVOLUTE_Z, dtype=np.int64)
    axes = np.zeros((n, 3))
    axes[:, 2] = 1.0
    out = np.empty(CHAIN_JACOBIAN + 6 * n)
    chain_kinematics(kind, axes, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.eye(3), np.zeros(3), n,
                     vn, vn, vn, out)
    b = np.empty(0, dtype=np.uint8)
    encode_arm_state(np.empty(1024, dtype=np.uint8), b, b, b, 1, 1, vn, vn, vn, out[:19], True, True, 1)
    parse_cartesian_command(np.frombuffer(b"\x20\x01", dtype=np.uint8), 1.0, 1.0, 0.1, np.empty(10),
                            np.empty(2, dtype=np.int64))


__all__ = [
    "accel_bounds",
    "apply_bounds",
    "bound_and_integrate",
    "chain_kinematics",
    "encode_arm_state",
    "ik_finish",
    "ik_prepare",
    "log3",
    "parse_cartesian_command",
    "spd_inverse",
    "warm_up",
]
