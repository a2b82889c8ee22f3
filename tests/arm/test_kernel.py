"""The arm's compiled per-tick kernels against the numpy / Pinocchio formulation of the same
equations (``services.arm.kernel``)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from typing import Any

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
from services.arm.state_encoder import CompiledStateEncoder
from services.robot.model import RobotModel
from services.robot.protocol import Command, CommandMode

names = ("ik_prepare", "ik_finish", "accel_bounds", "bound_and_integrate", "chain_kinematics",
         "encode_arm_state", "parse_cartesian_command")
robot = RobotModel.load()
sim = ArmSim(robot, ArmSimConfig())
encoder = CompiledStateEncoder(robot.joint_names, "base", 0.002)
before = [len(getattr(kernel, k).signatures) for k in names]
quat = Rotation.from_rotvec([0.1, 0.0, 0.0]).as_quat()
for i in range(30):  # Cartesian with and without references, joint mode, braking
    if i < 10:
        sim.submit(Command(sim.tick, CommandMode.CARTESIAN, np.array([0.1, 0.0, 0.0]), quat,
                           np.zeros(3) if i % 2 else None))
    elif i < 20:
        sim.submit(Command(sim.tick, CommandMode.JOINT, joint_acceleration=np.ones(7)))
    sim.step()
    encoder.encode(sim.snapshot(), watchdog_tripped=sim.watchdog_tripped, rejected_commands=i)
    # As the arm service decodes a command: the payload's bytes, the validation limits (floats).
    kernel.parse_cartesian_command(np.frombuffer(b"\\x20\\x01", dtype=np.uint8), 50.0, 10.0, 0.1,
                                   np.empty(10), np.zeros(2, dtype=np.int64))
print(before, [len(getattr(kernel, k).signatures) for k in names])
"""


