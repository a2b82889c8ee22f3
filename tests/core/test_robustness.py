"""Property tests: whatever the goal, start and push, the controller reaches the goal."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from trajectories import minimum_jerk

from psm import PhaseSpaceModel

DT = 0.002


@pytest.fixture(scope="module")
def model() -> PhaseSpaceModel:
    t = np.arange(0.0, 2.0 + 1e-9, DT)
    s = minimum_jerk(t, 2.0)
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


def _reach(rate: float, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A 3-D, 3 s rest-to-rest reach sampled at ``rate`` [Hz] with white noise of ``noise`` [m]:
    x and y move 0.4 / 0.25 m (y reverses once), z is constant (a table height)."""
    t = np.arange(0.0, 3.0, 1.0 / rate)
    s = minimum_jerk(t, t[-1])
    X = np.stack([0.4 * s, 0.25 * np.sin(np.pi * s) + 0.1 * s, np.full_like(s, 0.3)], axis=1)
    return t, X + np.random.default_rng(seed).normal(0.0, noise, X.shape)


@pytest.mark.parametrize("seed", [0, 1])
def test_unsmoothed_noise_is_not_a_reversal(seed: int) -> None:
    """``smoothing=0`` on a noisy 2 kHz recording: reversals must exceed the noise the smoothing
    left (8 × its estimate), so the noise is not cut into thousands of segments. (Regression:
    ~2,000 segments per dimension whose synchronisation stalled the reproduction.)"""
    t, X = _reach(2000.0, 1e-3, seed)
    model = PhaseSpaceModel.fit(t, X, smoothing=0.0)
    assert max(len(c) - 1 for c in model.cut_times) <= 30
    r = model.rollout(dt=DT, max_duration=6.0)
    assert r.done and abs(r.t[-1] - 3.0) < 0.3
    np.testing.assert_allclose(r.x[-1], model.goal, atol=model.parameters.position_tolerance)
    at_demo = np.stack([np.interp(t, r.t, r.x[:, d]) for d in range(3)], axis=1)
    # Loose: without smoothing the via-point velocities are differentiated noise (~1 m/s here).
    assert np.sqrt(np.mean((at_demo - X) ** 2)) < 0.05  # m, on a 0.4 m reach


def test_a_dimension_that_barely_moves_still_brakes_a_push() -> None:
    """z is constant in the demonstration (its largest |a| is the noise's): pushed at 0.2 m/s it
    must brake like the others. (Regression: eq. 10's m was per dimension, ~1e-3 m/s² for z,
    and z drifted away for minutes.)"""
    t, X = _reach(500.0, 1e-6, 0)
    model = PhaseSpaceModel.fit(t, X)
    assert 2 in model.hold_dimensions
    r = model.rollout(v0=[0.0, 0.0, 0.2], dt=DT, max_duration=10.0)
    assert r.done
    assert np.max(np.abs(r.x[:, 2] - 0.3)) < 0.05  # m


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), smoothing=st.sampled_from([0.005, 0.02, 0.05]))
def test_random_demonstrations_converge_from_other_starts_and_goals(seed: int, smoothing: float) -> None:
    """Random 1–5-D rest-to-rest motions (some dimensions barely move, white noise up to 1 mm,
    100 Hz–2 kHz), learned with any smoothing, run from a start and towards a goal ~5 cm away with
    an initial velocity about the motion's peak speed: every run reaches its goal.
    (Regression: far from its demonstrated segment the learned law obeyed the segment's speed
    margin before the acceleration limit, so a stiff spring accelerated at the limit until it could
    no longer stop; overshoots grew ~3× per swing and some runs diverged to kilometres.)"""
    rng = np.random.default_rng(seed)
    D = int(rng.integers(1, 6))
    rate = float(rng.choice([100.0, 250.0, 500.0, 1000.0, 2000.0]))
    t = np.arange(0.0, float(rng.uniform(0.5, 6.0)), 1.0 / rate)
    assume(t.size >= 10)
    s = minimum_jerk(t, t[-1])
    X = np.empty((t.size, D))
    for d in range(D):
        amplitude = rng.uniform(0.0, 0.5) * rng.choice([1.0, 0.0, 1e-5])
        phase, start_phase = rng.uniform(0.0, 6.0, 2)
        X[:, d] = amplitude * (np.sin(2.0 * np.pi * rng.uniform(0.0, 3.0) * s + phase) - np.sin(start_phase))
        X[:, d] += rng.uniform(-1.0, 1.0) + rng.normal(0.0, rng.choice([0.0, 1e-5, 2e-4, 1e-3]), t.size)
    assume(np.ptp(X, axis=0).max() >= 5e-3)  # a motion of at least 5 mm
    model = PhaseSpaceModel.fit(t, X, smoothing=smoothing)
    start = X[0] + rng.normal(0.0, 0.05, D)
    goal = X[-1] + rng.normal(0.0, 0.05, D) * rng.choice([0.0, 1.0])
    peak_speed = float(np.max(np.abs(np.gradient(model.rollout(dt=DT).x, DT, axis=0))))
    v0 = rng.normal(0.0, peak_speed, D) * rng.choice([0.0, 1.0])  # a push the size of the motion
    r = model.rollout(start, v0=v0, goal=goal, dt=DT, max_duration=10 * max(model.duration, 0.5) + 5)
    assert r.done, f"not done after {r.t[-1]:.1f} s; final error {r.x[-1] - goal}"
    assert np.all(np.isfinite(r.a))
