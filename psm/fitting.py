"""Learning one dimension of a PSM from a demonstration (paper §III-C, DESIGN §4).

Pipeline for each dimension of a demonstration ``t (T,) [s]``, ``X (T, D)``:

1. validate and put on a uniform time grid (:func:`validate_demonstration`);
2. Gaussian-kernel smoothing (sigma in seconds) and numerical derivatives (:func:`smooth`);
3. cut points: every direction reversal is a cut (:func:`turning_points`, a zig-zag filter with
   hysteresis so sensor noise is not a reversal); on top of that either the paper's cuts uniform in
   time (``segments=N``), the user's cut times, or ``"auto"`` (:func:`auto_cuts`): top-down splitting
   that minimises the piecewise-linear fit error in the position–acceleration plane until every
   segment is under a tolerance;
4. per segment: ``ẍ = c₀ + k (x − m)`` with ``c₀`` fixed by the boundary velocities (corrected eq. 5)
   and ``k`` by closed-form least squares, clamped below the stability bound (:mod:`psm.pstf`).

Least squares over any sample range is O(1) from prefix sums (:class:`_PrefixSums`), which makes
``"auto"`` a handful of vectorised passes instead of a search over all partitions.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter1d
from scipy.signal import fftconvolve

from psm.errors import DemonstrationError, ParameterError
from psm.pstf import K_MAX_FRACTION, coefficient_c, k_for_duration, k_limit, position, time_to_reach

#: Fewest samples a demonstration may have.
MIN_SAMPLES = 8
#: Time stamps whose spacing varies less than this (relative) are used as they are; otherwise the
#: demonstration is linearly resampled to its median spacing.
UNIFORM_RTOL = 1e-3


@dataclass(frozen=True)
class SmoothedDemo:
    """A demonstration on a uniform grid, smoothed and differentiated.

    ``t (T,) [s]`` starting at 0; ``x, v, a (T, D)``: position [unit], velocity [unit/s],
    acceleration [unit/s²]; ``dt [s]`` the grid spacing.
    """

    t: NDArray[np.float64]
    x: NDArray[np.float64]
    v: NDArray[np.float64]
    a: NDArray[np.float64]
    dt: float


@dataclass(frozen=True)
class DimensionFit:
    """The learned PSTF chain of one dimension.

    ``knots (N+1,)`` via-point positions [unit] (absolute, demonstration frame), ``velocities (N+1,)``
    [unit/s], ``k (N,)`` [1/s²], ``kappa (N,)`` stability margins [1/s²], ``durations (N,)`` [s]
    the model's nominal time per segment, ``cut_indices (N+1,)`` the demonstration samples of the
    knots, ``hold`` true when the dimension barely moves (one rest-to-rest segment).
    """

    knots: NDArray[np.float64]
    velocities: NDArray[np.float64]
    k: NDArray[np.float64]
    kappa: NDArray[np.float64]
    durations: NDArray[np.float64]
    cut_indices: NDArray[np.int64]
    hold: bool


def validate_demonstration(t: ArrayLike, X: ArrayLike) -> tuple[NDArray, NDArray]:
    """Check a demonstration and return it as float arrays ``t (T,)``, ``X (T, D)`` on a uniform grid.

    ``X`` may be ``(T,)`` for one dimension. Raises :class:`DemonstrationError` naming the problem:
    non-finite values, fewer than :data:`MIN_SAMPLES` samples, non-increasing time, length mismatch.
    """
    try:
        t = np.asarray(t, dtype=float)
        X = np.asarray(X, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DemonstrationError(f"demonstration is not numeric: {exc}") from None
    if t.ndim != 1:
        raise DemonstrationError(f"t must have shape (T,), got {t.shape}")
    if X.ndim == 1:
        X = X[:, None]
    if X.ndim != 2:
        raise DemonstrationError(f"X must have shape (T, D), got {X.shape}")
    if X.shape[0] != t.shape[0]:
        raise DemonstrationError(f"t has {t.shape[0]} samples but X has {X.shape[0]}")
    if X.shape[1] == 0:
        raise DemonstrationError("X has no dimension (D = 0)")
    if t.shape[0] < MIN_SAMPLES:
        raise DemonstrationError(f"need at least {MIN_SAMPLES} samples, got {t.shape[0]}")
    if not np.all(np.isfinite(t)):
        raise DemonstrationError(f"t has a non-finite value at index {int(np.argmin(np.isfinite(t)))}")
    bad = ~np.isfinite(X)
    if bad.any():
        i, d = np.argwhere(bad)[0]
        raise DemonstrationError(f"X has a non-finite value at sample {i}, dimension {d}")
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0))
        raise DemonstrationError(f"t must be strictly increasing (t[{i + 1}] <= t[{i}])")
    dt = float(np.median(steps))
    if np.max(np.abs(steps - dt)) > UNIFORM_RTOL * dt:
        grid = t[0] + dt * np.arange(math.floor((t[-1] - t[0]) / dt + 1e-9) + 1)
        X = np.stack([np.interp(grid, t, X[:, d]) for d in range(X.shape[1])], axis=1)
        t = grid
    return t - t[0], X


def smooth(t: NDArray, X: NDArray, sigma: float) -> SmoothedDemo:
    """Gaussian-kernel smoothing with standard deviation ``sigma`` [s] (0 disables it; the ends are
    point-reflected so they are not pulled inwards), then velocity and acceleration by second-order
    central differences.
    ``t (T,)`` uniform, ``X (T, D)``."""
    if not (sigma >= 0.0 and math.isfinite(sigma)):
        raise ParameterError(f"smoothing must be a finite number of seconds >= 0, got {sigma}")
    dt = float(t[1] - t[0])
    if sigma > 0:
        # Point-reflect the demonstration about its end samples before filtering: the start and
        # the goal stay where they were measured and the motion's slope continues through them
        # (padding with the end value would pull a motion still moving there inwards).
        pad = min(math.ceil(4.0 * sigma / dt), X.shape[0] - 1)
        head = 2.0 * X[0] - X[pad:0:-1]
        tail = 2.0 * X[-1] - X[-2 : -pad - 2 : -1]
        padded = np.concatenate([head, X, tail])
        x = _gaussian_smooth(padded, sigma / dt)[pad : pad + X.shape[0]]
    else:
        x = X.copy()
    v = np.gradient(x, dt, axis=0)
    a = np.gradient(v, dt, axis=0)
    return SmoothedDemo(t=t, x=x, v=v, a=a, dt=dt)


def _gaussian_smooth(X: NDArray, sigma_samples: float) -> NDArray:
    """Gaussian smoothing of ``X (T, D)`` along time with ``sigma_samples``; the kernel is truncated
    at 4 sigma. Long kernels are applied by FFT (O(T log T)), short ones directly; the edges are the
    caller's (the samples beyond the ends are taken as equal to the end samples)."""
    radius = int(4.0 * sigma_samples + 0.5)
    if radius < 16 or X.shape[0] < 4 * radius:
        return gaussian_filter1d(X, sigma_samples, axis=0, mode="nearest")
    u = np.arange(-radius, radius + 1, dtype=float)
    kernel = np.exp(-0.5 * (u / sigma_samples) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([np.repeat(X[:1], radius, axis=0), X, np.repeat(X[-1:], radius, axis=0)])
    return fftconvolve(padded, kernel[:, None], mode="valid", axes=0)


def turning_points(x: NDArray, tolerance: float) -> list[int]:
    """Indices of direction reversals of ``x (T,)``, ignoring reversals smaller than ``tolerance``.

    A zig-zag filter: a local extremum becomes a cut only once the motion has come back from it by
    at least ``tolerance`` [unit]; the extreme sample of each leg is the cut. Endpoints excluded.
    """
    dx = np.diff(x)
    sign = np.sign(dx)
    nz = np.flatnonzero(sign)
    if nz.size < 2:
        return []
    flips = nz[1:][sign[nz[1:]] != sign[nz[:-1]]]  # first step of each new direction
    candidates = [*list(flips), x.shape[0] - 1]
    pivots: list[int] = []
    trend = 0.0
    origin = 0
    extreme = 0
    for i in candidates:
        xi = x[i]
        if trend == 0.0:
            if abs(xi - x[origin]) >= tolerance:
                trend = math.copysign(1.0, xi - x[origin])
                extreme = i
            continue
        if (xi - x[extreme]) * trend > 0.0:
            extreme = i
        elif (x[extreme] - xi) * trend >= tolerance:
            pivots.append(extreme)
            trend = -trend
            extreme = i
    if trend == 0.0:
        return []
    # Refine each pivot to the extreme sample between its neighbours (candidates are step starts).
    refined = []
    bounds = [0, *pivots, x.shape[0] - 1]
    for p_i, p in enumerate(pivots):
        lo, hi = bounds[p_i], bounds[p_i + 2]
        window = x[lo : hi + 1]
        refined.append(lo + int(np.argmax(window) if x[p] >= x[lo] else np.argmin(window)))
    return refined


class _PrefixSums:
    """Prefix sums of one dimension's samples, for O(1) least squares over any index range."""

    def __init__(self, x: NDArray, a: NDArray) -> None:
        zero = np.zeros(1)
        self.sx = np.concatenate([zero, np.cumsum(x)])
        self.sxx = np.concatenate([zero, np.cumsum(x * x)])
        self.sa = np.concatenate([zero, np.cumsum(a)])
        self.saa = np.concatenate([zero, np.cumsum(a * a)])
        self.sxa = np.concatenate([zero, np.cumsum(x * a)])

    def slope(self, i: int, j: int, x_c: float, v_c: float, x_n: float, v_n: float) -> float:
        """Unclamped least-squares ``k`` [1/s²] over samples ``i..j`` with the given end states."""
        return self.line(i, j, x_c, v_c, x_n, v_n, math.inf)[0]

    def line(
        self, i: int, j: int, x_c: float, v_c: float, x_n: float, v_n: float, k_cap: float
    ) -> tuple[float, float]:
        """Scalar :meth:`fit` of one range: ``(k, sse)`` with ``k`` clamped to ``k_cap``."""
        n = j - i + 1
        delta = x_n - x_c
        if delta == 0.0:
            return -math.inf, math.inf
        c0 = (v_n * v_n - v_c * v_c) / (2.0 * delta)
        m = 0.5 * (x_c + x_n)
        sx = float(self.sx[j + 1] - self.sx[i])
        sa = float(self.sa[j + 1] - self.sa[i])
        num = float(self.sxa[j + 1] - self.sxa[i]) - m * sa - c0 * sx + n * c0 * m
        den = float(self.sxx[j + 1] - self.sxx[i]) - 2.0 * m * sx + n * m * m
        if den <= 0.0:
            return -math.inf, math.inf
        k = min(num / den, k_cap)
        sse = float(self.saa[j + 1] - self.saa[i]) - 2.0 * c0 * sa + n * c0 * c0 - 2.0 * k * num + k * k * den
        return k, max(sse, 0.0)

    def fit(
        self,
        i: NDArray,
        j: NDArray,
        x: NDArray,
        v: NDArray,
        kappa: NDArray,
        k_rest: NDArray,
    ) -> tuple[NDArray, NDArray]:
        """Least-squares ``k`` and residual sum of squares of ``a ≈ c₀ + k (x − m)`` over samples
        ``i..j`` (inclusive, arrays of equal shape), with ``c₀, m`` from the end samples and ``k``
        clamped to ``ρ k_max − kappa``. ``k_rest`` replaces ``k`` where the ends are both at rest and
        the clamp leaves no valid slope. Returns ``(k, sse)`` [1/s², unit²/s⁴]."""
        n = (j - i + 1).astype(float)
        sx = self.sx[j + 1] - self.sx[i]
        sxx = self.sxx[j + 1] - self.sxx[i]
        sa = self.sa[j + 1] - self.sa[i]
        saa = self.saa[j + 1] - self.saa[i]
        sxa = self.sxa[j + 1] - self.sxa[i]
        x_c, x_n, v_c, v_n = x[i], x[j], v[i], v[j]
        delta = x_n - x_c
        safe = np.where(delta == 0.0, 1.0, delta)
        c0 = (v_n * v_n - v_c * v_c) / (2.0 * safe)
        m = 0.5 * (x_c + x_n)
        num = sxa - m * sa - c0 * sx + n * c0 * m
        den = sxx - 2.0 * m * sx + n * m * m
        k_ls = num / np.where(den > 0.0, den, 1.0)
        k_cap = K_MAX_FRACTION * ((np.abs(v_c) + np.abs(v_n)) / safe) ** 2 - kappa
        k = np.minimum(k_ls, k_cap)
        k = np.where(np.isfinite(k), k, k_rest)
        sse = saa - 2.0 * c0 * sa + n * c0 * c0 - 2.0 * k * num + k * k * den
        return k, np.maximum(sse, 0.0)


def _segment_kappa(delta: NDArray, duration: NDArray, min_speed_ratio: float) -> NDArray:
    """Stability margin ``(2μ/T)²`` [1/s²] of segments lasting ``duration`` [s] in the demo."""
    return (2.0 * min_speed_ratio / np.maximum(duration, 1e-12)) ** 2 * (delta != 0.0)


class _Segmenter:
    """Fits one segment of one dimension between two sample indices (inclusive).

    ``x (T,)`` smoothed positions, ``v_knot (T,)`` velocities to use when a sample is a via-point
    (zero at reversals and at the end), ``sums`` prefix sums of ``x`` and the acceleration.
    """

    def __init__(
        self, t: NDArray, x: NDArray, v_knot: NDArray, dt: float, sums: _PrefixSums,
        min_speed_ratio: float, k_fit: str,
    ) -> None:
        self.t, self.x, self.v_knot, self.dt = t, x, v_knot, dt
        self.sums, self.min_speed_ratio, self.k_fit = sums, min_speed_ratio, k_fit
        self._slopes: dict[tuple[int, int, float, float], float] = {}

    def boundary(self, lo: int, hi: int) -> tuple[float, float, float, float]:
        """``(x_c, v_c, x_n, v_n)``; a knot velocity pointing against the segment (noise) is 0."""
        x_c, x_n = float(self.x[lo]), float(self.x[hi])
        v_c, v_n = float(self.v_knot[lo]), float(self.v_knot[hi])
        delta = x_n - x_c
        return x_c, (v_c if v_c * delta >= 0.0 else 0.0), x_n, (v_n if v_n * delta >= 0.0 else 0.0)

    def kappa(self, lo: int, hi: int) -> float:
        """Stability margin ``(2μ/T)²`` [1/s²] of the segment."""
        if self.x[hi] == self.x[lo]:
            return 0.0
        return (2.0 * self.min_speed_ratio / ((hi - lo) * self.dt)) ** 2

    def slope(self, lo: int, hi: int) -> float:
        """The segment's ``k`` [1/s²]: least squares (clamped) or the demonstrated duration."""
        key = (lo, hi, float(self.v_knot[lo]), float(self.v_knot[hi]))
        if key not in self._slopes:
            self._slopes[key] = self._slope(lo, hi)
        return self._slopes[key]

    def _slope(self, lo: int, hi: int) -> float:
        x_c, v_c, x_n, v_n = self.boundary(lo, hi)
        kap = self.kappa(lo, hi)
        k_cap = k_limit(v_c, v_n, x_n - x_c, kap)
        if self.k_fit == "duration":
            return k_for_duration(x_c, v_c, x_n, v_n, (hi - lo) * self.dt, k_cap)
        return min(self.sums.slope(lo, hi, x_c, v_c, x_n, v_n), k_cap)

    def deviation(self, lo: int, hi: int) -> float:
        """Largest |PSTF − demonstration| [unit] over the segment's samples, the PSTF started at the
        segment's first via-point at its time (timing drift inside the segment counts)."""
        x_c, v_c, x_n, v_n = self.boundary(lo, hi)
        k = self.slope(lo, hi)
        c = coefficient_c(x_c, v_c, x_n, v_n, k)
        t_end = time_to_reach(x_c, v_c, x_n, v_n, k)
        # At most ~32 evenly spaced samples (the deviation is smooth at the sample scale), on
        # Python floats: this runs a dozen times per dimension and numpy's per-call cost dominates.
        t0 = float(self.t[lo])
        worst = 0.0
        for i in range(lo, hi + 1, max(1, (hi - lo) // 32)):
            elapsed = float(self.t[i]) - t0
            # Past its arrival the PSTF would continue; the chain moves on to the next segment.
            x_model = position(elapsed, x_c, v_c, k, c) if elapsed <= t_end else x_n
            worst = max(worst, abs(x_model - float(self.x[i])))
        return worst

    def error(self, lo: int, hi: int, tolerance: float) -> float:
        """The segment's :meth:`deviation`, skipped (0) when a cheap O(1) estimate already shows it
        within ``tolerance``: an RMS acceleration residual ``e`` of the best line over a segment of
        duration ``T`` bends the path by about ``e T²/8``, so ``2 e T²/8 ≤ tolerance`` (a factor 2
        of safety) accepts it without computing the PSTF. Noise inflates ``e``, so the shortcut
        never accepts a noisy segment the exact test would reject."""
        x_c, v_c, x_n, v_n = self.boundary(lo, hi)
        _, sse = self.sums.line(lo, hi, x_c, v_c, x_n, v_n, k_limit(v_c, v_n, x_n - x_c, self.kappa(lo, hi)))
        duration = (hi - lo) * self.dt
        if 2.0 * math.sqrt(sse / (hi - lo + 1)) * duration * duration / 8.0 <= tolerance:
            return 0.0
        return self.deviation(lo, hi)

    def split_sse(self, lo: int, hi: int, cand: NDArray) -> NDArray:
        """Residual sums of squares of the acceleration line fits of ``lo..c`` plus ``c..hi`` for every
        candidate cut ``c`` in ``cand`` (one vectorised evaluation)."""
        n_c = cand.size
        starts = np.concatenate([np.full(n_c, lo), cand])
        ends = np.concatenate([cand, np.full(n_c, hi)])
        kap = _segment_kappa(self.x[ends] - self.x[starts], (ends - starts) * self.dt, self.min_speed_ratio)
        _, sse = self.sums.fit(starts, ends, self.x, self.v_knot, kap, -kap)
        return sse[:n_c] + sse[n_c:]


def auto_cuts(
    cuts: list[int],
    segmenter: _Segmenter,
    tolerance: float,
    min_samples: int,
    min_delta: float,
    max_segments: int,
) -> list[int]:
    """Refine ``cuts`` (sorted sample indices including both ends) by top-down splitting.

    ``tolerance`` [unit] is a position budget: a segment is split while its PSTF, started at the
    segment's first via-point, deviates from the (smoothed) demonstration by more than that at any
    sample (:meth:`_Segmenter.deviation`). Judging positions, not accelerations, makes the criterion
    blind to zero-mean acceleration noise, which bends no path. The worst segment is split at the
    sample that minimises the two halves' residual in the position–acceleration plane (O(1) per
    candidate from prefix sums), each half having at least ``min_samples`` samples and moving at
    least ``min_delta`` [unit], until every segment is within budget or ``max_segments`` exist.
    Velocity sign changes never fall inside a segment: the reversals are cuts already.
    """
    x = segmenter.x
    cuts = sorted(set(cuts))
    error = {lo: segmenter.error(lo, hi, tolerance) for lo, hi in itertools.pairwise(cuts)}
    blocked: set[int] = set()
    while len(cuts) - 1 < max_segments:
        worst, worst_err = -1, tolerance
        for idx, lo in enumerate(cuts[:-1]):
            if lo not in blocked and error[lo] > worst_err:
                worst, worst_err = idx, error[lo]
        if worst < 0:
            break
        lo, hi = cuts[worst], cuts[worst + 1]
        cand = np.arange(lo + min_samples, hi - min_samples + 1)
        if cand.size:
            ok = (np.abs(x[cand] - x[lo]) >= min_delta) & (np.abs(x[hi] - x[cand]) >= min_delta)
            cand = cand[ok]
        if cand.size == 0:
            blocked.add(lo)
            continue
        if cand.size > 128:  # at most ~128 evenly spaced candidates
            cand = cand[:: math.ceil(cand.size / 128)]
        s = int(cand[int(np.argmin(segmenter.split_sse(lo, hi, cand)))])
        cuts.insert(worst + 1, s)
        error[lo] = segmenter.error(lo, s, tolerance)
        error[s] = segmenter.error(s, hi, tolerance)
    return cuts


def _merge_short(cuts: list[int], fixed: set[int], x: NDArray, min_delta: float) -> list[int]:
    """Drop optional cuts that leave a segment moving less than ``min_delta`` [unit]."""
    out = [cuts[0]]
    for c in cuts[1:-1]:
        if c in fixed or (abs(x[c] - x[out[-1]]) >= min_delta and abs(x[cuts[-1]] - x[c]) >= min_delta):
            out.append(c)
    out.append(cuts[-1])
    return out


def fit_dimension(
    demo_t: NDArray,
    x: NDArray,
    v: NDArray,
    a: NDArray,
    dt: float,
    segments: str | int | Sequence[float],
    hold_tolerance: float,
    auto_tolerance: float,
    max_segments: int,
    min_speed_ratio: float,
    min_segment_samples: int,
    k_fit: str = "least_squares",
) -> DimensionFit:
    """Learn the PSTF chain of one dimension from smoothed samples ``x, v, a (T,)``.

    ``segments``: ``"auto"``, a number of segments uniform in time (the paper's choice; direction
    reversals are added as cuts), or a sequence of cut times [s] from the demonstration's start.
    A dimension whose range is below ``hold_tolerance`` [unit] becomes one rest-to-rest hold.
    """
    T = x.shape[0]
    duration = float(demo_t[-1])
    if float(np.ptp(x)) < hold_tolerance:
        knots = np.array([x[0], x[-1]])
        kappa = np.array([(math.pi / duration) ** 2])
        k = -kappa.copy()
        dur = np.array([time_to_reach(x[0], 0.0, x[-1], 0.0, k[0]) if x[-1] != x[0] else 0.0])
        return DimensionFit(
            knots=knots, velocities=np.zeros(2), k=k, kappa=kappa, durations=dur,
            cut_indices=np.array([0, T - 1]), hold=True,
        )
    turns = turning_points(x, hold_tolerance)
    fixed = {0, T - 1, *turns}
    # Motions start and end at rest (a robot starts a skill standing still; a demonstration's
    # first and last velocities are sensor noise around zero), and reverse at rest.
    v_knot = v.copy()
    v_knot[turns] = 0.0
    v_knot[0] = 0.0
    v_knot[-1] = 0.0
    segmenter = _Segmenter(demo_t, x, v_knot, dt, _PrefixSums(x, a), min_speed_ratio, k_fit)
    if isinstance(segments, str):
        if segments != "auto":
            raise ParameterError(f"segments must be 'auto', an int or cut times, got {segments!r}")
        cuts = _merge_short(sorted(fixed), fixed, x, hold_tolerance)
        cuts = auto_cuts(cuts, segmenter, auto_tolerance, min_segment_samples, hold_tolerance, max_segments)
    else:
        if isinstance(segments, int | np.integer):
            if segments < 1:
                raise ParameterError(f"segments must be >= 1, got {segments}")
            times = np.linspace(0.0, duration, int(segments) + 1)[1:-1]
        else:
            times = np.asarray(segments, dtype=float).ravel()
            if not np.all(np.isfinite(times)) or np.any((times <= 0) | (times >= duration)):
                raise ParameterError(f"cut times must lie strictly inside (0, {duration:g}) s")
        extra = {round(tc / dt) for tc in times}
        cuts = _merge_short(sorted(fixed | extra), fixed, x, hold_tolerance)
    cut_idx = np.asarray(cuts, dtype=np.int64)
    bounds = [segmenter.boundary(lo, hi) for lo, hi in itertools.pairwise(cuts)]
    knots = x[cut_idx].copy()
    # A via-point's velocity must suit both segments it joins (noise can flip a near-zero one).
    vel = np.array([b[1] for b in bounds] + [0.0])
    vel[1:-1] = np.where(vel[1:-1] * np.array([b[3] for b in bounds[:-1]]) > 0.0, vel[1:-1], 0.0)
    kappa = np.array([segmenter.kappa(lo, hi) for lo, hi in itertools.pairwise(cuts)])
    v_fit = segmenter.v_knot.copy()
    v_fit[cut_idx] = vel
    segmenter.v_knot = v_fit
    k = np.array([segmenter.slope(lo, hi) for lo, hi in itertools.pairwise(cuts)])
    durations = np.array(
        [time_to_reach(knots[s], vel[s], knots[s + 1], vel[s + 1], k[s]) for s in range(k.size)]
    )
    return DimensionFit(
        knots=knots, velocities=vel, k=k, kappa=kappa, durations=durations,
        cut_indices=cut_idx, hold=False,
    )
