"""The learned model in motion: reproduction, generalisation, perturbations, persistence."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from trajectories import minimum_jerk

from psm import ModelFileError, ParameterError, PhaseSpaceModel, ShapeError
from psm.controller import MODE_STOP, MODE_WRONG_WAY
from psm.fitting import smooth, validate_demonstration

DT = 0.002


def resample(t_ref: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x (N, D) on t, linearly interpolated on t_ref (held at the ends)."""
    return np.stack([np.interp(t_ref, t, x[:, d]) for d in range(x.shape[1])], axis=1)


@pytest.fixture
def model(reach_demo) -> PhaseSpaceModel:
    t, X = reach_demo
    return PhaseSpaceModel.fit(t, X)


def demo_accel_max(t: np.ndarray, X: np.ndarray) -> float:
    demo = smooth(*validate_demonstration(t, X), 0.02)
    return float(np.max(np.abs(demo.a)))


@pytest.mark.parametrize(("k_fit", "rel_rmse"), [("least_squares", 0.015), ("duration", 0.005)])
def test_reproduces_its_own_demonstration(reach_demo, k_fit: str, rel_rmse: float) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X, k_fit=k_fit)
    r = model.rollout(dt=DT)
    assert r.done
    rng = np.ptp(X, axis=0)
    rmse = np.sqrt(np.mean((resample(t, r.t, r.x) - X) ** 2, axis=0))
    assert np.all(rmse < rel_rmse * np.max(rng)), rmse  # relative to the reach
    assert abs(r.t[-1] - t[-1]) < 0.05 * t[-1]  # same duration within 5 %
    np.testing.assert_allclose(r.x[-1], X[-1], atol=model.parameters.position_tolerance)
    assert np.all(np.abs(r.v[-1]) <= model.parameters.velocity_tolerance)


def test_hits_every_demonstrated_via_point_velocity(model: PhaseSpaceModel) -> None:
    r = model.rollout(dt=DT, sync_gain=0.0)
    for d, vp in enumerate(model.via_points):
        positions = model.goal[d] + vp.position
        direction = np.sign(np.diff(vp.position))
        for i in range(1, len(positions) - 1):
            if vp.velocity[i] == 0.0:
                continue  # turning points: v = 0 where the motion reverses, checked below
            # first sample at or past via-point i while in segment i-1 or i
            seg = r.segment[:, d]
            mask = (seg >= i - 1) & ((r.x[:, d] - positions[i]) * direction[i - 1] >= 0)
            n = int(np.argmax(mask))
            assert mask[n]
            scale = max(abs(vp.velocity[i]), 0.02)
            assert r.v[n, d] == pytest.approx(vp.velocity[i], abs=0.05 * scale + 2 * DT * 5.0)
        # reversals happen at the via-points with v = 0
        turns = [i for i in range(1, len(positions) - 1) if vp.velocity[i] == 0.0]
        for i in turns:
            assert np.min(np.abs(r.x[:, d] - positions[i])) < 1e-3


def test_generalises_to_a_new_goal_and_start(reach_demo, model: PhaseSpaceModel) -> None:
    t, X = reach_demo
    goal = model.goal + np.array([0.1, -0.05, 0.08])
    start = model.start + np.array([-0.05, 0.03, 0.02])
    r = model.rollout(start, goal=goal, dt=DT)
    assert r.done
    np.testing.assert_allclose(r.x[-1], goal, atol=model.parameters.position_tolerance)
    assert np.max(np.abs(r.a)) < 3.0 * demo_accel_max(t, X)
    # the phase-space structure moves with the goal: every reversal of the demonstration
    # (a via-point with v = 0) is reached at the same place relative to the new goal
    for d, vp in enumerate(model.via_points):
        for i in range(1, len(vp.position) - 1):
            if vp.velocity[i] == 0.0:
                assert np.min(np.abs(r.x[:, d] - (goal[d] + vp.position[i]))) < 1e-3


def test_goal_moved_mid_motion_converges_with_continuous_velocity(
    reach_demo, model: PhaseSpaceModel
) -> None:
    t, X = reach_demo
    g0 = model.goal
    g1 = g0 + np.array([0.15, 0.1, -0.05])
    r = model.rollout(dt=DT, goal_fn=lambda s: g0 if s < 0.8 else g1)
    assert r.done
    np.testing.assert_allclose(r.x[-1], g1, atol=model.parameters.position_tolerance)
    # velocity is continuous: per-step velocity change is bounded by the acceleration
    dv = np.abs(np.diff(r.v, axis=0))
    assert np.all(dv <= np.abs(r.a[:-1]) * DT + 1e-12)
    assert np.max(np.abs(r.a)) < 5.0 * demo_accel_max(t, X)


