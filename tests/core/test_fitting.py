"""Learning: validation, smoothing, segmentation and the least-squares slope."""

from __future__ import annotations

import numpy as np
import pytest
from trajectories import minimum_jerk

from psm import DemonstrationError, ParameterError, PhaseSpaceModel, pstf
from psm.fitting import fit_grid, smooth, turning_points, validate_demonstration


@pytest.mark.parametrize(
    ("t", "X", "message"),
    [
        (np.arange(5.0), np.zeros((5, 2)), "at least"),
        (np.arange(10.0), np.zeros((9, 2)), "samples but X has"),
        (np.r_[0.0, 1.0, 1.0, *np.arange(2.0, 9.0)], np.zeros((10, 2)), "strictly increasing"),
        (np.arange(10.0), np.where(np.arange(20).reshape(10, 2) == 7, np.nan, 0.0), "sample 3"),
        (np.arange(10.0), np.zeros((10, 0)), "no dimension"),
        (np.arange(10.0), np.zeros((10, 2, 2)), "shape (T, D)"),
    ],
)
def test_invalid_demonstrations_raise_one_clear_error(t, X, message: str) -> None:
    with pytest.raises(DemonstrationError, match=message.replace("(", r"\(").replace(")", r"\)")):
        PhaseSpaceModel.fit(t, X)


def test_invalid_parameters() -> None:
    t = np.linspace(0, 1, 100)
    X = np.linspace(0, 1, 100)
    with pytest.raises(ParameterError, match="smoothing"):
        PhaseSpaceModel.fit(t, X, smoothing=-1.0)
    with pytest.raises(ParameterError, match="segments"):
        PhaseSpaceModel.fit(t, X, segments="many")
    with pytest.raises(ParameterError, match="cut times"):
        PhaseSpaceModel.fit(t, X, segments=[0.5, 2.0])
    with pytest.raises(ParameterError, match="k_fit"):
        PhaseSpaceModel.fit(t, X, k_fit="magic")


def test_non_uniform_time_is_resampled_to_the_median_step() -> None:
    t = np.cumsum(np.r_[0.0, np.full(50, 0.01), np.full(50, 0.012)])
    X = np.sin(t)[:, None]
    t_u, X_u = validate_demonstration(t, X)
    assert np.allclose(np.diff(t_u), np.median(np.diff(t)))
    np.testing.assert_allclose(X_u[:, 0], np.sin(t_u + t[0]), atol=1e-4)


def test_smoothing_and_derivatives_of_a_parabola() -> None:
    t = np.arange(0.0, 1.0, 0.001)
    X = (3.0 * t**2)[:, None]
    demo = smooth(t, X, 0.0)
    np.testing.assert_allclose(demo.v[5:-5, 0], 6.0 * t[5:-5], atol=1e-9)
    np.testing.assert_allclose(demo.a[5:-5, 0], 6.0, atol=1e-6)


def test_turning_points_ignore_noise_but_find_reversals() -> None:
    rng = np.random.default_rng(3)
    t = np.linspace(0, 1, 2000)
    x = np.sin(2 * np.pi * 1.5 * t) + rng.normal(0, 1e-3, t.size)
    turns = turning_points(x, tolerance=0.05)
    # sin(3πt) on [0,1] has extrema at t = 1/6, 1/2, 5/6
    np.testing.assert_allclose(t[turns], [1 / 6, 1 / 2, 5 / 6], atol=0.01)


def test_least_squares_recovers_the_slope_of_an_exact_pstf() -> None:
    """A demonstration that IS one PSTF (k = -6, ending at rest) is learned back with that k."""
    x_c, v_c, k = 0.0, 0.0, -6.0  # rest to rest: motions start and end at rest
    x_n0, v_n0 = 0.5, 0.0
    c0 = pstf.coefficient_c(x_c, v_c, x_n0, v_n0, k)
    T0 = pstf.time_to_reach(x_c, v_c, x_n0, v_n0, k)
    t0 = np.linspace(0.0, T0, 4001)
    x0, _ = pstf.propagate(t0, x_c, v_c, k, c0)
    # One segment asked for: without the velocity extremum (the PSTF's own speed peak) as a
    # via-point inside it.
    model = PhaseSpaceModel.fit(t0, x0, segments=1, smoothing=0.0, velocity_extrema=False)
    assert len(model.k[0]) == 1
    assert model.k[0][0] == pytest.approx(k, rel=2e-3)
    assert model.segment_durations[0][0] == pytest.approx(T0, rel=2e-3)


def test_duration_fit_reproduces_segment_times(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X, k_fit="duration")
    for d in range(3):
        demo_durations = np.diff(model.cut_times[d])
        np.testing.assert_allclose(model.segment_durations[d], demo_durations, rtol=1e-4, atol=1e-6)


