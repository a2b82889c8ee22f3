"""Tests of the trajectory metrics in ``benchmarks/metrics.py`` against analytic values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from benchmarks.metrics import (
    discrete_frechet_distance,
    dtw_distance,
    final_point_error,
    pairwise_distances,
    resample_by_arc_length,
    rmse_over_time,
    trajectory_metrics,
)


def _naive_dp(a: np.ndarray, b: np.ndarray, kind: str) -> float:
    """Textbook double loop (DTW normalised by path cells, or discrete Fréchet)."""
    a = np.atleast_2d(np.asarray(a, float).T).T
    b = np.atleast_2d(np.asarray(b, float).T).T
    N, M = len(a), len(b)
    C = np.array([[math.dist(a[i], b[j]) for j in range(M)] for i in range(N)])
    V = np.full((N, M), np.inf)
    L = np.zeros((N, M), dtype=int)
    for i in range(N):
        for j in range(M):
            if i == 0 and j == 0:
                V[0, 0], L[0, 0] = C[0, 0], 1
                continue
            cands = []
            if i > 0 and j > 0:
                cands.append((V[i - 1, j - 1], L[i - 1, j - 1]))
            if i > 0:
                cands.append((V[i - 1, j], L[i - 1, j]))
            if j > 0:
                cands.append((V[i, j - 1], L[i, j - 1]))
            best = min(cands, key=lambda c: c[0])  # first minimum: diag, up, left
            V[i, j] = C[i, j] + best[0] if kind == "dtw" else max(C[i, j], best[0])
            L[i, j] = best[1] + 1
    return V[-1, -1] / L[-1, -1] if kind == "dtw" else V[-1, -1]


def _line(n: int = 50) -> np.ndarray:
    s = np.linspace(0.0, 1.0, n)
    return np.column_stack([10.0 * s, 4.0 * s])


curves = st.integers(1, 12).flatmap(
    lambda n: arrays(np.float64, (n, 2), elements=st.floats(-100, 100, allow_nan=False, width=64))
)


# ---------------------------------------------------------------- identities / offsets


def test_identical_curves_give_zero() -> None:
    t = np.linspace(0, 2, 200)
    x = np.column_stack([np.sin(3 * t), np.cos(2 * t), t])
    m = trajectory_metrics(t, x, t, x)
    assert m == {"rmse": 0.0, "dtw": 0.0, "frechet": 0.0, "final": 0.0}


def test_perpendicular_shift_gives_exact_offset_for_every_metric() -> None:
    a = _line()
    direction = np.array([10.0, 4.0]) / math.hypot(10.0, 4.0)
    offset = 2.5 * np.array([-direction[1], direction[0]])  # perpendicular, |offset| = 2.5
    b = a + offset
    t = np.linspace(0.0, 1.0, len(a))
    assert rmse_over_time(t, b, t, a) == pytest.approx(2.5, abs=1e-12)
    # every pair (i, j) is at least |offset| apart, the diagonal path is exactly |offset|
    assert dtw_distance(a, b) == pytest.approx(2.5, abs=1e-12)
    assert discrete_frechet_distance(a, b) == pytest.approx(2.5, abs=1e-12)
    assert final_point_error(b, a) == pytest.approx(2.5, abs=1e-12)


def test_shift_along_the_line_frechet_exact_dtw_smaller() -> None:
    a = _line(101)
    step = a[1] - a[0]
    b = a + 3 * step  # shifted by three samples along the line itself
    off = 3 * math.hypot(*step)
    # the start pair alone forces Fréchet >= |offset|; the diagonal coupling achieves it
    assert discrete_frechet_distance(a, b) == pytest.approx(off, rel=1e-12)
    # DTW may re-align interior samples onto each other, so its mean cost is lower
    assert dtw_distance(a, b) < 0.5 * off


# ---------------------------------------------------------------- hand-computed cases


def test_hand_computed_1d_case() -> None:
    # C = [[0, 2], [1, 1], [2, 0]]; DTW path (0,0)-(1,0|1)-(2,1): cost 1 over 3 cells
    assert dtw_distance([0.0, 1.0, 2.0], [0.0, 2.0]) == pytest.approx(1.0 / 3.0)
    assert discrete_frechet_distance([0.0, 1.0, 2.0], [0.0, 2.0]) == pytest.approx(1.0)


def test_against_single_point_is_mean_and_max_distance() -> None:
    a = np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 8.0]])
    p = np.array([[0.0, 0.0]])
    # every sample of a is matched to the single point: mean 5, max 10
    assert dtw_distance(a, p) == pytest.approx(5.0)
    assert discrete_frechet_distance(a, p) == pytest.approx(10.0)


def test_hand_computed_2d_case() -> None:
    a = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]])
    b = np.array([[0.0, 1.0], [2.0, 1.0]])
    # C = [[1, sqrt5], [1, 1], [sqrt5, 1]]: best path (0,0)-(1,0)-(2,1) or (0,0)-(1,1)-(2,1)
    assert dtw_distance(a, b) == pytest.approx(1.0)
    assert discrete_frechet_distance(a, b) == pytest.approx(1.0)
    # b lifted by 1: C = [[2, sqrt8], [sqrt2, sqrt2], [sqrt8, 2]]; both corner cells are 2
    # and the middle can be crossed at sqrt2, so Fréchet = 2 (DTW = (2 + sqrt2 + 2) / 3)
    b2 = b + np.array([0.0, 1.0])
    assert discrete_frechet_distance(a, b2) == pytest.approx(2.0)
    assert dtw_distance(a, b2) == pytest.approx((4.0 + math.sqrt(2.0)) / 3.0)


def test_pairwise_distances_exact() -> None:
    C = pairwise_distances([[0.0, 0.0], [3.0, 4.0]], [[0.0, 0.0], [6.0, 8.0]])
    np.testing.assert_array_equal(C, [[0.0, 10.0], [5.0, 5.0]])


# ---------------------------------------------------------------- properties


@settings(max_examples=60, deadline=None)
@given(a=curves, b=curves)
def test_matches_textbook_double_loop(a: np.ndarray, b: np.ndarray) -> None:
    assert dtw_distance(a, b) == pytest.approx(_naive_dp(a, b, "dtw"), rel=1e-12, abs=1e-9)
    assert discrete_frechet_distance(a, b) == pytest.approx(_naive_dp(a, b, "frechet"), rel=1e-12, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(a=curves, b=curves)
def test_symmetry_and_bounds(a: np.ndarray, b: np.ndarray) -> None:
    f_ab = discrete_frechet_distance(a, b)
    assert f_ab == discrete_frechet_distance(b, a)
    assert dtw_distance(a, b) == pytest.approx(dtw_distance(b, a), rel=1e-12, abs=1e-9)
    # Fréchet couples both start points and both end points
    assert f_ab >= math.dist(a[0], b[0]) - 1e-12
    assert f_ab >= math.dist(a[-1], b[-1]) - 1e-12
    assert dtw_distance(a, b) >= 0.0


@settings(max_examples=40, deadline=None)
@given(a=curves, b=curves, data=st.data())
def test_invariance_to_repeated_samples(a: np.ndarray, b: np.ndarray, data: st.DataObject) -> None:
    """Re-timing a curve on the same samples (holding some samples longer) changes nothing."""
    reps = np.array(data.draw(st.lists(st.integers(1, 4), min_size=len(a), max_size=len(a))))
    a_slow = np.repeat(a, reps, axis=0)
    assert discrete_frechet_distance(a_slow, b) == discrete_frechet_distance(a, b)
    assert discrete_frechet_distance(a_slow, a) == 0.0
    assert dtw_distance(a_slow, a) == 0.0


def test_time_reparametrisation_of_a_dense_curve() -> None:
    """Same path, different speed profile: DTW/Fréchet see ~0, time-indexed RMSE does not."""
    t = np.linspace(0.0, 1.0, 2001)

    def path(s: np.ndarray) -> np.ndarray:
        return np.column_stack([np.cos(np.pi * s), np.sin(np.pi * s)]) * 100.0

    x_uniform = path(t)
    x_eased = path(t**2 * (3 - 2 * t))  # smoothstep re-timing of the same half-circle
    spacing = 100.0 * np.pi / 2000  # max arc length between neighbouring samples
    assert discrete_frechet_distance(x_uniform, x_eased) <= 1.5 * spacing
    assert dtw_distance(x_uniform, x_eased) <= 1.5 * spacing
    assert rmse_over_time(t, x_eased, t, x_uniform) > 10.0


# ---------------------------------------------------------------- RMSE time handling


def test_rmse_interpolates_model_onto_reference_stamps() -> None:
    t_ref = np.array([0.0, 1.0, 2.0])
    # model sampled coarser: linear interpolation recovers the ramp exactly
    assert rmse_over_time([0.0, 2.0], [0.0, 2.0], t_ref, [0.0, 1.0, 2.0]) == 0.0
    # against a zero reference the errors are 0, 1, 2
    got = rmse_over_time([0.0, 2.0], [0.0, 2.0], t_ref, [0.0, 0.0, 0.0])
    assert got == pytest.approx(math.sqrt(5.0 / 3.0))


def test_rmse_holds_final_point_of_shorter_model() -> None:
    t_ref = np.arange(4.0)
    x_ref = np.array([0.0, 1.0, 1.0, 1.0])
    assert rmse_over_time([0.0, 1.0], [0.0, 1.0], t_ref, x_ref) == 0.0
    # a model that stops early at 0.5 is held there: errors 0, .5, .5, .5
    got = rmse_over_time([0.0, 1.0], [0.0, 0.5], t_ref, x_ref)
    assert got == pytest.approx(math.sqrt(0.75 / 4.0))


def test_rmse_ignores_model_tail_after_reference_end() -> None:
    t_model = np.arange(10.0)
    x_model = np.concatenate([[0.0, 1.0], np.full(8, 50.0)])
    assert rmse_over_time(t_model, x_model, [0.0, 1.0], [0.0, 1.0]) == 0.0
    # ... but the final-point error sees it
    assert final_point_error(x_model, [0.0, 1.0]) == 49.0


def test_rmse_uses_relative_time_and_euclidean_norm() -> None:
    t = np.linspace(5.0, 6.0, 11)  # both start at 5 s: shifted to 0
    ref = np.zeros((11, 2))
    model = ref + np.array([3.0, 4.0])
    assert rmse_over_time(t, model, t - 5.0, ref) == pytest.approx(5.0)


def test_invalid_input_raises() -> None:
    with pytest.raises(ValueError, match="NaN"):
        dtw_distance([0.0, np.nan], [0.0])
    with pytest.raises(ValueError, match="dimension"):
        discrete_frechet_distance(np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="increasing"):
        rmse_over_time([0.0, 0.0], [1.0, 2.0], [0.0, 1.0], [1.0, 2.0])


# ---------------------------------------------------------------- arc-length resampling


def test_arc_length_resampling_of_a_line_is_evenly_spaced_with_exact_ends() -> None:
    # samples bunched at the start (a motion accelerating from rest), 3-4-5 direction
    s = np.linspace(0.0, 1.0, 40) ** 3
    x = np.column_stack([3.0 * s, 4.0 * s])
    r = resample_by_arc_length(x, 11)
    assert r.shape == (11, 2)
    np.testing.assert_allclose(r, np.column_stack([np.linspace(0, 3, 11), np.linspace(0, 4, 11)]), atol=1e-12)
    np.testing.assert_array_equal(r[0], x[0])
    np.testing.assert_array_equal(r[-1], x[-1])


def test_arc_length_resampling_skips_repeated_samples_and_keeps_the_corner() -> None:
    corner = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    r = resample_by_arc_length(corner, 5)
    np.testing.assert_allclose(r, [[0, 0], [1, 0], [2, 0], [2, 1], [2, 2]], atol=1e-12)
    np.testing.assert_array_equal(resample_by_arc_length(np.array([[1.0, 2.0], [1.0, 2.0]]), 3), [[1, 2]] * 3)
    with pytest.raises(ValueError, match="n must be"):
        resample_by_arc_length(corner, 1)


def test_arc_length_resampling_removes_the_sampling_phase_from_dtw_and_frechet() -> None:
    """The same curve sampled half a sample later: the discrete metrics see up to half the sample
    spacing; after resampling both curves along their length only the chords' corner cutting
    (spacing² × curvature / 8) remains."""
    t = np.linspace(0.0, 1.0, 201)
    phase = np.pi * t**2  # non-uniform speed along a half circle of radius 50
    a = 50.0 * np.column_stack([np.cos(phase), np.sin(phase)])
    t_half = np.concatenate([[0.0], 0.5 * (t[1:] + t[:-1]), [1.0]])
    b = np.column_stack([np.interp(t_half, t, a[:, d]) for d in range(2)])
    spacing = float(np.max(np.linalg.norm(np.diff(a, axis=0), axis=1)))
    assert dtw_distance(a, b) > 0.1 * spacing
    assert discrete_frechet_distance(a, b) > 0.4 * spacing
    ra, rb = resample_by_arc_length(a, 200), resample_by_arc_length(b, 200)
    corner_cut = spacing**2 / (8.0 * 50.0)
    assert dtw_distance(ra, rb) < 4.0 * corner_cut
    assert discrete_frechet_distance(ra, rb) < 4.0 * corner_cut
    assert 4.0 * corner_cut < 0.05 * spacing  # so the check above is a strong one