def test_goal_moving_continuously_is_tracked(model: PhaseSpaceModel) -> None:
    g0 = model.goal

    def goal_fn(s: float) -> np.ndarray:
        u = min(s, 2.0)  # moves along a curve for 2 s, then stays
        return g0 + 0.05 * np.array([math.sin(2 * u), math.cos(2 * u) - 1.0, 0.5 * u])

    r = model.rollout(dt=DT, goal_fn=goal_fn, max_duration=8.0)
    assert r.done
    np.testing.assert_allclose(r.x[-1], goal_fn(10.0), atol=model.parameters.position_tolerance)
    assert np.max(np.abs(r.a)) < 10.0


def test_push_against_the_motion_recovers(reach_demo, model: PhaseSpaceModel) -> None:
    t, X = reach_demo

    def push(s: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if 0.7 <= s < 0.7 + DT / 2:
            v = v.copy()
            v[0] = -0.6  # shoved backwards along x at 0.6 m/s
        return x, v

    r = model.rollout(dt=DT, disturbance=push)
    assert r.done
    np.testing.assert_allclose(r.x[-1], model.goal, atol=model.parameters.position_tolerance)
    # the wrong-direction rule (eq. 10) applied a constant acceleration m towards the via-point
    i = round(0.7 / DT)
    assert r.a[i, 0] == pytest.approx(model.parameters.wrong_way_accel[0])
    assert np.max(np.abs(r.a)) <= max(3.0 * demo_accel_max(t, X), model.parameters.wrong_way_accel[0])


def test_wrong_way_mode_reported_by_the_controller(model: PhaseSpaceModel) -> None:
    ctrl = model.controller()
    a = ctrl.step(model.start, np.array([-0.5, 0.0, 0.0]), DT)
    assert ctrl.modes[0] == MODE_WRONG_WAY
    assert a[0] == pytest.approx(model.parameters.wrong_way_accel[0])


def test_synchronisation_pulls_completion_times_together(model: PhaseSpaceModel) -> None:
    """Hold x back for a while: with eq. 14 the other dimensions wait for it."""

    def hold_x(s: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if s < 0.5:
            x = x.copy()
            v = v.copy()
            x[0] = model.start[0]
            v[0] = 0.0
        return x, v

    def finish_times(r) -> np.ndarray:
        err = np.abs(r.x - model.goal)
        return np.array([r.t[np.flatnonzero(err[:, d] > 2e-3)[-1]] for d in range(3)])

    spread = {
        gain: np.ptp(finish_times(model.rollout(dt=DT, disturbance=hold_x, sync_gain=gain)))
        for gain in (0.0, model.parameters.sync_gain, 16.0)
    }
    assert spread[0.0] > 0.3  # held back 0.5 s, x finishes ~0.5 s after the others without eq. 14
    assert spread[model.parameters.sync_gain] < 0.7 * spread[0.0]
    assert spread[16.0] < 0.2 * spread[0.0]


def test_collision_stop_and_resume(model: PhaseSpaceModel) -> None:
    ctrl = model.controller()
    x, v = model.start.copy(), np.zeros(3)
    x_ob = model.start[0] + 0.15
    ctrl.request_stop(0, x_ob)
    max_x = -np.inf
    for _ in range(1500):
        a = ctrl.step(x, v, DT)
        x = x + v * DT + 0.5 * a * DT * DT
        v = v + a * DT
        max_x = max(max_x, x[0])
    assert ctrl.modes[0] == MODE_STOP
    assert max_x <= x_ob + 1e-6
    assert abs(v[0]) < 1e-3
    ctrl.clear_stops()
    for _ in range(3000):
        a = ctrl.step(x, v, DT)
        x = x + v * DT + 0.5 * a * DT * DT
        v = v + a * DT
        if ctrl.done:
            break
    assert ctrl.done
    np.testing.assert_allclose(x, model.goal, atol=model.parameters.position_tolerance)


def test_a_collision_stop_holds_in_the_world_while_the_goal_moves(model: PhaseSpaceModel) -> None:
    """The law runs on the velocity relative to a moving goal, the stop on the measured one: an
    axis braked at a stop comes to rest there, although relative to the goal it is moving."""
    goal = model.goal.copy()
    goal_velocity = np.array([0.05, 0.0, 0.0])  # the goal moves on, beyond the stop
    ctrl = model.controller(goal)
    x, v = model.start.copy(), np.zeros(3)
    x_ob = model.start[0] + 0.15
    ctrl.request_stop(0, x_ob)
    max_x = -np.inf
    for _ in range(2500):
        goal = goal + goal_velocity * DT
        ctrl.set_goal(goal)
        a = ctrl.step(x, v, DT, goal_velocity)
        x = x + v * DT + 0.5 * a * DT * DT
        v = v + a * DT
        max_x = max(max_x, x[0])
    assert ctrl.modes[0] == MODE_STOP
    assert max_x <= x_ob + 1e-6
    assert abs(v[0]) < 1e-3  # at rest in the world (relative to the goal: -0.05 m/s)


def _disturbed_at_stop(
    model: PhaseSpaceModel, side: float | None, push: float = 0.0, shift: float = 0.0
) -> tuple[np.ndarray, float, Any]:
    """An axis braked at a stop 5 cm along x, then at tick 1000 pushed by ``push`` [m/s] or
    moved by ``shift`` [m] (a drift), 1000 more ticks; the stop's obstacle on ``side`` (None: not
    given). Returns the final state, the largest x after the disturbance and the controller."""
    ctrl = model.controller()
    x, v = model.start.copy(), np.zeros(3)
    ctrl.request_stop(0, model.start[0] + 0.05, side)
    max_x = -np.inf
    for tick in range(2000):
        if tick == 1000:
            v[0] += push
            x[0] += shift
        a = ctrl.step(x, v, DT)
        x = x + v * DT + 0.5 * a * DT * DT
        v = v + a * DT
        if tick >= 1000:
            max_x = max(max_x, x[0])
    return np.concatenate([x, v]), max_x, ctrl


def test_an_axis_past_its_stop_on_the_obstacles_side_is_brought_back_to_it(model: PhaseSpaceModel) -> None:
    """With the obstacle's side given a stop is a barrier: an axis found past it (a drift of the
    arm) springs back to it instead of following its segment on towards the goal. Without the
    side the stop only brakes an approaching axis, as eq. 15 does."""
    assert model.goal[0] > model.start[0] + 0.05
    stop = model.start[0] + 0.05
    state, _, ctrl = _disturbed_at_stop(model, +1.0, shift=1e-3)
    assert ctrl.modes[0] == MODE_STOP
    assert state[0] == pytest.approx(stop, abs=1e-6) and abs(state[3]) < 1e-6
    state, _, _ = _disturbed_at_stop(model, None, shift=1e-3)
    assert state[0] > stop + 0.01


def test_an_axis_pushed_at_its_stop_never_passes_it_and_comes_to_rest(model: PhaseSpaceModel) -> None:
    """Pushed towards the obstacle while resting at the stop, the axis does not pass it (the
    braking ends the tick on the stop), and moving back from it, it is braked to rest at the
    wrong-way deceleration ``m`` instead of drifting back towards the start."""
    stop = model.start[0] + 0.05
    for side in (+1.0, None):
        state, max_x, ctrl = _disturbed_at_stop(model, side, push=0.2)
        assert ctrl.modes[0] == MODE_STOP
        assert max_x <= stop + 1e-12
        assert abs(state[3]) < 1e-9
        reach = 0.2**2 / (2.0 * model.parameters.wrong_way_accel[0])  # braked at m from 0.2 m/s
        assert stop - reach - 1e-3 < state[0] < stop


def test_a_stop_brakes_at_most_to_end_the_tick_on_it(model: PhaseSpaceModel) -> None:
    ctrl = model.controller()
    x, v = model.start.copy(), np.zeros(3)
    gap = 1e-9
    ctrl.request_stop(0, x[0] + gap)
    v[0] = 0.2
    a = ctrl.step(x, v, DT)
    # The constant deceleration that covers the gap in one tick: 2 (v dt − gap) / dt².
    assert a[0] == pytest.approx(-2.0 * (0.2 * DT - gap) / DT**2, rel=1e-9)
    assert x[0] + v[0] * DT + 0.5 * a[0] * DT * DT == pytest.approx(x[0] + gap, abs=1e-12)


def test_time_to_go_counts_down(model: PhaseSpaceModel) -> None:
    ctrl = model.controller()
    x, v = model.start.copy(), np.zeros(3)
    ttg = []
    for _ in range(600):
        a = ctrl.step(x, v, DT)
        ttg.append(ctrl.time_to_go.max())
        # The tuple views a control loop reads every tick are the same numbers.
        assert ctrl.time_to_go_tuple == tuple(ctrl.time_to_go.tolist())
        assert ctrl.segment_tuple == tuple(ctrl.segment.tolist())
        x = x + v * DT + 0.5 * a * DT * DT
        v = v + a * DT
    ttg = np.array(ttg)
    assert ttg[0] == pytest.approx(model.duration, rel=0.05)
    # counts down at roughly real time (within 20 %) while the motion runs
    slope = np.polyfit(np.arange(ttg.size) * DT, ttg, 1)[0]
    assert -1.2 < slope < -0.8


@pytest.mark.parametrize("k", [2.0, -5.0, 0.0, 3.8, 1e-9])
@pytest.mark.parametrize("v_n", [0.0, 0.15])
def test_time_to_go_is_the_closed_form_time_of_the_segment(k: float, v_n: float) -> None:
    """The controller's t_e in a segment is psm.pstf.time_to_reach of the measured state with the
    segment's slope, bit for bit (the hot path writes the closed form out), for k > 0, k < 0,
    k ≈ 0 and k near the stability bound, towards a via-point at rest and one in motion."""
    from psm.controller import DimensionChain, PSMController
    from psm.pstf import time_to_reach

    # Two segments, -0.4 -> -0.2 -> 0 (goal-relative), the via-point at -0.2 moving at v_n.
    chain = DimensionChain(
        offsets=(-0.4, -0.2, 0.0), velocities=(0.0, v_n, 0.0), k=(k, -1.0), kappa=(1e-3, 1e-3),
        durations=(1.0, 1.0), hold=False,
    )
    ctrl = PSMController([chain], [1.0], np.array([50.0]), 0.0, 1e-6, 1e-6)
    x, v = 1.0 - 0.3, 0.2  # in the first segment, moving towards the via-point at 0.8
    ctrl.step([x], [v], DT)
    assert ctrl.segment_tuple == (0,)
    # k_max = ((|v| + |v_n|)/Δ)²: every k above stays below 0.97 k_max - κ, so it is used as is.
    assert ctrl.time_to_go_tuple[0] == time_to_reach(x, v, 0.8, v_n, k) + 1.0



@settings(max_examples=300, deadline=None)
@given(
    x_frac=st.floats(0.0, 0.99),
    v=st.floats(0.0, 3.0),
    v_n=st.floats(0.0, 2.0),
    k_frac=st.floats(-3.0, 0.999),
    sign=st.sampled_from([1.0, -1.0]),
)
def test_time_to_go_matches_the_closed_form_for_any_state(
    x_frac: float, v: float, v_n: float, k_frac: float, sign: float
) -> None:
    """The same for any state inside a segment, either direction, any slope below the stability
    bound: the hot path's written-out closed form gives psm.pstf.time_to_reach bit for bit."""
    from psm.controller import DimensionChain, PSMController
    from psm.pstf import K_MAX_FRACTION, time_to_reach

    kappa = 1e-3
    x_n = 1.0 - 0.2 * sign  # the via-point, 0.2 before the goal at 1.0
    x = x_n - sign * 0.2 * (1.0 - x_frac)  # between the first via-point and x_n
    assume(x != x_n)
    speed_ratio = (v + v_n) / (x_n - x)
    k_top = K_MAX_FRACTION * (speed_ratio * speed_ratio) - kappa  # the controller's clamp of k
    k = k_frac * max(abs(k_top), 1.0)
    chain = DimensionChain(
        offsets=(-0.4 * sign, -0.2 * sign, 0.0), velocities=(0.0, v_n * sign, 0.0), k=(k, -1.0),
        kappa=(kappa, kappa), durations=(1.0, 1.0), hold=False,
    )
    ctrl = PSMController([chain], [1.0], np.array([50.0]), 0.0, 1e-6, 1e-6)
    ctrl.step([x], [v * sign], DT)
    expected = time_to_reach(x, v * sign, x_n, v_n * sign, min(k, k_top))
    assume(ctrl.segment_tuple == (0,) and expected > DT)  # else the next segment's time is reported
    assert ctrl.time_to_go_tuple[0] == expected + 1.0

def test_one_dimensional_demonstration() -> None:
    t = np.linspace(0, 1, 501)
    x = 0.3 * (1 - np.cos(np.pi * t)) / 2
    model = PhaseSpaceModel.fit(t, x)
    assert model.dim == 1
    r = model.rollout(dt=DT)
    assert r.done and r.x[-1, 0] == pytest.approx(0.3, abs=1e-4)


def test_bad_arguments_raise_clear_errors(model: PhaseSpaceModel) -> None:
    with pytest.raises(ShapeError, match=r"goal must have shape \(3,\)"):
        model.rollout(goal=[1.0, 2.0])
    with pytest.raises(ShapeError, match="x0"):
        model.rollout(x0=[np.nan, 0, 0])
    with pytest.raises(ParameterError, match="dt"):
        model.rollout(dt=0.0)
    ctrl = model.controller()
    with pytest.raises(ShapeError):
        ctrl.set_goal(np.zeros(4))
    with pytest.raises(ShapeError):
        ctrl.step(np.zeros(2), np.zeros(2), DT)
    with pytest.raises(ParameterError):
        ctrl.step(np.zeros(3), np.zeros(3), -1.0)


def test_save_load_round_trip_gives_identical_rollouts(tmp_path, model: PhaseSpaceModel) -> None:
    path = tmp_path / "model.json"
    model.save(path)
    loaded = PhaseSpaceModel.load(path)
    assert loaded.to_dict() == model.to_dict()
    goal = model.goal + 0.05
    a = model.rollout(goal=goal, dt=DT)
    b = loaded.rollout(goal=goal, dt=DT)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and np.array_equal(a.t, b.t)


def test_load_rejects_bad_files(tmp_path, model: PhaseSpaceModel) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ModelFileError, match="not valid JSON"):
        PhaseSpaceModel.load(bad)
    data = model.to_dict()
    data["version"] = 99
    bad.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match="version"):
        PhaseSpaceModel.load(bad)
    data = model.to_dict()
    del data["dimensions"][0]["k"]
    bad.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match="invalid model file"):
        PhaseSpaceModel.load(bad)
    bad.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ModelFileError, match="not a PSM model"):
        PhaseSpaceModel.load(bad)