def test_the_arm_loads_each_kernel_once_before_its_first_tick() -> None:
    """In a fresh process, ``ArmSim`` compiles (or loads) every kernel for the types its ticks
    use when it is built: a kernel compiled at a tick instead stalls the realtime loop for
    ~0.2-2 s."""
    out = subprocess.run([sys.executable, "-c", _LOADED_ONCE], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert out.stdout.split("\n")[-2] == "[1, 1, 1, 1, 1, 1, 1] [1, 1, 1, 1, 1, 1, 1]", out.stdout


# ---------------------------------------------------------------------- chain kinematics
_CHAIN_URDF = """<robot name="chain">
  <link name="base"/>
  {links}
</robot>"""


def _joint(name: str, parent: str, child: str, kind: str, axis: str, xyz: str, rpy: str) -> str:
    return (
        f'<link name="{child}"/><joint name="{name}" type="{kind}"><parent link="{parent}"/>'
        f'<child link="{child}"/><origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>'
        '<limit lower="-2" upper="2" effort="1" velocity="1"/></joint>'
    )


def _mixed_chain_urdf(tmp_path: Path) -> Path:
    """Every joint kind the compiled kinematics handles: revolute about x, y, z and an
    unaligned axis, prismatic along a coordinate and an unaligned axis, with rotated
    placements, and a fixed end-effector link."""
    joints = [
        ("j1", "base", "l1", "revolute", "0 0 1", "0 0 0.3", "0 0 0"),
        ("j2", "l1", "l2", "revolute", "0 1 0", "0.05 0 0.2", "0.3 -0.2 0.1"),
        ("j3", "l2", "l3", "prismatic", "1 0 0", "0 0.1 0.25", "0 0.4 0"),
        ("j4", "l3", "l4", "revolute", "0.6 0 0.8", "0.1 0 0.1", "-0.5 0 0.7"),
        ("j5", "l4", "l5", "revolute", "1 0 0", "0 -0.08 0.2", "0 0 -1.1"),
        ("j6", "l5", "l6", "prismatic", "0 0.6 0.8", "0.02 0.03 0.1", "0.2 0.2 0.2"),
    ]
    links = "".join(_joint(*j) for j in joints)
    links += ('<link name="tool"/><joint name="tool_joint" type="fixed"><parent link="l6"/>'
              '<child link="tool"/><origin xyz="0.01 0.02 0.15" rpy="0.1 -0.3 0.5"/></joint>')
    path = tmp_path / "chain.urdf"
    path.write_text(_CHAIN_URDF.format(links=links))
    return path


def _pinocchio_ee(robot: RobotModel, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> dict[str, np.ndarray]:
    robot.update(q, dq)
    J, drift = robot.jacobian(), robot.drift()
    M = robot.ee_placement()
    xyzquat = pin.SE3ToXYZQUAT(M)
    quat = xyzquat[3:] if xyzquat[6] >= 0 else -xyzquat[3:]
    return {"position": xyzquat[:3], "quat_xyzw": quat, "twist": robot.ee_velocity(),
            "acceleration": J @ ddq + drift, "drift": drift, "rotation": M.rotation.ravel(), "J": J.ravel()}


def _chain_ee(robot: RobotModel, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> dict[str, np.ndarray]:
    from services.arm.sim import SerialChain

    c = SerialChain.from_robot(robot)
    assert c is not None
    out = np.full(c.size, np.nan)
    kernel.chain_kinematics(c.kind, c.axis, c.joint_rotation, c.joint_translation, c.ee_rotation,
                            c.ee_translation, c.n_ee, q, dq, ddq, out)
    got = {k: out[a:b] for k, (a, b) in kernel.CHAIN_LAYOUT.items()}
    got["J"] = out[kernel.CHAIN_JACOBIAN:]
    return got


@pytest.mark.parametrize("which", ["panda", "mixed"])
def test_chain_kinematics_equal_pinocchio(robot: RobotModel, tmp_path: Path, which: str) -> None:
    """Placement, quaternion (w ≥ 0), Jacobian, twist, drift J̇q̇ and J q̈ + J̇q̇ of the compiled
    kinematics agree with Pinocchio's to rounding, over random states of the Panda and of a
    chain with every supported joint kind."""
    model = robot if which == "panda" else RobotModel.load(_mixed_chain_urdf(tmp_path), ee_frame="tool")
    rng = np.random.default_rng(7)
    for _ in range(300):
        q = rng.uniform(model.limits.lower, model.limits.upper)
        dq, ddq = rng.normal(0.0, 1.5, model.n), rng.normal(0.0, 5.0, model.n)
        ref, got = _pinocchio_ee(model, q, dq, ddq), _chain_ee(model, q, dq, ddq)
        for key, value in ref.items():
            np.testing.assert_allclose(got[key], value, rtol=0, atol=1e-12, err_msg=key)


def test_chain_kinematics_of_a_frame_before_the_last_joint(tmp_path: Path) -> None:
    """An end-effector frame on an inner link: the joints after it leave it alone (zero
    Jacobian columns) and the rest still equals Pinocchio."""
    model = RobotModel.load(_mixed_chain_urdf(tmp_path), ee_frame="l4")
    q, dq, ddq = np.full(model.n, 0.3), np.linspace(-1.0, 1.0, model.n), np.ones(model.n)
    got = _chain_ee(model, q, dq, ddq)
    ref = _pinocchio_ee(model, q, dq, ddq)
    for key, value in ref.items():
        np.testing.assert_allclose(got[key], value, rtol=0, atol=1e-12, err_msg=key)
    assert not got["J"].reshape(6, model.n)[:, 4:].any()


def test_a_model_that_is_not_a_serial_chain_uses_pinocchio(tmp_path: Path) -> None:
    """A tree (two branches off the base) is not a serial chain: the simulation keeps
    Pinocchio's kinematics, with the same snapshot fields."""
    from services.arm.sim import ArmSim, ArmSimConfig, SerialChain

    links = (_joint("a1", "base", "a", "revolute", "0 0 1", "0 0 0.1", "0 0 0")
             + _joint("b1", "base", "b", "revolute", "0 1 0", "0 0.2 0.1", "0 0 0")
             + _joint("a2", "a", "tip", "revolute", "1 0 0", "0 0 0.3", "0 0 0"))
    path = tmp_path / "tree.urdf"
    path.write_text(_CHAIN_URDF.format(links=links))
    model = RobotModel.load(path, ee_frame="tip")
    assert SerialChain.from_robot(model) is None
    sim = ArmSim(model, ArmSimConfig(start_pose=[0.1, 0.2, 0.3]))
    snap = sim.snapshot()
    assert snap.ee_packed is None
    ref = _pinocchio_ee(model, snap.q, snap.dq, snap.ddq)
    np.testing.assert_allclose(snap.ee.position, ref["position"], atol=1e-15)


def test_the_simulation_steps_the_same_with_compiled_and_pinocchio_kinematics(robot: RobotModel) -> None:
    """1,000 ticks of Cartesian commands with an orientation reference: the compiled
    kinematics and Pinocchio's give the same trajectory to rounding (the clamps and the
    integrator amplify 1e-16 differences only slightly over a run)."""
    from services.arm.sim import ArmSim, ArmSimConfig
    from services.robot.protocol import Command, CommandMode

    sims = [ArmSim(robot.with_own_data(), ArmSimConfig()) for _ in range(2)]
    sims[1]._chain = None  # Pinocchio's calls
    sims[1]._refresh()
    quat = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_quat()
    for i in range(1000):
        acc = np.array([0.4 * math.sin(i * 0.01), 0.3 * math.cos(i * 0.013), -0.2 * math.sin(i * 0.007)])
        for sim in sims:
            sim.submit(Command(sim.tick, CommandMode.CARTESIAN, acc, quat if i > 300 else None))
            sim.step()
    a, b = (s.snapshot() for s in sims)
    np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.dq, b.dq, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.ee.position, b.ee.position, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.ee.quat_xyzw, b.ee.quat_xyzw, rtol=0, atol=1e-10)


# ---------------------------------------------------------------------- state encoder
_F64 = st.floats(allow_nan=True, allow_infinity=True, width=64)
_F64_OR_ZERO = st.one_of(st.sampled_from([0.0, -0.0]), _F64)


@settings(max_examples=300, deadline=None)
@given(
    q=st.lists(_F64_OR_ZERO, min_size=N, max_size=N),
    ee=st.lists(_F64_OR_ZERO, min_size=19, max_size=19),
    time_ns=st.one_of(st.just(0), st.integers(0, 2**63 - 1)),
    tick=st.one_of(st.just(0), st.integers(0, 2**63 - 1)),
    braking=st.booleans(),
    watchdog=st.booleans(),
    rejected=st.one_of(st.just(0), st.integers(0, 2**40)),
    frame_id=st.sampled_from(["", "base", "wörld"]),
    dt_s=st.sampled_from([0.0, 0.002, 1e-3]),
)
def test_the_compiled_state_encoder_equals_protobuf(
    robot: RobotModel, q, ee, time_ns, tick, braking, watchdog, rejected, frame_id, dt_s
) -> None:
    """Byte for byte ``state_message(...).SerializeToString()``, zero and negative-zero
    fields (omitted / kept as protobuf does), NaN and inf, large varints, the saturated
    ``rejected_commands`` and empty constant fields included."""
    from services.arm.sim import ArmSnapshot
    from services.arm.state_encoder import CompiledStateEncoder
    from services.robot.protocol import EEState, StateEncoder, state_message

    e = np.array(ee)
    q_arr = np.array(q)
    ee_state = EEState(position=e[0:3], quat_xyzw=e[3:7], rotation=np.eye(3), linear_velocity=e[7:10],
                       angular_velocity=e[10:13], linear_acceleration=e[13:16], angular_acceleration=e[16:19])
    names = list(robot.joint_names)
    encoder = CompiledStateEncoder(names, frame_id, dt_s)
    for packed in (e, None):  # the compiled kinematics' buffer, or the fields one by one
        snap = ArmSnapshot(tick, time_ns, q_arr, -q_arr, q_arr[::-1].copy(), ee_state, braking, packed)
        got = encoder.encode(snap, watchdog_tripped=watchdog, rejected_commands=rejected)
        want = state_message(snap, names, frame_id, dt_s, watchdog_tripped=watchdog,
                             rejected_commands=rejected).SerializeToString()
        assert got == want
        assert got == StateEncoder(names, frame_id, dt_s).encode(
            snap, watchdog_tripped=watchdog, rejected_commands=rejected)


# ---------------------------------------------------------------------- command decoding
def _general_path(payload: bytes) -> tuple[str, Any]:
    """What the arm's general path makes of a command: ``("accepted", (stamp, Command))`` or
    ``("rejected", reason)``."""
    from services.arm.controller import ValidationLimits, validate_command
    from services.bus.messages import ArmCommand, MessageDecodeError, decode
    from services.robot.protocol import CommandRejectedError, command_from_message

    try:
        msg = decode(payload, "application/protobuf;psm.ArmCommand", ArmCommand)
        cmd = validate_command(command_from_message(msg), N, ValidationLimits())  # type: ignore[arg-type]
    except MessageDecodeError:
        return "rejected", "malformed"
    except CommandRejectedError as exc:
        return "rejected", exc.reason
    return "accepted", (int(msg.stamp_ns), cmd)  # type: ignore[attr-defined]


def _compiled_path(payload: bytes) -> tuple[int, Any]:
    from services.arm.controller import ValidationLimits

    v = ValidationLimits()
    vals, ints = np.full(10, np.nan), np.zeros(2, dtype=np.int64)
    flags = kernel.parse_cartesian_command(
        np.frombuffer(payload, dtype=np.uint8), v.max_linear_acceleration, v.max_angular_velocity,
        v.quat_norm_tolerance, vals, ints,
    )
    return flags, (vals, ints)


def _same_bits(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and a.tobytes() == b.tobytes())


def _check_paths_agree(payload: bytes) -> int:
    """The compiled decoding decides only commands the general path accepts, with the same
    values bit for bit; returns its result."""
    flags, (vals, ints) = _compiled_path(payload)
    if flags == kernel.COMMAND_SLOW:
        return flags
    verdict, detail = _general_path(payload)
    assert verdict == "accepted", (payload.hex(), detail)
    stamp, cmd = detail
    assert (int(ints[0]), int(ints[1])) == (stamp, cmd.tick)
    assert _same_bits(vals[0:3], cmd.linear_acceleration)
    quat = vals[3:7] if flags & kernel.COMMAND_HAS_ORIENTATION else None
    omega = vals[7:10] if flags & kernel.COMMAND_HAS_ANGULAR_VELOCITY else None
    assert _same_bits(quat, cmd.orientation_xyzw) and _same_bits(omega, cmd.angular_velocity)
    return flags


_F = st.floats(allow_nan=True, allow_infinity=True, width=64)
_SMALL = st.floats(-60.0, 60.0)


@st.composite
def _commands(draw: Any) -> bytes:
    """Serialised ArmCommands: plausible Cartesian commands, their edges (limits, quaternion
    norms, NaN, inf, negative zero), other modes, strings, goal updates, and mutations of the
    bytes (truncation, flipped bytes, duplicated or appended fields)."""
    from services.bus.messages import ArmCommand

    m = ArmCommand(
        stamp_ns=draw(st.integers(-(2**63), 2**63 - 1)),
        seq=draw(st.integers(0, 2**64 - 1)),
        tick=draw(st.one_of(st.integers(0, 2**40), st.integers(0, 2**64 - 1))),
        mode=draw(st.sampled_from([1, 1, 1, 0, 2, 7])),
        source=draw(st.sampled_from(["", "planner", "plännér"])),
        frame_id=draw(st.sampled_from(["", "base"])),
    )
    if draw(st.integers(0, 9)):
        a = m.linear_acceleration
        a.x, a.y, a.z = (draw(st.one_of(_SMALL, _SMALL, _SMALL, _F, st.just(-0.0))) for _ in range(3))
    if draw(st.booleans()):
        axis = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(3)])
        scale = draw(st.sampled_from([1.0, 1.0, -1.0, -1.0, 1.05, 0.85, 2.0]))
        quat = Rotation.from_rotvec(axis * 3.0).as_quat() * scale
        if draw(st.integers(0, 9)) == 0:
            quat[draw(st.integers(0, 3))] = draw(_F)
        o = m.orientation_reference
        o.x, o.y, o.z, o.w = (float(c) for c in quat)
    if draw(st.booleans()):
        w = m.angular_velocity_reference
        w.x, w.y, w.z = (draw(st.one_of(st.floats(-8.0, 8.0), st.floats(-8.0, 8.0), _F)) for _ in range(3))
    m.has_angular_velocity_reference = draw(st.booleans())
    if draw(st.integers(0, 4)) == 0:
        m.joint_accelerations.extend([draw(st.floats(-5.0, 5.0)) for _ in range(N)])
    if draw(st.integers(0, 4)) == 0:
        ref = m.goal_updates.add()
        ref.name, ref.stamp_ns = "person", 3
    payload = bytearray(m.SerializeToString())
    mutation = draw(st.integers(0, 9))  # 1-4: mutated
    if mutation == 1 and payload:
        del payload[draw(st.integers(0, len(payload) - 1)):]
    elif mutation == 2 and payload:
        payload[draw(st.integers(0, len(payload) - 1))] = draw(st.integers(0, 255))
    elif mutation == 3:
        payload += payload[: draw(st.integers(0, len(payload)))]
    elif mutation == 4:
        payload += bytes(draw(st.lists(st.integers(0, 255), max_size=12)))
    return bytes(payload)


