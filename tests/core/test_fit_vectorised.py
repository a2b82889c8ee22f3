"""The vectorised fitting kernels against scalar references (seeded; analytic where possible).

The fit batches its numerical work across segments and dimensions (``psm.fitting``); these tests
pin every batched piece to the scalar form it replaces, and the lockstep splitting to the plain
greedy order, so the learned model does not depend on how the work is batched.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.signal import fftconvolve
from trajectories import minimum_jerk

from psm import PhaseSpaceModel, fitting, pstf


def _segment_batch(rng: np.random.Generator, n: int, k_sign: int) -> tuple[np.ndarray, ...]:
    """``n`` random PSTFs ``(t, x_c, v_c, k, c)`` with ``k`` of sign ``k_sign`` (0: mixed, with
    some ``k = 0``), ``|k| t²`` from 1e-12 (the series branch) to ~30, and some ``t = 0``."""
    x_c = rng.uniform(-1.0, 1.0, n)
    v_c = rng.uniform(-2.0, 2.0, n)
    c = rng.uniform(-5.0, 5.0, n)
    sign = rng.choice([-1.0, 1.0], n) if k_sign == 0 else np.full(n, float(k_sign))
    k = sign * 10.0 ** rng.uniform(-8.0, 1.5, n)
    t = rng.uniform(0.0, 1.0, n)
    t[::13] = 0.0
    t[::19] *= 1e-4
    if k_sign == 0:
        k[::17] = 0.0
    return t, x_c, v_c, k, c


@pytest.mark.parametrize("k_sign", [0, -1, 1])
def test_positions_equal_propagate(k_sign: int) -> None:
    rng = np.random.default_rng(11 + k_sign)
    t, x_c, v_c, k, c = _segment_batch(rng, 3000, k_sign)
    x = pstf.positions(t, x_c, v_c, k, c)
    ref = np.array([pstf.propagate(*args)[0] for args in zip(t, x_c, v_c, k, c, strict=True)])
    # Relative to the size of the terms summed (a position near 0 has no relative precision).
    scale = np.abs(x_c) + np.abs(v_c * t) + np.abs((k * x_c + c) * t * t) * np.cosh(np.sqrt(np.abs(k)) * t)
    assert np.all(np.abs(x - ref) <= 1e-12 * scale)


def test_positions_broadcast_and_equal_the_closed_forms_of_design_section_4() -> None:
    t = np.linspace(0.0, 1.5, 301)
    x_c, v_c, c = 0.2, 0.7, -1.3
    for k in (4.0, -9.0, 0.0):
        x = pstf.positions(t, x_c, v_c, k, c)
        assert x.shape == t.shape
        if k > 0:
            w = math.sqrt(k)
            A = (x_c + v_c / w + c / k) / 2
            B = (x_c - v_c / w + c / k) / 2
            exact = A * np.exp(w * t) + B * np.exp(-w * t) - c / k
        elif k < 0:
            w = math.sqrt(-k)
            exact = (x_c + c / k) * np.cos(w * t) + (v_c / w) * np.sin(w * t) - c / k
        else:
            exact = x_c + v_c * t + c * t * t / 2
        np.testing.assert_allclose(x, exact, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(x, pstf.propagate(t, x_c, v_c, k, c)[0], rtol=1e-12, atol=1e-14)


def _demo(T: int = 600, D: int = 2, seed: int = 3) -> fitting.SmoothedDemo:
    """A smoothed random motion from rest to rest with reversals (a few sines of a minimum-jerk
    phase) and 0.2 mm noise, ``T`` samples at 2 ms, ``D`` dimensions."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.002
    s = minimum_jerk(t, t[-1])
    X = np.stack(
        [0.1 * np.sin(2 * np.pi * rng.uniform(0.5, 1.5) * s + rng.uniform(0, 6)) for _ in range(D)], axis=1
    )
    return fitting.smooth(t, X + rng.normal(0.0, 2e-4, X.shape), 0.02)


def test_batched_least_squares_equals_the_scalar_line() -> None:
    demo = _demo(D=1)
    x, v, a = demo.x[:, 0], demo.v[:, 0], demo.a[:, 0]
    sums = fitting._PrefixSums(demo.x, demo.a)
    rng = np.random.default_rng(5)
    first = rng.integers(0, x.size - 10, 400)
    last = first + rng.integers(5, 300, 400)
    last = np.minimum(last, x.size - 1)
    kappa = rng.uniform(0.0, 3.0, 400)
    # Knot velocities along each range (as the fit's boundary makes them), so both forms agree.
    delta = x[last] - x[first]
    v_c = np.where(v[first] * delta >= 0.0, v[first], 0.0)
    v_n = np.where(v[last] * delta >= 0.0, v[last], 0.0)
    start = np.stack([x[first], v_c * v_c, np.abs(v_c)])
    end = np.stack([x[last], v_n * v_n, np.abs(v_n)])
    k, sse = sums.fit(first, last + 1, last - first, start, end, kappa)
    for s in range(400):
        i, j = int(first[s]), int(last[s])
        k_cap = pstf.k_limit(v_c[s], v_n[s], delta[s], kappa[s] if delta[s] != 0.0 else 0.0)
        k_ref, sse_ref = sums.line(0, i, j, x[i], v_c[s], x[j], v_n[s], k_cap)
        assert k[s] == pytest.approx(k_ref, rel=1e-12, abs=1e-12)
        assert sse[s] == pytest.approx(sse_ref, rel=1e-12, abs=1e-12 * float(np.sum(a[i : j + 1] ** 2)))
    # The sums themselves: the prefix sums of x, x², a, a², x·a of that dimension.
    i, j = 17, 400
    expected = [x[i : j + 1], x[i : j + 1] ** 2, a[i : j + 1], a[i : j + 1] ** 2, x[i : j + 1] * a[i : j + 1]]
    got = sums.rows[:, j + 1] - sums.rows[:, i]
    np.testing.assert_allclose(got, [np.sum(e) for e in expected], rtol=1e-10)


