"""The planner's commands scaled into the arm's joint acceleration limits
(:mod:`services.planner.feasibility`): the joint accelerations of the scaled command, computed
independently with Pinocchio, stay within the limits' share, the binding joint at its bound; a
command within the limits is left as it is; the feeding task at the far grid row no longer makes
the arm clamp."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.planner.feasibility import SINGULAR_SIGMA, JointAccelerationScaling
from services.robot.model import RobotModel

FRACTION = 0.8


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def _joint_accels(robot: RobotModel, q: np.ndarray, dq: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``J⁺ ([a; 0] − J̇q̇)`` from Pinocchio directly (the local-world-aligned frame Jacobian and
    the classical drift of the end-effector frame), without the module's code."""
    model, data = robot.model, robot.model.createData()
    pin.forwardKinematics(model, data, q, dq, np.zeros(model.nv))
    pin.updateFramePlacements(model, data)
    pin.computeJointJacobians(model, data, q)
    frame = robot.ee_frame_id
    J = pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED)
    spatial = pin.getFrameAcceleration(model, data, frame, pin.LOCAL_WORLD_ALIGNED)
    twist = pin.getFrameVelocity(model, data, frame, pin.LOCAL_WORLD_ALIGNED)
    drift = np.concatenate([spatial.linear + np.cross(twist.angular, twist.linear), spatial.angular])
    b = np.concatenate([a, np.zeros(3)]) - drift
    return J.T @ np.linalg.solve(J @ J.T, b)


def _sigma_min(robot: RobotModel, q: np.ndarray) -> float:
    model, data = robot.model, robot.model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    J = pin.getFrameJacobian(model, data, robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
    return float(np.linalg.svd(J, compute_uv=False)[-1])


def test_near_a_singular_pose_nothing_is_scaled(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the smallest singular value of J may be below SINGULAR_SIGMA the arm's damped inverse
    bounds the joint accelerations and the undamped estimate would not: no scaling. (The
    Jacobian of the ready pose with one task direction shrunk to 1 mm per rad.)"""
    robot = RobotModel.load()
    q = robot.resolve_pose("ready")
    robot.update(q, np.zeros(robot.n))
    J = robot.jacobian().copy()
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    S[-1] = 1e-3
    monkeypatch.setattr(robot, "jacobian", lambda: (U * S) @ Vt)
    a = np.array([5.0, -5.0, 5.0])
    assert JointAccelerationScaling(robot, FRACTION).scale(a, 0, lambda: (q, np.zeros(robot.n))) == 1.0
    monkeypatch.undo()
    assert JointAccelerationScaling(robot, FRACTION).scale(10 * a, 0, lambda: (q, np.zeros(robot.n))) < 1.0


def test_a_command_within_the_limits_is_not_scaled(robot: RobotModel) -> None:
    scaling = JointAccelerationScaling(robot, FRACTION)
    q = robot.resolve_pose("ready")
    assert scaling.scale(np.array([0.1, -0.2, 0.05]), 0, lambda: (q, np.zeros(robot.n))) == 1.0


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-0.6, 0.6), min_size=7, max_size=7),
    st.lists(st.floats(-0.5, 0.5), min_size=7, max_size=7),
    st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3),
)
def test_the_scaled_command_keeps_every_joint_within_its_share(
    robot: RobotModel, dq_off: list[float], dq: list[float], a: list[float]
) -> None:
    q = robot.resolve_pose("ready") + np.asarray(dq_off)
    q = np.clip(q, robot.limits.lower, robot.limits.upper)
    dqv, av = np.asarray(dq), np.asarray(a)
    limit = FRACTION * robot.limits.acceleration
    s = JointAccelerationScaling(robot, FRACTION).scale(av, 0, lambda: (q, dqv))
    assert 0.0 <= s <= 1.0
    if _sigma_min(robot, q) < SINGULAR_SIGMA / math.sqrt(6.0):
        assert s == 1.0  # near a singular pose the arm's damped inverse takes over
        return
    drift_only = np.abs(_joint_accels(robot, q, dqv, np.zeros(3)))
    ddq = np.abs(_joint_accels(robot, q, dqv, s * av))
    if (drift_only <= limit).all() and _sigma_min(robot, q) >= SINGULAR_SIGMA:
        assert (ddq <= limit * (1 + 1e-6) + 1e-9).all(), (s, ddq / limit)
        if s < 1.0:  # scaled no more than needed: a joint is at its bound
            assert np.isclose(ddq / limit, 1.0, rtol=1e-6).any(), (s, ddq / limit)


def test_the_far_grid_row_runs_without_a_joint_clamp() -> None:
    """Grid point 7 of the feeding benchmark (person 5 cm farther in y, near the arm's reach):
    the arm clamped 14 ticks of reach_person's start to its joint acceleration limits before the
    scaling; with it, none, and the task still succeeds."""
    import services.arm.sim as sim
    from benchmarks.feeding import grid, moved_config
    from experiments.feeding import PERSON_JITTER_M, person_goals
    from experiments.harness import feeding_models, run_in_process, stack_settings
    from services.tasks.feeding import load_feeding

    clamped: list[int] = []
    original = sim.ArmSim.step

    def step(self: sim.ArmSim) -> object:
        snap = original(self)
        if self.clamp.acceleration:
            clamped.append(self.tick)
        return snap

    base = load_feeding()
    models = feeding_models(base.task)
    settings_ = stack_settings()
    cfg = moved_config(grid(0.05)[7])
    counts = {}
    for fraction in (0.0, settings_.joint_accel_fraction):
        clamped.clear()
        s = stack_settings(overrides={"planner.joint_accel_fraction": fraction})
        sim.ArmSim.step = step  # type: ignore[method-assign]
        try:
            res = run_in_process(cfg, models, s, goals=person_goals(cfg.scene.person, PERSON_JITTER_M,
                                                                    np.random.default_rng(1)))
        finally:
            sim.ArmSim.step = original  # type: ignore[method-assign]
        assert res.summary["success"], fraction
        counts[fraction] = len(clamped)
    assert counts[0.0] > 0, counts  # the premise: unscaled, the arm clamps here
    assert counts[settings_.joint_accel_fraction] == 0, counts


def test_the_kinematics_run_on_few_ticks_and_every_scaled_command_uses_fresh_ones(robot: RobotModel) -> None:
    from services.planner.feasibility import REFRESH_TICKS

    scaling = JointAccelerationScaling(robot, FRACTION)
    q0 = robot.resolve_pose("ready")
    calls: list[int] = []
    state = {"q": q0}

    def joints() -> tuple[np.ndarray, np.ndarray]:
        calls.append(1)
        return state["q"], np.zeros(robot.n)

    small = np.array([0.1, 0.0, 0.0])
    for tick in range(3 * REFRESH_TICKS):
        assert scaling.scale(small, tick, joints) == 1.0
    assert len(calls) == 3  # once per REFRESH_TICKS
    # A large command on a cached tick: the joints are read again (they moved) and the factor is
    # the one computed from scratch there.
    state["q"] = q0 + 0.05
    big = np.array([40.0, -20.0, 10.0])
    s = scaling.scale(big, 3 * REFRESH_TICKS - 1, joints)  # cached since tick 2 * REFRESH_TICKS
    assert len(calls) == 4
    fresh = JointAccelerationScaling(robot, FRACTION)
    assert s == fresh.scale(big, 0, lambda: (state["q"], np.zeros(robot.n))) < 1.0