@settings(max_examples=3000, deadline=None)
@given(payload=_commands())
def test_the_compiled_command_decoding_agrees_with_the_general_path(payload: bytes) -> None:
    """Whatever the bytes, the compiled decoding either leaves the command to protobuf and
    ``validate_command`` or accepts it exactly as they do (same stamp, tick, vectors to the
    bit): it never accepts what they reject."""
    _check_paths_agree(payload)


def test_the_compiled_command_decoding_takes_the_planners_commands() -> None:
    """The commands a planner sends (``cartesian_command``: acceleration, orientation, angular
    velocity, source and frame) are decided by the compiled decoding, with or without an
    orientation reference, negative zeros and w < 0 included; what it leaves alone is left."""
    from services.bus.messages import ArmState
    from services.robot.protocol import cartesian_command

    state = ArmState(stamp_ns=1_700_000_000_000_000_000, tick=123_456, frame_id="base")
    quat = Rotation.from_rotvec([0.3, -2.0, 0.4]).as_quat()
    cases = [
        (cartesian_command(state, [0.1, -0.2, 3.0], quat, [0.5, 0.0, -0.1], seq=9, source="planner"), 3),
        (cartesian_command(state, [0.0, -0.0, 0.0], -quat, None, source="probe"), 1),
        (cartesian_command(state, [1.0, 2.0, 3.0]), 0),
    ]
    for msg, flags in cases:
        assert _check_paths_agree(msg.SerializeToString()) == flags
    # A joint command, a goal update, a non-ASCII source: left to the general path.
    joint = cases[2][0]
    joint.mode = joint.JOINT_ACCELERATION
    joint.joint_accelerations.extend([0.0] * N)
    with_update = cartesian_command(state, [1.0, 0.0, 0.0])
    with_update.goal_updates.add(name="person", stamp_ns=5)
    accented = cartesian_command(state, [1.0, 0.0, 0.0], source="plännér")
    for msg in (joint, with_update, accented):
        assert _compiled_path(msg.SerializeToString())[0] == kernel.COMMAND_SLOW


def test_the_compiled_state_encoder_refuses_more_joints_than_it_was_made_for(robot: RobotModel) -> None:
    """The encoder's buffer is sized for its joints: a snapshot with more raises instead of
    writing past it (the compiled serialiser checks the room before it writes)."""
    from services.arm.sim import ArmSim, ArmSimConfig
    from services.arm.state_encoder import CompiledStateEncoder

    snap = ArmSim(robot, ArmSimConfig()).snapshot()
    short = CompiledStateEncoder(list(robot.joint_names)[:2], "base", 0.002)
    with pytest.raises(ValueError, match="7 joints"):
        short.encode(snap)
    assert CompiledStateEncoder(robot.joint_names, "base", 0.002).encode(snap)