def _reference_split(seg: fitting._Segmenter, lo: int, hi: int, cand: np.ndarray) -> int:
    """The split search as written before batching: 1-D prefix sums, one segment at a time."""
    x, v, dt, mu = seg.x, seg.v_knot, seg.dt, seg.min_speed_ratio
    a = seg.sums.rows[2, seg.d * seg.sums.stride + 1 : (seg.d + 1) * seg.sums.stride]
    a = np.diff(np.concatenate([[0.0], a]))  # back from the prefix sums to the samples
    starts = np.concatenate([np.full(cand.size, lo), cand])
    ends = np.concatenate([cand, np.full(cand.size, hi)])
    sse = np.empty(starts.size)
    for s, (i, j) in enumerate(zip(starts, ends, strict=True)):
        xs, as_ = x[i : j + 1], a[i : j + 1]
        delta = x[j] - x[i]
        kap = (2.0 * mu / ((j - i) * dt)) ** 2 * (delta != 0.0)
        c0 = (v[j] ** 2 - v[i] ** 2) / (2.0 * delta)
        m = 0.5 * (x[i] + x[j])
        num = np.sum((as_ - c0) * (xs - m))
        den = np.sum((xs - m) ** 2)
        k = min(num / den, pstf.K_MAX_FRACTION * ((abs(v[i]) + abs(v[j])) / delta) ** 2 - kap)
        sse[s] = max(np.sum((as_ - c0 - k * (xs - m)) ** 2), 0.0)
    total = sse[: cand.size] + sse[cand.size :]
    return int(cand[np.argmin(total)])


def _segmenters(demo: fitting.SmoothedDemo, k_fit: str = "duration") -> list[fitting._Segmenter]:
    v_knot = demo.v.copy()  # at rest at the ends and the reversals, as fit_dimensions makes it
    v_knot[0] = v_knot[-1] = 0.0
    for d in range(demo.x.shape[1]):
        v_knot[fitting.turning_points(demo.x[:, d], 1e-3), d] = 0.0
    samples = fitting._Samples(demo.t, demo.x, v_knot, demo.a, demo.dt, 0.5)
    return [fitting._Segmenter(samples, d, 0.5, k_fit) for d in range(demo.x.shape[1])]


def test_batched_split_search_equals_the_reference_split() -> None:
    demo = _demo(T=900, D=3, seed=8)
    segs = _segmenters(demo)
    jobs = []
    for seg in segs:
        turns = fitting.turning_points(seg.x, 1e-3)
        bounds = [0, *turns, seg.x.size - 1]
        for lo, hi in itertools.pairwise(bounds):
            cand = seg.split_candidates(lo, hi, 10, 1e-3)
            if cand.size:
                jobs.append((seg, lo, hi, cand))
    assert len(jobs) >= 4
    assert fitting._split_points(jobs) == [_reference_split(*job) for job in jobs]


