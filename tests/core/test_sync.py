"""Cross-dimension timing: the "scale" synchronisation (shared progress) and start retiming."""

from __future__ import annotations

import numpy as np
import pytest
from trajectories import minimum_jerk

from psm import ParameterError, PhaseSpaceModel

DT = 0.002


def sequential_demo(noise: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """x moves 0.3 m in the first second while y waits at rest, then y moves 0.2 m while x waits."""
    t = np.arange(0.0, 2.0 + 1e-9, DT)
    x = 0.3 * minimum_jerk(t, 1.0)
    y = 0.2 * minimum_jerk(t - 1.0, 1.0)
    X = np.stack([x, y], axis=1)
    if noise:
        X = X + np.random.default_rng(seed).normal(0.0, noise, X.shape)
    return t, X


def on_demo_clock(t: np.ndarray, r) -> np.ndarray:
    return np.stack([np.interp(t, r.t, r.x[:, d]) for d in range(r.x.shape[1])], axis=1)


@pytest.mark.parametrize(("noise", "seed"), [(0.0, 0), (5e-5, 1), (5e-5, 2)])
def test_scale_sync_holds_a_dwell_while_the_other_dimension_moves(noise: float, seed: int) -> None:
    t, X = sequential_demo(noise, seed)
    model = PhaseSpaceModel.fit(t, X)
    assert model.parameters.sync_mode == "scale"
    r = model.rollout(dt=DT)
    assert r.done
    x = on_demo_clock(t, r)
    moving_x = x[:, 0] < 0.27  # x has not yet done 90 % of its move
    assert np.max(np.abs(x[moving_x, 1])) < 0.01 * 0.2  # y holds within 2 mm (1 % of its move)
    rmse = np.sqrt(np.mean((x - sequential_demo()[1]) ** 2, axis=0))
    assert rmse[0] < 0.01 * 0.3 and rmse[1] < 0.075 * 0.2, rmse  # eq. 14: y is ~0.12 m off
    assert abs(r.t[-1] - t[-1]) < 0.05 * t[-1]


def test_paper_braking_does_not_hold_the_dwell() -> None:
    """The case the option exists for: with eq. 14 y sets off while x is still moving."""
    t, X = sequential_demo()
    model = PhaseSpaceModel.fit(t, X)
    r = model.rollout(dt=DT, sync_mode="brake")
    assert r.done
    x = on_demo_clock(t, r)
    assert np.max(np.abs(x[x[:, 0] < 0.27, 1])) > 0.25 * 0.2
    r0 = model.rollout(dt=DT, sync_gain=0.0)  # no synchronisation at all: the same
    x0 = on_demo_clock(t, r0)
    assert np.max(np.abs(x0[x0[:, 0] < 0.27, 1])) > 0.25 * 0.2


def test_scale_sync_reproduces_the_reach_at_least_as_well_as_eq14(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    err = {}
    for mode in ("brake", "scale"):
        r = model.rollout(dt=DT, sync_mode=mode)
        assert r.done
        np.testing.assert_allclose(r.x[-1], X[-1], atol=model.parameters.position_tolerance)
        err[mode] = float(np.max(np.sqrt(np.mean((on_demo_clock(t, r) - X) ** 2, axis=0))))
    assert err["scale"] <= 1.05 * err["brake"] + 1e-5, err


def test_scale_sync_keeps_velocity_continuous_and_acceleration_bounded(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    r = model.rollout(dt=DT, sync_mode="scale")
    a_max = np.asarray(model.parameters.max_acceleration)
    assert np.all(np.abs(r.a) <= a_max + 1e-9)
    assert np.all(np.abs(np.diff(r.v, axis=0)) <= a_max * DT + 1e-9)


def test_scale_sync_waits_for_a_held_dimension(reach_demo) -> None:
    """Hold x at its start for 0.5 s: the other dimensions wait and all finish close together."""
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)

    def hold_x(s: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if s < 0.5:
            x, v = x.copy(), v.copy()
            x[0], v[0] = model.start[0], 0.0
        return x, v

    def finish_times(r) -> np.ndarray:
        err = np.abs(r.x - model.goal)
        return np.array([r.t[np.flatnonzero(err[:, d] > 2e-3)[-1]] for d in range(3)])

    spread = {
        mode: np.ptp(finish_times(model.rollout(dt=DT, disturbance=hold_x, sync_mode=mode)))
        for mode in ("brake", "scale")
    }
    spread_off = np.ptp(finish_times(model.rollout(dt=DT, disturbance=hold_x, sync_gain=0.0)))
    assert spread_off > 0.3
    assert spread["scale"] < 0.2 * spread_off, spread


def test_scale_sync_follows_a_moving_goal(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    g0 = model.goal
    g1 = g0 + np.array([0.05, -0.04, 0.03])
    r = model.rollout(dt=DT, goal_fn=lambda s: g0 + (g1 - g0) * min(1.0, s / 1.5), sync_mode="scale")
    assert r.done
    np.testing.assert_allclose(r.x[-1], g1, atol=model.parameters.position_tolerance)


def test_start_retime_keeps_the_first_segment_duration(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X, start_retime=True)
    assert model.parameters.start_retime
    # From the demonstration's own start, retiming changes nothing.
    a = model.rollout(dt=DT, start_retime=True)
    b = model.rollout(dt=DT, start_retime=False)
    assert a.x.shape == b.x.shape
    np.testing.assert_allclose(a.x, b.x, atol=1e-6)
    # From farther away the first segment keeps its duration (as a DMP keeps its execution time)
    # instead of stretching out.
    x0 = model.start + np.array([-0.1, 0.0, 0.0])
    t_on = model.rollout(x0, dt=DT, start_retime=True).t[-1]
    t_off = model.rollout(x0, dt=DT, start_retime=False).t[-1]
    assert abs(t_on - t[-1]) < 0.7 * abs(t_off - t[-1]), (t_on, t_off)


def test_sync_options_are_validated_and_saved(tmp_path, reach_demo) -> None:
    t, X = reach_demo
    with pytest.raises(ParameterError, match="sync_mode"):
        PhaseSpaceModel.fit(t, X, sync_mode="fast")
    with pytest.raises(ParameterError, match="sync_time"):
        PhaseSpaceModel.fit(t, X, sync_time=0.0)
    model = PhaseSpaceModel.fit(t, X, sync_mode="brake", sync_time=0.2, start_retime=True, start_shift=True)
    with pytest.raises(ParameterError, match="sync_mode"):
        model.controller(sync_mode="nope")
    path = tmp_path / "m.json"
    model.save(path)
    loaded = PhaseSpaceModel.load(path)
    assert loaded.parameters == model.parameters
    np.testing.assert_array_equal(loaded.rollout(dt=DT).x, model.rollout(dt=DT).x)


def test_model_files_without_the_options_load_with_the_paper_behaviour(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    data = model.to_dict()
    for key in ("sync_mode", "sync_time", "start_retime", "start_shift"):
        del data["parameters"][key]
    old = PhaseSpaceModel.from_dict(data)
    assert old.parameters.sync_mode == "brake"
    assert not old.parameters.start_retime
    assert not old.parameters.start_shift
    np.testing.assert_array_equal(
        old.rollout(dt=DT).x, model.rollout(dt=DT, sync_mode="brake", start_retime=False, start_shift=False).x
    )


def test_start_shift_changes_nothing_from_the_demonstrated_start(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    a = model.rollout(dt=DT, start_shift=True)
    b = model.rollout(dt=DT, start_shift=False)
    assert a.x.shape == b.x.shape
    np.testing.assert_allclose(a.x, b.x, atol=1e-9)


@pytest.mark.parametrize("offset", [(-0.05, 0.03, 0.0), (0.0, -0.1, 0.05)])
def test_start_shift_fades_a_start_offset_along_the_motion(reach_demo, offset) -> None:
    """From a displaced start the path stays near the demonstration plus an offset that fades
    linearly in time (what a DMP does); without the shift the first segment absorbs it all."""
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    delta = np.asarray(offset)
    reference = X + delta * (1.0 - t / t[-1])[:, None]
    err = {}
    for shift in (False, True):
        r = model.rollout(model.start + delta, dt=DT, start_shift=shift)
        assert r.done
        np.testing.assert_allclose(r.x[-1], X[-1], atol=model.parameters.position_tolerance)
        err[shift] = float(np.max(np.abs(on_demo_clock(t, r) - reference)))
    assert err[True] < 0.6 * err[False], err


@pytest.mark.parametrize("offset", [(0.3, 0.0, 0.0), (0.45, 0.0, 0.0), (-0.2, 0.2, -0.1)])
def test_start_shift_with_large_offsets_stays_safe(reach_demo, offset) -> None:
    """Offsets that collapse or reverse shifted segments: the goal is still reached, with
    continuous velocity and bounded acceleration, also while the goal moves."""
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    a_max = np.asarray(model.parameters.max_acceleration)
    g0 = model.goal
    g1 = g0 + np.array([0.03, 0.02, -0.02])
    r = model.rollout(
        model.start + np.asarray(offset),
        dt=DT,
        start_shift=True,
        goal_fn=lambda s: g0 + (g1 - g0) * min(1.0, s),
    )
    assert r.done
    np.testing.assert_allclose(r.x[-1], g1, atol=model.parameters.position_tolerance)
    assert np.all(np.abs(np.diff(r.v, axis=0)) <= a_max * DT + 1e-9)


def diagonal_demo() -> tuple[np.ndarray, np.ndarray]:
    """A 2-D reach: x 0.3 m and y 0.2 m together, minimum jerk over 2 s."""
    t = np.arange(0.0, 2.0 + 1e-9, DT)
    s = minimum_jerk(t, 2.0)
    return t, np.stack([0.3 * s, 0.2 * s], axis=1)


def test_scale_sync_spreads_a_lead_opened_by_a_goal_jump() -> None:
    """The goal jumps 0.3 m further in y at 40 % of the motion: y now needs longer, and x (ahead)
    slows over the rest of the motion instead of stopping at once, yet both still arrive together
    (without excusing such a lead, x braked to 13 % of its speed and waited)."""
    t, X = diagonal_demo()
    model = PhaseSpaceModel.fit(t, X)
    g0 = model.goal
    g1 = g0 + np.array([0.0, 0.3])
    t_jump = 0.8
    r = model.rollout(dt=DT, goal_fn=lambda s: g0 if s < t_jump else g1)
    assert r.done
    np.testing.assert_allclose(r.x[-1], g1, atol=1e-3)
    after = (r.t > t_jump) & (r.x[:, 0] < g1[0] - 0.02)  # x still on its way (> 2 cm to go)
    assert after.any()
    x_speed = np.abs(r.v[after, 0])
    # x keeps moving: its speed never drops below a fifth of its speed at the jump.
    assert x_speed.min() > 0.2 * abs(r.v[np.searchsorted(r.t, t_jump), 0]), x_speed.min()
    # ... and the dimensions still finish together: x is not done long before y.
    x_arrival = r.t[np.argmax(np.abs(r.x[:, 0] - g1[0]) < 1e-3)]
    y_arrival = r.t[np.argmax(np.abs(r.x[:, 1] - g1[1]) < 1e-3)]
    assert abs(x_arrival - y_arrival) < 0.3, (x_arrival, y_arrival)
    assert np.all(np.abs(r.a) <= np.asarray(model.parameters.max_acceleration) + 1e-9)
