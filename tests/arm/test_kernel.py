"""The arm's compiled per-tick kernels against the numpy / Pinocchio formulation of the same
equations (``services.arm.kernel``)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from services.arm import kernel
from services.arm.controller import (
    CLAMP_ACCELERATION,
    CLAMP_POSITION,
    CLAMP_VELOCITY,
    POSITION_GUARD,
)
from services.robot.model import RobotModel

N = 7


def _spd(rng: np.random.Generator, cond: float = 1e3) -> np.ndarray:
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    return Q @ np.diag(np.geomspace(1.0, 1.0 / cond, 6) * rng.uniform(0.1, 10.0)) @ Q.T


def test_spd_inverse_equals_the_inverse_and_gives_the_frobenius_bound() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        A = _spd(rng, 10 ** rng.uniform(0, 8))
        K = np.empty((6, 6))
        s = kernel.spd_inverse(A, K)
        ref = np.linalg.inv(A)
        scale = np.abs(ref).max()
        np.testing.assert_allclose(K, ref, rtol=0, atol=1e-9 * scale)
        assert np.array_equal(K, K.T)
        assert s == pytest.approx(1.0 / np.linalg.norm(ref), rel=1e-9)
        assert s <= np.linalg.eigvalsh(A).min() * (1 + 1e-9)  # a lower bound of λ_min


def test_spd_inverse_of_a_matrix_that_is_not_positive_definite() -> None:
    K = np.full((6, 6), 7.0)
    A = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -1e-3])
    assert kernel.spd_inverse(A, K) == 0.0
    np.testing.assert_array_equal(K, np.eye(6))
    A[5, 5] = np.nan
    assert kernel.spd_inverse(A, K) == 0.0


@pytest.mark.parametrize(
    "angles",
    [
        np.geomspace(1e-12, 1e-2, 40),  # near the identity (the Taylor branch below 1e-4)
        np.linspace(0.05, math.pi - 0.05, 60),  # nominal
        math.pi - np.geomspace(1e-12, 0.02, 40),  # within and beside the near-π branch
        np.array([math.pi]),
    ],
    ids=["small", "nominal", "near-pi", "pi"],
)
def test_log3_matches_pinocchio(angles: np.ndarray) -> None:
    rng = np.random.default_rng(2)
    out = np.empty(3)
    for theta in angles:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(theta * axis).as_matrix()
        kernel.log3(R, out)
        ref = pin.log3(R)
        # Toward π the antisymmetric part vanishes (rounding / sin θ), and the axis from the
        # diagonal within 0.01 rad of π is as precise as the square root of the rounding.
        tol = 1e-7 if theta > math.pi - 1e-2 else 1e-12 if theta < 2.0 else 1e-13 / math.sin(theta)
        if theta == math.pi:  # ±axis are the same rotation
            assert min(np.abs(out - ref).max(), np.abs(out + ref).max()) < tol
        else:
            np.testing.assert_allclose(out, ref, rtol=0, atol=tol)
        np.testing.assert_allclose(pin.exp3(out), R, rtol=0, atol=1e-7)


def _reference_ik(J, drift, q, dq, posture, g, omega, R, a_lin, R_ref, w_ref):
    """The IK law with numpy: damped pseudo-inverse, posture in the null space, orientation PD."""
    A = J @ J.T
    s = 1.0 / np.linalg.norm(np.linalg.inv(A)) if np.linalg.eigvalsh(A).min() > 0 else 0.0
    sigma = math.sqrt(s)
    lam2 = 0.0 if sigma >= g["eps"] else (1 - (sigma / g["eps"]) ** 2) * g["lam"] ** 2
    pinv = J.T @ np.linalg.inv(A + lam2 * np.eye(6))
    p = g["kp_n"] * (posture - q) - g["kd_n"] * dq
    alpha = g["kp_r"] * pin.log3(R_ref @ R.T) + g["kd_r"] * (w_ref - omega)
    a = np.concatenate([a_lin, alpha])
    ddq = pinv @ (a - drift) + (np.eye(J.shape[1]) - pinv @ J) @ p
    return ddq, sigma, math.sqrt(lam2)


def test_ik_matches_the_numpy_formulation(robot: RobotModel) -> None:
    rng = np.random.default_rng(3)
    g = {"kp_n": 10.0, "kd_n": 6.0, "eps": 0.04, "lam": 0.05, "kp_r": 100.0, "kd_r": 20.0}
    lim = robot.limits
    damped = 0
    for i in range(300):
        q = rng.uniform(lim.lower, lim.upper)
        if i % 3 == 0:
            q[3] = lim.upper[3]  # elbow stretched: near a singularity
            q[5] = rng.uniform(-0.05, 0.05)
        dq = rng.uniform(-1, 1, N) * lim.velocity
        robot.update(q, dq)
        J, drift = robot.jacobian(), robot.drift()
        twist = robot.ee_velocity()
        R = np.ascontiguousarray(robot.ee_placement().rotation)
        posture = rng.uniform(lim.lower, lim.upper)
        K, b0, p = np.empty((6, 6)), np.empty(6), np.empty(N)
        sigma, lam = kernel.ik_prepare(J, drift, q, dq, posture, g["kp_n"], g["kd_n"], g["eps"],
                                       g["lam"], K, b0, p)
        a_lin = rng.normal(size=3)
        R_ref = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        w_ref = rng.normal(size=3)
        ddq = np.empty(N)
        kernel.ik_finish(J, K, b0, p, twist[3:], R, a_lin, R_ref, w_ref, g["kp_r"], g["kd_r"], ddq)
        ref, ref_sigma, ref_lam = _reference_ik(J, drift, q, dq, posture, g, twist[3:], R, a_lin,
                                                R_ref, w_ref)
        assert sigma == pytest.approx(ref_sigma, rel=1e-8)
        assert lam == pytest.approx(ref_lam, rel=1e-6, abs=1e-12)
        np.testing.assert_allclose(ddq, ref, rtol=1e-8, atol=1e-8 * np.abs(ref).max())
        damped += lam > 0
    assert damped > 10  # the damped branch was exercised


def _reference_bounds(q, dq, lim, brake, dt):
    """joint_accel_bounds in numpy, the same operations in the same order."""
    d = np.stack([np.maximum(lim.upper - q, 0.0), np.maximum(q - lim.lower, 0.0)])
    s = (np.sqrt(d * (2.0 / brake) + 2.25 * dt * dt) - 1.5 * dt) * brake
    v = np.minimum(lim.velocity, s) * np.array([[1.0], [-1.0]])
    h = (v - dq) / dt
    hi = np.minimum(lim.acceleration, h[0])
    lo = np.maximum(-lim.acceleration, h[1])
    bad = lo > hi
    fix = np.clip((np.clip(dq, v[1], v[0]) - dq) / dt, -lim.acceleration, lim.acceleration)
    return np.where(bad, fix, lo), np.where(bad, fix, hi), s[1] >= lim.velocity, s[0] >= lim.velocity


def _bounds(q, dq, lim, brake, dt):
    out = (np.empty(N), np.empty(N), np.empty(N, dtype=bool), np.empty(N, dtype=bool))
    kernel.accel_bounds(q, dq, lim.lower, lim.upper, lim.velocity, lim.acceleration, brake, dt, *out)
    return out


def test_accel_bounds_equal_the_numpy_formulation_bit_for_bit(robot: RobotModel) -> None:
    rng = np.random.default_rng(4)
    lim = robot.limits
    brake = 0.5 * lim.acceleration
    outside = 0
    for _ in range(2000):
        span = lim.upper - lim.lower
        q = rng.uniform(lim.lower - 0.01 * span, lim.upper + 0.01 * span)  # some outside the limits
        dq = rng.uniform(-1.3, 1.3, N) * lim.velocity
        got = _bounds(q, dq, lim, brake, 0.002)
        ref = _reference_bounds(q, dq, lim, brake, 0.002)
        for a, b in zip(got, ref, strict=True):
            np.testing.assert_array_equal(a, b)
        assert (got[0] <= got[1]).all()
        outside += int(((q < lim.lower) | (q > lim.upper) | (np.abs(dq) > lim.velocity)).any())
    assert outside > 100


def test_bound_and_integrate_clamps_and_steps(robot: RobotModel) -> None:
    rng = np.random.default_rng(5)
    lim, dt = robot.limits, 0.002
    brake = 0.5 * lim.acceleration
    seen = 0
    for _ in range(2000):
        q = rng.uniform(lim.lower, lim.upper)
        dq = rng.uniform(-1, 1, N) * lim.velocity
        lo, hi, lo_v, hi_v = _bounds(q, dq, lim, brake, dt)
        ddq_in = rng.normal(size=N) * lim.acceleration * rng.uniform(0.1, 3.0)
        ddq, dq1, q1 = np.empty(N), np.empty(N), np.empty(N)
        flags = kernel.bound_and_integrate(ddq_in, q, dq, dt, lim.acceleration, lo, hi, lo_v, hi_v,
                                           lim.lower, lim.upper, ddq, dq1, q1)
        ratio = (np.abs(ddq_in) / lim.acceleration).max()
        ref = ddq_in / ratio if ratio > 1 else ddq_in
        below, above = ref < lo, ref > hi
        vel = (below & lo_v) | (above & hi_v)
        expect = (CLAMP_ACCELERATION * (ratio > 1) | CLAMP_VELOCITY * vel.any()
                  | CLAMP_POSITION * ((below | above) & ~vel).any())
        assert flags & ~POSITION_GUARD == expect
        np.testing.assert_array_equal(ddq, np.clip(ref, lo, hi))
        v = dq + ddq * dt
        x = q + v * dt
        out = (x < lim.lower) | (x > lim.upper)  # from a state that cannot stop in time
        assert bool(flags & POSITION_GUARD) == out.any()
        np.testing.assert_array_equal(dq1, np.where(out, 0.0, v))
        np.testing.assert_array_equal(q1, np.clip(x, lim.lower, lim.upper))
        seen |= flags
    assert seen == CLAMP_ACCELERATION | CLAMP_VELOCITY | CLAMP_POSITION | POSITION_GUARD


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(0.0, 1.0), min_size=N, max_size=N),
    st.lists(st.floats(-1.0, 1.0), min_size=N, max_size=N),
    st.lists(st.floats(-1e3, 1e3), min_size=N, max_size=N),
)
def test_the_next_state_stays_within_every_limit(robot: RobotModel, u, w, a) -> None:
    """From a state inside the viable set, any requested acceleration gives a next state
    inside the position and velocity limits, at most the acceleration limit."""
    lim, dt = robot.limits, 0.002
    brake = 0.5 * lim.acceleration
    q = np.clip(lim.lower + np.array(u) * (lim.upper - lim.lower), lim.lower, lim.upper)
    stop = (np.sqrt(2.25 * dt * dt + 2 * np.minimum(q - lim.lower, lim.upper - q) / brake) - 1.5 * dt) * brake
    dq = np.array(w) * np.minimum(lim.velocity, stop)
    lo, hi, lo_v, hi_v = _bounds(q, dq, lim, brake, dt)
    ddq, dq1, q1 = np.empty(N), np.empty(N), np.empty(N)
    flags = kernel.bound_and_integrate(np.array(a), q, dq, dt, lim.acceleration, lo, hi, lo_v, hi_v,
                                       lim.lower, lim.upper, ddq, dq1, q1)
    assert not flags & POSITION_GUARD
    assert (np.abs(ddq) <= lim.acceleration * (1 + 1e-12)).all()
    assert (np.abs(dq1) <= lim.velocity * (1 + 1e-12)).all()
    assert ((q1 >= lim.lower) & (q1 <= lim.upper)).all()


_LOADED_ONCE = """
import numpy as np
from scipy.spatial.transform import Rotation
from services.arm import kernel
from services.arm.sim import ArmSim, ArmSimConfig
from services.robot.model import RobotModel
from services.robot.protocol import Command, CommandMode

