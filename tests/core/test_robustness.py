"""Property tests: whatever the goal, start and push, the controller reaches the goal."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psm import PhaseSpaceModel

DT = 0.002


@pytest.fixture(scope="module")
def model() -> PhaseSpaceModel:
    t = np.arange(0.0, 2.0 + 1e-9, DT)
    u = t / 2.0
    s = 10 * u**3 - 15 * u**4 + 6 * u**5  # minimum-jerk phase
    X = np.stack([0.4 * s, 0.2 * np.sin(np.pi * s), 0.1 * np.sin(2 * np.pi * s)], axis=1)
    return PhaseSpaceModel.fit(t, X)


offsets = st.lists(st.floats(-0.2, 0.2, allow_nan=False), min_size=3, max_size=3)


@settings(max_examples=40, deadline=None)
@given(
    goal_offset=offsets,
    start_offset=offsets,
    push_time=st.floats(0.0, 2.5),
    push_velocity=st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3),
)
def test_always_converges_with_bounded_acceleration(
    model: PhaseSpaceModel, goal_offset, start_offset, push_time, push_velocity
) -> None:
    goal = model.goal + np.array(goal_offset)
    start = model.start + np.array(start_offset)
    push_step = round(push_time / DT)

    def push(t: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if round(t / DT) == push_step:
            v = v + np.array(push_velocity)
        return x, v

    r = model.rollout(start, goal=goal, dt=DT, disturbance=push, max_duration=30.0)
    assert r.done, f"not done after {r.t[-1]:.1f} s; final error {r.x[-1] - goal}"
    np.testing.assert_allclose(r.x[-1], goal, atol=model.parameters.position_tolerance)
    assert np.all(np.isfinite(r.a))
    # Bounded: the larger of the wrong-way braking m and a few times the demonstrated peak, plus
    # the terminal spring's capture of the last tick.
    bound = 6.0 * max(model.parameters.wrong_way_accel)
    assert np.max(np.abs(r.a)) < bound


@settings(max_examples=40, deadline=None)
@given(
    data=st.data(),
    velocity=st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3),
)
def test_a_start_exactly_on_a_via_point_or_the_goal_is_handled(
    model: PhaseSpaceModel, data: st.DataObject, velocity
) -> None:
    """Exact coincidences (Δ = 0 to the goal or to a via-point) at any velocity: no division by
    zero, the goal is reached. (Regression: a start on the goal with v ≠ 0 raised ZeroDivisionError.)"""
    start = np.empty(3)
    for d, vp in enumerate(model.via_points):
        j = data.draw(st.integers(0, len(vp.position) - 1), label=f"via-point of dim {d}")
        start[d] = model.goal[d] + vp.position[j]  # j = last: exactly the goal
    r = model.rollout(start, v0=np.array(velocity), dt=DT, max_duration=30.0)
    assert r.done and np.all(np.isfinite(r.a))
    np.testing.assert_allclose(r.x[-1], model.goal, atol=model.parameters.position_tolerance)
    assert np.max(np.abs(r.a)) < 6.0 * max(model.parameters.wrong_way_accel)