def test_segments_are_monotone_and_reversals_are_cuts(reach_demo) -> None:
    t, X = reach_demo
    for spec in ("auto", 4, [0.5, 1.0, 1.5]):
        model = PhaseSpaceModel.fit(t, X, segments=spec)
        for d, vp in enumerate(model.via_points):
            steps = np.diff(vp.position)
            assert np.all(steps != 0.0)
            # velocities never point against the segment they bound
            assert np.all(vp.velocity[:-1] * steps >= 0.0)
            assert np.all(vp.velocity[1:] * steps >= 0.0)
            assert vp.position[-1] == 0.0 and vp.velocity[-1] == 0.0
            # every stable segment has a finite, positive duration
            assert np.all(np.isfinite(model.segment_durations[d]))
            assert np.all(model.segment_durations[d] > 0.0)
        # y reverses once (s = 1/2), z twice (s = 1/4, 3/4): those are knots with v = 0
        assert np.sum(model.via_points[1].velocity[1:-1] == 0.0) >= 1
        assert np.sum(model.via_points[2].velocity[1:-1] == 0.0) >= 2


def test_uniform_cuts_count(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X, segments=6)
    # x is monotone: exactly the 6 uniform segments
    assert len(model.k[0]) == 6
    np.testing.assert_allclose(model.cut_times[0], np.linspace(0, 2, 7), atol=0.002)


def test_auto_uses_fewer_segments_on_a_simple_motion_than_on_a_complex_one(reach_demo) -> None:
    t, X = reach_demo
    model = PhaseSpaceModel.fit(t, X)
    n = [len(k) for k in model.k]
    assert n[0] < n[2]
    assert max(n) <= model.parameters.max_segments


def test_noise_does_not_fragment_the_model(noisy_reach_demo) -> None:
    t, X = noisy_reach_demo
    model = PhaseSpaceModel.fit(t, X)
    assert max(len(k) for k in model.k) < model.parameters.max_segments


def test_a_barely_moving_dimension_is_a_hold_not_a_huge_k(reach_demo) -> None:
    t, X = reach_demo
    X = X.copy()
    X[:, 1] = 0.25 + 1e-6 * np.sin(40 * t)  # micrometre wobble
    model = PhaseSpaceModel.fit(t, X)
    assert model.hold_dimensions == [1]
    assert abs(model.k[1][0]) < 100.0
    r = model.rollout(dt=0.002)
    assert np.max(np.abs(r.a[:, 1])) < 1e-2
    assert r.done


def _wave(rate: float) -> tuple[np.ndarray, np.ndarray]:
    """A 2-D, 3 s rest-to-rest motion with reversals, sampled at ``rate`` [Hz]: ``t (T,)``,
    ``X (T, 2)`` [m]."""
    t = np.arange(0.0, 3.0 + 0.5 / rate, 1.0 / rate)
    s = minimum_jerk(t, 3.0)
    X = np.stack([0.3 * np.sin(2.0 * np.pi * s) + 0.2 * s, 0.25 * (1 - np.cos(3.0 * np.pi * s))], axis=1)
    return t, X


def test_fit_grid_keeps_a_demonstration_that_is_not_dense() -> None:
    demo = smooth(*validate_demonstration(*_wave(250.0)), 0.02)  # dt 4 ms > sigma / 8
    assert fit_grid(demo, 0.02) is demo
    assert fit_grid(demo, 0.0) is demo


def test_fit_grid_is_a_coarser_uniform_grid_through_the_smoothed_demonstration() -> None:
    demo = smooth(*validate_demonstration(*_wave(1000.0)), 0.02)
    grid = fit_grid(demo, 0.02)
    assert grid.dt <= 0.02 / 4 + 1e-12
    assert grid.t.shape[0] < demo.t.shape[0] / 4
    np.testing.assert_allclose(np.diff(grid.t), grid.dt, rtol=1e-9)
    assert grid.t[0] == 0.0 and grid.t[-1] == pytest.approx(demo.t[-1], abs=1e-12)
    for name in ("x", "v", "a"):
        fine, coarse = getattr(demo, name), getattr(grid, name)
        np.testing.assert_allclose(coarse[[0, -1]], fine[[0, -1]], rtol=0, atol=1e-12 * np.abs(fine).max())
        at_grid = np.stack([np.interp(grid.t, demo.t, fine[:, d]) for d in range(2)], axis=1)
        np.testing.assert_allclose(coarse, at_grid, rtol=0, atol=1e-9 * np.abs(fine).max())


def test_a_dense_demonstration_learns_the_model_of_its_sparser_sampling() -> None:
    """The fit grid makes 1 kHz and 250 Hz samplings of one motion learn nearly the same model
    (and the model keeps the demonstration's own time base)."""
    fine = PhaseSpaceModel.fit(*_wave(1000.0))
    sparse = PhaseSpaceModel.fit(*_wave(250.0))
    assert fine.to_dict()["demo_dt"] == pytest.approx(1e-3)
    for c_fine, c_sparse in zip(fine.cut_times, sparse.cut_times, strict=True):
        assert abs(len(c_fine) - len(c_sparse)) <= 2  # the greedy splits may land differently
        assert c_fine[0] == 0.0 and c_fine[-1] == pytest.approx(3.0)
    t, X = _wave(1000.0)
    for model in (fine, sparse):
        r = model.rollout(dt=0.002)
        assert r.done and abs(r.t[-1] - 3.0) < 0.02
        at_demo = np.stack([np.interp(t, r.t, r.x[:, d]) for d in range(2)], axis=1)
        assert np.max(np.abs(at_demo - X)) < 5e-3  # m, on a 0.5 m motion (tolerance 2.5 mm)