def test_a_slow_approach_to_a_via_point_keeps_the_demonstrated_timing() -> None:
    """A small, slow rest-to-rest wiggle before the motion (a hand settling) ends at via-points
    the state approaches at a crawl. The controller follows the segment law until it arrives
    instead of skipping ahead once within ``position_tolerance``, which ran every later via-point
    ~1/10 s early (regression: 26-80 ms early on the recorded grasp_spoon demonstration)."""
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    dip = np.where(t < 0.3, -0.0015 * np.sin(np.pi * t / 0.3) ** 2, 0.0)
    reach = 0.1 * minimum_jerk(t - 0.3, 1.5)
    model = PhaseSpaceModel.fit(t, dip + reach, position_tolerance=1e-2)  # 1 mm: the regime of the bug
    cuts = model.cut_times[0]
    assert cuts[1] == pytest.approx(0.15, abs=0.02)  # the wiggle's reversal is a via-point
    r = model.rollout(dt=DT)
    for j in range(1, len(cuts) - 1):
        reached = r.t[np.argmax(r.segment[:, 0] >= j)]
        assert reached == pytest.approx(cuts[j], abs=3 * DT), f"via-point {j}"
    assert r.done and 1.8 < r.t[-1] < 2.05  # the motion ends at 1.8 s, then rests until 2 s


@pytest.mark.parametrize("smoothing", [0.0, 0.05])
def test_a_demonstration_that_does_not_move_is_a_hold(smoothing: float) -> None:
    """A constant demonstration (the smoothing's float rounding is not a motion: it used to become
    ~100 segments of 1e-16 that never finished) is a hold in every dimension."""
    t = np.arange(0.0, 2.0, DT)
    X = np.tile([0.3, -0.2], (t.size, 1))
    model = PhaseSpaceModel.fit(t, X, smoothing=smoothing)
    assert model.hold_dimensions == [0, 1]
    r = model.rollout(dt=DT)
    assert r.done and r.t[-1] < 0.1
    r = model.rollout(X[0] + [0.01, -0.02], dt=DT, max_duration=10.0)  # displaced: comes back
    assert r.done
    np.testing.assert_allclose(r.x[-1], X[0], atol=model.parameters.position_tolerance)