def _reference_deviation(seg: fitting._Segmenter, lo: int, hi: int) -> float:
    """The deviation check as written before batching: a scalar loop over ~32 samples."""
    x_c, v_c, x_n, v_n = seg.boundary(lo, hi)
    k = seg.slope(lo, hi)
    c = pstf.coefficient_c(x_c, v_c, x_n, v_n, k)
    t_end = pstf.time_to_reach(x_c, v_c, x_n, v_n, k)
    worst = 0.0
    for i in range(lo, hi + 1, max(1, (hi - lo) // 32)):
        elapsed = float(seg.t[i]) - float(seg.t[lo])
        x_model = float(pstf.propagate(elapsed, x_c, v_c, k, c)[0]) if elapsed <= t_end else x_n
        worst = max(worst, abs(x_model - float(seg.x[i])))
    return worst


@pytest.mark.parametrize("k_fit", ["duration", "least_squares"])
def test_batched_deviations_equal_the_scalar_loop(k_fit: str) -> None:
    demo = _demo(T=1200, D=3, seed=4)
    segs = _segmenters(demo, k_fit)
    rng = np.random.default_rng(9)
    batch = []
    for seg in segs:
        turns = fitting.turning_points(seg.x, 1e-3)
        bounds = [0, *turns, seg.x.size - 1]
        for lo, hi in itertools.pairwise(bounds):
            batch.append((seg, lo, hi))
            if hi - lo > 60:  # and a sub-segment, as the splitting makes them
                mid = int(rng.integers(lo + 20, hi - 20))
                batch.append((seg, lo, mid))
    got = fitting._deviations(batch)
    ref = [_reference_deviation(*item) for item in batch]
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
    assert max(ref) > 1e-4  # the check is not vacuous


def _sequential_auto_cuts(
    cuts: list[int],
    seg: fitting._Segmenter,
    tol: float,
    min_samples: int,
    min_delta: float,
    max_segments: int,
) -> list[int]:
    """Greedy top-down splitting of one dimension, one split at a time (the order to reproduce)."""
    cuts = sorted(set(cuts))
    error = {lo: fitting._errors([(seg, lo, hi)], tol)[0] for lo, hi in itertools.pairwise(cuts)}
    blocked: set[int] = set()
    while len(cuts) - 1 < max_segments:
        worst, worst_err = -1, tol
        for idx, lo in enumerate(cuts[:-1]):
            if lo not in blocked and error[lo] > worst_err:
                worst, worst_err = idx, error[lo]
        if worst < 0:
            break
        lo, hi = cuts[worst], cuts[worst + 1]
        cand = seg.split_candidates(lo, hi, min_samples, min_delta)
        if cand.size == 0:
            blocked.add(lo)
            continue
        s = fitting._split_points([(seg, lo, hi, cand)])[0]
        cuts.insert(worst + 1, s)
        error[lo] = fitting._errors([(seg, lo, s)], tol)[0]
        error[s] = fitting._errors([(seg, s, hi)], tol)[0]
    return cuts


@pytest.mark.parametrize(("tol", "max_segments"), [(5e-4, 24), (1e-4, 24), (3e-4, 8), (2e-5, 6)])
def test_lockstep_splitting_keeps_the_greedy_order_of_each_dimension(tol: float, max_segments: int) -> None:
    """With and without ``max_segments`` stopping the splitting (then the order decides the cuts)."""
    demo = _demo(T=1500, D=3, seed=12)
    segs = _segmenters(demo)
    cuts = [[0, *fitting.turning_points(seg.x, 1e-3), seg.x.size - 1] for seg in segs]
    got = fitting._auto_cuts([list(c) for c in cuts], segs, tol, 10, 1e-3, max_segments)
    ref = [
        _sequential_auto_cuts(list(c), seg, tol, 10, 1e-3, max_segments)
        for c, seg in zip(cuts, segs, strict=True)
    ]
    assert got == ref
    assert sum(map(len, ref)) > sum(map(len, cuts))  # some splitting happened


def test_fitting_dimensions_together_equals_one_at_a_time(noisy_reach_demo) -> None:
    t, X = noisy_reach_demo
    X = X.copy()
    X[:, 1] = 0.1 + 1e-7 * np.sin(t)  # and a hold dimension
    demo = fitting.smooth(*fitting.validate_demonstration(t, X), 0.02)
    for segments in ("auto", 5):
        kw = dict(
            hold_tolerance=1e-4,
            auto_tolerance=5e-4,
            max_segments=24,
            min_speed_ratio=0.5,
            min_segment_samples=10,
            k_fit="duration",
        )
        together = fitting.fit_dimensions(demo.t, demo.x, demo.v, demo.a, demo.dt, segments, **kw)
        for d, fit in enumerate(together):
            one = slice(d, d + 1)
            (alone,) = fitting.fit_dimensions(
                demo.t, demo.x[:, one], demo.v[:, one], demo.a[:, one], demo.dt, segments, **kw
            )
            for field in ("knots", "velocities", "k", "kappa", "durations", "cut_indices"):
                np.testing.assert_array_equal(getattr(fit, field), getattr(alone, field))
            assert fit.hold == alone.hold == (d == 1)


def test_fft_smoothing_equals_fftconvolve() -> None:
    rng = np.random.default_rng(2)
    X = np.cumsum(rng.normal(size=(3000, 3)), axis=0)
    sigma = 20.0
    radius = int(4.0 * sigma + 0.5)
    u = np.arange(-radius, radius + 1, dtype=float)
    kernel = np.exp(-0.5 * (u / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([np.repeat(X[:1], radius, axis=0), X, np.repeat(X[-1:], radius, axis=0)])
    ref = fftconvolve(padded, kernel[:, None], mode="valid", axes=0)
    np.testing.assert_allclose(
        fitting._gaussian_smooth(X, sigma), ref, rtol=0.0, atol=1e-12 * np.max(np.abs(X))
    )


def test_a_fit_is_deterministic_and_unchanged_by_batching(reach_demo) -> None:
    """The public API end to end: two fits agree bit for bit (no state leaks between fits)."""
    t, X = reach_demo
    a, b = PhaseSpaceModel.fit(t, X), PhaseSpaceModel.fit(t, X)
    for d in range(3):
        np.testing.assert_array_equal(a.k[d], b.k[d])
        assert a.cut_times[d] == b.cut_times[d]