names = ("ik_prepare", "ik_finish", "accel_bounds", "bound_and_integrate")
sim = ArmSim(RobotModel.load(), ArmSimConfig())
before = [len(getattr(kernel, k).signatures) for k in names]
quat = Rotation.from_rotvec([0.1, 0.0, 0.0]).as_quat()
for i in range(30):  # Cartesian with and without references, joint mode, braking
    if i < 10:
        sim.submit(Command(sim.tick, CommandMode.CARTESIAN, np.array([0.1, 0.0, 0.0]), quat,
                           np.zeros(3) if i % 2 else None))
    elif i < 20:
        sim.submit(Command(sim.tick, CommandMode.JOINT, joint_acceleration=np.ones(7)))
    sim.step()
print(before, [len(getattr(kernel, k).signatures) for k in names])
"""


def test_the_arm_loads_each_kernel_once_before_its_first_tick() -> None:
    """In a fresh process, ``ArmSim`` compiles (or loads) every kernel for the types its ticks
    use when it is built: a kernel compiled at a tick instead stalls the realtime loop for
    ~0.2-2 s."""
    out = subprocess.run([sys.executable, "-c", _LOADED_ONCE], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert out.stdout.split("\n")[-2] == "[1, 1, 1, 1] [1, 1, 1, 1]", out.stdout
