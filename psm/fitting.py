"""Learning one dimension of a PSM from a demonstration (paper §III-C; ``docs/psm.md``).

Pipeline for each dimension of a demonstration ``t (T,) [s]``, ``X (T, D)``:

1. validate and put on a uniform time grid (:func:`validate_demonstration`);
2. Gaussian-kernel smoothing (sigma in seconds) and numerical derivatives (:func:`smooth`);
3. cut points: every direction reversal is a cut (:func:`turning_points`, a zig-zag filter with
   hysteresis so sensor noise is not a reversal); on top of that either the paper's cuts uniform in
   time (``segments=N``), the user's cut times, or ``"auto"`` (:func:`_auto_cuts`): top-down
   splitting at the point that minimises the piecewise-linear fit error in the position–acceleration
   plane, until every segment's PSTF stays within a position tolerance of the demonstration;
   before any of these, the significant velocity extrema of each dimension
   (:func:`velocity_extremum_points`) and the user's ``via_point_times`` become via-points that keep the
   velocity of the unsmoothed demonstration there (:class:`RawDemo`), so that the motion passes
   those positions at the demonstrated speeds;
4. per segment: ``ẍ = c₀ + k (x − m)`` with ``c₀`` fixed by the boundary velocities (corrected eq. 5)
   and ``k`` by ``k_fit``: the demonstrated duration (default) or closed-form least squares, clamped
   below the stability bound (:mod:`psm.pstf`).

Least squares over any sample range is O(1) from prefix sums (:class:`_PrefixSums`), which makes
``"auto"`` a handful of vectorised passes instead of a search over all partitions. All dimensions
are learned together (:func:`fit_dimensions`): the greedy splitting of each dimension is replayed
level by level of its splitting tree (:class:`_Greedy`), so that each round is one vectorised split
search and one vectorised deviation check for every dimension and segment concerned. At the sizes
involved (a few hundred numbers) numpy's per-call cost dominates, so the batches are built to make
as few numpy calls as possible; the result is the same as splitting each dimension on its own.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.fft as sp_fft
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter1d

from psm.errors import DemonstrationError, ParameterError
from psm.pstf import (
    K_MAX_FRACTION,
    coefficient_c,
    k_for_duration,
    k_limit,
    positions_from_acceleration,
    time_to_reach,
)

#: How a segment's ``k`` may be chosen (``k_fit``): the demonstrated duration, or the paper's
#: least squares in the position–acceleration plane.
K_FIT_MODES = ("duration", "least_squares")
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


#: The velocity of a task via-point is read from the unsmoothed demonstration over the narrowest
#: window whose noise leaves at most this fraction of the demonstration's top speed as error
#: (:meth:`RawDemo.velocity`).
RAW_VELOCITY_NOISE = 0.01
#: The noise of the unsmoothed samples at a task via-point is estimated from the samples within
#: this many of it on either side.
RAW_NOISE_SAMPLES = 256
#: A velocity extremum keeps the unsmoothed demonstration's velocity where the smoothed speed is
#: at least this fraction of the demonstration's top speed (a stroke's peak, which the smoothing
#: rounds off), and the smoothed velocity elsewhere: at the slow extrema (the dips between
#: strokes, a slow guided phase) the unsmoothed velocity of a hand-guided recording is mostly
#: the hand's tremor (±0.02 m/s at 8-12 Hz on the committed recordings, a third of a 0.06 m/s
#: guided speed), which the via-point would otherwise impose on the motion. A user's via-point
#: always keeps the unsmoothed velocity.
RAW_VELOCITY_MIN_SPEED = 0.7


@dataclass(frozen=True)
class RawDemo:
    """The demonstration before smoothing, for the velocities of the task via-points (velocity
    extrema and the user's): ``t (T,)`` [s] uniform from 0, ``x (T, D)`` [unit];
    ``speed_scale`` [unit/s] the demonstration's top speed and ``max_window`` [s] the widest
    half-window :meth:`velocity` may use (the smoothing sigma)."""

    t: NDArray[np.float64]
    x: NDArray[np.float64]
    speed_scale: float
    max_window: float

    def half_window(self, i: int, d: int) -> int:
        """The half-width ``n`` [samples] of the line fit of :meth:`velocity` at sample ``i`` of
        dimension ``d``: the least-squares slope over ``2n + 1`` samples of white noise of
        deviation ``s`` has the deviation ``s / (dt √(Σ j²))``, ``Σ j² = n (n + 1)(2n + 1)/3``
        over ``j = −n..n``. ``s`` is :func:`noise_level` of the unsmoothed samples within
        :data:`RAW_NOISE_SAMPLES` of ``i``; ``n`` is the smallest that brings the deviation to
        :data:`RAW_VELOCITY_NOISE` of ``speed_scale`` (1 on clean data: the central difference),
        at most ``max_window / dt``."""
        T = self.t.shape[0]
        dt = float(self.t[1] - self.t[0])
        cap = max(1, math.floor(self.max_window / dt + 1e-9))
        target = RAW_VELOCITY_NOISE * self.speed_scale * dt
        if cap == 1 or not target > 0.0:
            return 1
        lo, hi = max(0, i - RAW_NOISE_SAMPLES), min(T, i + RAW_NOISE_SAMPLES + 1)
        s = float(noise_level(self.x[lo:hi, d : d + 1])[0])
        need = (s / target) ** 2  # Σ j² needed
        n = 1
        while n < cap and n * (n + 1) * (2 * n + 1) / 3.0 < need:
            n += 1
        return n

    def velocity(self, times: NDArray, d: int) -> NDArray[np.float64]:
        """Velocity [unit/s] of dimension ``d`` at ``times (n,)`` [s]: the slope of the
        least-squares line through the unsmoothed samples within :meth:`half_window` samples of
        each time (the central difference on clean data). ``(n,)``.

        Unlike the smoothed velocity it does not round a speed peak off: a line fit over a
        symmetric window of half-width ``w`` is exact for a locally quadratic motion, and at a
        speed extremum (locally cubic, ``x = v₀τ + cτ³``) it reads ``v₀ + (3/5) c w²``, where a
        Gaussian of sigma ``σ`` reads ``v₀ + 3 c σ²``."""
        t, x = self.t, self.x[:, d]
        dt = float(t[1] - t[0])
        out = np.empty(len(times))
        for i, tc in enumerate(np.asarray(times, dtype=float).tolist()):
            half = self.half_window(min(t.shape[0] - 1, max(0, round(tc / dt))), d) * dt
            lo = max(0, int(np.searchsorted(t, tc - half - 1e-6 * dt)))
            hi = min(t.shape[0], int(np.searchsorted(t, tc + half + 1e-6 * dt, side="right")))
            if hi - lo < 2:  # at an end: the two samples nearest to it
                lo, hi = (0, 2) if lo == 0 else (t.shape[0] - 2, t.shape[0])
            tau = t[lo:hi] - t[lo:hi].mean()
            out[i] = float(np.dot(tau, x[lo:hi]) / np.dot(tau, tau))
        return out


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
    shortest, longest = float(steps.min()), float(steps.max())
    if shortest <= 0:
        i = int(np.argmax(steps <= 0))
        raise DemonstrationError(f"t must be strictly increasing (t[{i + 1}] <= t[{i}])")
    if longest - shortest <= UNIFORM_RTOL * shortest:
        return t - t[0], X  # uniform: every step within UNIFORM_RTOL of the median one
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
        x = _gaussian_smooth(X, sigma / dt, reflect=pad)
    else:
        x = X.copy()
    v = _gradient(x, dt)
    a = _gradient(v, dt)
    return SmoothedDemo(t=t, x=x, v=v, a=a, dt=dt)


def _gradient(q: NDArray, dt: float) -> NDArray:
    """``np.gradient(q, dt, axis=0)`` for ``q (T, D)``, ``T ≥ 2``, ``dt`` [s] (the same operations:
    central differences inside, one-sided at the ends), without its argument handling; the
    result has ``q``'s memory layout."""
    out = np.empty_like(q)
    np.subtract(q[2:], q[:-2], out=out[1:-1])
    out[1:-1] /= 2.0 * dt
    np.subtract(q[1], q[0], out=out[0])
    out[0] /= dt
    np.subtract(q[-1], q[-2], out=out[-1])
    out[-1] /= dt
    return out


#: The fit's grid spacing is at most ``sigma / FIT_GRID_PER_SIGMA`` (see :func:`fit_grid`).
FIT_GRID_PER_SIGMA = 4.0


def _interpolate_rows(q: NDArray, low: NDArray, high: NDArray, w_low: NDArray, w: NDArray) -> NDArray:
    """``q[low] w_low + q[high] w`` for ``q (T, D)``, ``low, high = low + 1, w (n,)`` and
    ``w_low = 1 − w`` (the caller's, shared by the arrays it interpolates), worked along memory
    order: the smoothed arrays are usually column-major (``(D, T)`` transposed), where gathering
    rows is several times slower than gathering within each column."""
    if q.strides[0] < q.strides[1]:  # column-major (or a slice of such an array)
        qt = q.T
        out = qt.take(low, axis=1)
        out *= w_low
        out += qt.take(high, axis=1) * w
        return out.T
    return q.take(low, axis=0) * w_low[:, None] + q.take(high, axis=0) * w[:, None]


def fit_grid(demo: SmoothedDemo, sigma: float) -> SmoothedDemo:
    """The smoothed demonstration on the grid the segments are fitted on: ``demo`` itself, or,
    when its samples are more than twice as dense as ``sigma / 4`` [s], a uniform grid of spacing
    at most ``sigma / 4`` over the same span, both ends included.

    After Gaussian smoothing with ``sigma`` nothing varies faster than the kernel: its frequency
    response ``exp(−(2πf sigma)²/2)`` is ``e⁻⁷⁹`` at the Nyquist frequency ``2/sigma`` of a
    ``sigma / 4`` grid, so the coarser grid aliases nothing, and the segmentation works on 4 samples
    per ``sigma`` instead of all of them (a 1 kHz demonstration with ``sigma`` = 20 ms: 5× fewer).
    The grid is not coarser still because the cuts land on it: on LASA a ``sigma / 2`` grid cost
    reproduction accuracy (13 instead of 16 of 30 shapes at or below DMP-50's RMSE). The values
    on the new grid are linear interpolations of the smoothed samples (positions, velocities and
    accelerations alike), whose error ``dt² |x''| / 8`` is far below the smoothing's own bias
    ``sigma² |x''| / 2``.
    """
    T = demo.t.shape[0]
    factor = math.floor(sigma / (FIT_GRID_PER_SIGMA * demo.dt))
    if factor < 2:
        return demo
    n = math.ceil((T - 1) / factor)  # intervals of the new grid
    position = np.arange(n + 1) * ((T - 1) / n)  # fractional sample index of each grid point
    low = np.minimum(position.astype(np.intp), T - 2)
    w = position - low
    # (Interpolated per array: a stacked (T, 3D) copy would be a large allocation, which costs
    # page faults on every fit.)
    high, w_low = low + 1, 1.0 - w
    x, v, a = (_interpolate_rows(q, low, high, w_low, w) for q in (demo.x, demo.v, demo.a))
    spacing = float(demo.t[-1]) / n
    return SmoothedDemo(t=np.arange(n + 1) * spacing, x=x, v=v, a=a, dt=spacing)


def _gaussian_smooth(X: NDArray, sigma_samples: float, reflect: int = 0) -> NDArray:
    """Gaussian smoothing of ``X (T, D)`` along time with ``sigma_samples``; the kernel is truncated
    at 4 sigma. Long kernels are applied by FFT (O(T log T)), short ones directly.

    ``reflect`` samples point-reflected about each end sample extend ``X`` first
    (``2 X[0] − X[reflect:0:-1]`` before it, ``2 X[-1] − X[-2:-reflect-2:-1]`` after it,
    ``reflect < T``); beyond that the samples are taken as equal to the first and last ones. The
    result is that of ``X``'s own samples, ``(T, D)``.

    The FFT path is ``scipy.signal.fftconvolve(..., mode="valid")`` written out (same transforms,
    same result) on a ``(D, n_fft)`` buffer filled in place (extension and zero padding to the
    transform length included: no concatenated copy, which at a few thousand samples also keeps
    the fit's memory from growing), with the kernel's transform from :func:`_kernel_spectrum`."""
    radius = int(4.0 * sigma_samples + 0.5)
    T, D = X.shape
    extended = T + 2 * reflect
    if radius < 16 or extended < 4 * radius:
        if reflect:
            head = 2.0 * X[0] - X[reflect:0:-1]
            tail = 2.0 * X[-1] - X[-2 : -reflect - 2 : -1]
            X = np.concatenate([head, X, tail])
        return gaussian_filter1d(X, sigma_samples, axis=0, mode="nearest")[reflect : reflect + T]
    width = extended + 2 * radius  # the end samples repeated ``radius`` times
    n_fft = sp_fft.next_fast_len(width + 2 * radius, True)  # the full convolution's length
    padded = np.empty((D, n_fft))
    body = padded[:, radius : radius + extended]
    if reflect:
        np.subtract((2.0 * X[0])[:, None], X[reflect:0:-1].T, out=body[:, :reflect])
        np.subtract((2.0 * X[-1])[:, None], X[-2 : -reflect - 2 : -1].T, out=body[:, reflect + T :])
    body[:, reflect : reflect + T] = X.T
    padded[:, :radius] = body[:, :1]
    padded[:, radius + extended : width] = body[:, -1:]
    padded[:, width:] = 0.0
    spectrum = sp_fft.rfft(padded, axis=1)
    del padded, body  # (freed before the inverse transform allocates its result)
    spectrum *= _kernel_spectrum(sigma_samples, radius, n_fft)
    full = sp_fft.irfft(spectrum, n_fft, axis=1)
    return full[:, 2 * radius + reflect : 2 * radius + reflect + T].T


def _kernel_spectrum(sigma_samples: float, radius: int, n_fft: int) -> NDArray[np.complex128]:
    """The real FFT ``(n_fft // 2 + 1,)`` of the normalised Gaussian kernel of ``sigma_samples``
    truncated at ``radius`` samples, zero-padded to ``n_fft``."""
    u = np.arange(-radius, radius + 1, dtype=float)
    kernel = np.exp(-0.5 * (u / sigma_samples) ** 2)
    kernel /= kernel.sum()
    return sp_fft.rfft(kernel, n_fft)


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
    candidates = [*flips.tolist(), x.shape[0] - 1]
    values = x[candidates].tolist()  # the loop runs on Python floats
    pivots: list[int] = []
    trend = 0.0
    x_origin = float(x[0])
    extreme, x_extreme = 0, x_origin
    for i, xi in zip(candidates, values, strict=True):
        if trend == 0.0:
            if abs(xi - x_origin) >= tolerance:
                trend = math.copysign(1.0, xi - x_origin)
                extreme, x_extreme = i, xi
            continue
        if (xi - x_extreme) * trend > 0.0:
            extreme, x_extreme = i, xi
        elif (x_extreme - xi) * trend >= tolerance:
            pivots.append(extreme)
            trend = -trend
            extreme, x_extreme = i, xi
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


#: A direction reversal must exceed this many times the noise level of its dimension
#: (:func:`noise_level`) to become a cut.
REVERSAL_NOISE_FACTOR = 8.0
#: A velocity extremum is a via-point when the velocity swings back from it by at least this
#: fraction of the demonstration's top speed (:func:`velocity_extremum_points`). The tremor of the
#: committed arm recordings swings their 20 ms-smoothed velocities by up to about 15 % of their
#: top speeds; from 15–20 % on, the extrema found are those of the guided motion.
VELOCITY_EXTREMUM_PROMINENCE = 0.2


def velocity_extremum_points(v: NDArray, tolerance: float) -> list[int]:
    """Indices of the significant interior extrema of the velocity ``v (T,)`` [unit/s] of one
    dimension: the speed peak of each stroke and the dips between strokes.

    :func:`turning_points` on the velocity with the hysteresis ``tolerance`` [unit/s]: an
    extremum counts once the velocity has come back from it by ``tolerance``, so the wiggles that
    noise or tremor leave on a smoothed velocity are not extrema; the first and the last sample
    never are. ``[]`` when ``tolerance`` is not a positive number."""
    if not tolerance > 0.0:
        return []
    return turning_points(v, tolerance)


def noise_level(x: NDArray) -> NDArray:
    """Robust estimate of the white-noise standard deviation [unit] of each column of ``x (T, D)``
    from its second differences, ``(D,)``: for white noise of deviation ``s`` they have deviation
    ``√6 s``; a smooth motion contributes only ``x'' dt²``, and the median absolute deviation
    ignores the few large values at sharp turns. On a smoothed demonstration it is the noise the
    smoothing left (≈ 0 for clean data)."""
    if x.shape[0] < 3:
        return np.zeros(x.shape[1])
    q = x.T  # (D, T): along memory order for the usual column-major x
    d2 = q[:, 2:] - 2.0 * q[:, 1:-1] + q[:, :-2]
    if not np.isfinite(d2).all():  # NaN propagates through np.median, not through _row_medians
        mad = np.median(np.abs(d2 - np.median(d2, axis=1)[:, None]), axis=1)
    else:
        mad = _row_medians(np.abs(d2 - _row_medians(d2)[:, None]))
    return mad / (0.6745 * math.sqrt(6.0))


def _row_medians(q: NDArray) -> NDArray:
    """``np.median(q, axis=1)`` of a finite ``q (D, n)``, ``n ≥ 1``, ``(D,)``: the same partition
    and the same mean of the middle two (``(a + b) / 2``), without np.median's generic handling
    (NaN checks, axis bookkeeping), which is most of its cost at a few thousand numbers."""
    n = q.shape[1]
    half = n // 2
    if n % 2:
        return np.partition(q, half, axis=1)[:, half].copy()
    part = np.partition(q, [half - 1, half], axis=1)
    return (part[:, half - 1] + part[:, half]) / 2.0


class _PrefixSums:
    """Prefix sums of the samples of ``D`` dimensions, for O(1) least squares over any index range.

    ``rows (5, D·(T+1))``: column ``d·(T+1) + i`` holds the sums over samples ``0..i−1`` of
    dimension ``d`` of ``x, x², a, a², x·a`` (``x (T, D)`` [unit], ``a (T, D)`` [unit/s²]), so the
    sums over samples ``i..j`` are ``rows[:, b + j + 1] − rows[:, b + i]`` with ``b = d·(T+1)``
    (:attr:`stride`).
    """

    def __init__(self, x: NDArray, a: NDArray) -> None:
        T, D = x.shape
        self.stride = T + 1
        self.rows = np.empty((5, D * (T + 1)))
        sums = self.rows.reshape(5, D, T + 1)
        sums[:, :, 0] = 0.0  # the sum over no sample, before each dimension
        # The five terms of every dimension, (5, D, T), written in place and summed there in one
        # accumulation along time (sequential, as np.cumsum of each term alone; no temporary).
        terms = sums[:, :, 1:]
        x_t, a_t = x.T, a.T
        terms[0] = x_t
        np.multiply(x_t, x_t, out=terms[1])
        terms[2] = a_t
        np.multiply(a_t, a_t, out=terms[3])
        np.multiply(x_t, a_t, out=terms[4])
        np.add.accumulate(terms, axis=2, out=terms)

    def line(
        self, d: int, i: int, j: int, x_c: float, v_c: float, x_n: float, v_n: float, k_cap: float
    ) -> tuple[float, float]:
        """Scalar :meth:`fit` of one range of dimension ``d``: ``(k, sse)`` with ``k`` clamped to
        ``k_cap`` [1/s²]; ``(−inf, inf)`` when the range has no slope (``Δ = 0`` or no spread)."""
        n = j - i + 1
        delta = x_n - x_c
        if delta == 0.0:
            return -math.inf, math.inf
        c0 = (v_n * v_n - v_c * v_c) / (2.0 * delta)
        m = 0.5 * (x_c + x_n)
        base = d * self.stride
        sx, sxx, sa, saa, sxa = (self.rows[:, base + j + 1] - self.rows[:, base + i]).tolist()
        num = sxa - m * sa - c0 * sx + n * c0 * m
        den = sxx - 2.0 * m * sx + n * m * m
        if den <= 0.0:
            return -math.inf, math.inf
        k = min(num / den, k_cap)
        sse = saa - 2.0 * c0 * sa + n * c0 * c0 - 2.0 * k * num + k * k * den
        return k, max(sse, 0.0)

    def fit(
        self, i: NDArray, j: NDArray, steps: NDArray, start: NDArray, end: NDArray, kappa: NDArray
    ) -> tuple[NDArray, NDArray]:
        """Least-squares ``k`` and residual sum of squares of ``a ≈ c₀ + k (x − m)`` over ranges of
        samples, with ``c₀, m`` from the end states and ``k`` clamped to ``ρ k_max − kappa``.

        ``i, j (n,)``: the columns of :attr:`rows` before the first and at the last sample of each
        range (``d·(T+1) + first`` and ``d·(T+1) + last + 1``); ``steps (n,)`` = last − first;
        ``start, end (3, n)``: ``x`` [unit], ``v²`` [unit²/s²], ``|v|`` [unit/s] at the first and
        last sample; ``kappa (n,)`` [1/s²] the stability margin of a range that moves (a range
        with ``Δ = 0`` gets 0, and ``−kappa`` replaces a ``k`` left non-finite by the clamp).
        Returns ``(k, sse)`` ``(n,)`` [1/s², unit²/s⁴]. Numpy's per-call cost dominates at the
        sizes of a split search, so the arithmetic is written with as few calls as possible (the
        same operations, in the same order, as :meth:`line`)."""
        # (Updated in place where a temporary is not needed again: fewer allocations.)
        rows = self.rows.take(j, axis=1)
        sx, sxx, sa, saa, sxa = np.subtract(rows, self.rows.take(i, axis=1), out=rows)
        x_c, vv_c, speed_c = start
        x_n, vv_n, speed_n = end
        n = steps + 1.0
        delta = x_n - x_c
        moving = delta != 0.0
        kappa = kappa * moving
        safe = np.logical_not(moving, out=moving).astype(float)
        safe += delta  # Δ, or 1 where Δ = 0
        c0 = vv_n - vv_c
        c0 /= 2.0 * safe  # (v_n² − v_c²) / (2Δ)
        m = x_c + x_n
        m *= 0.5
        n_c0 = n * c0
        num = sxa - m * sa
        num -= c0 * sx
        num += n_c0 * m  # sxa − m sa − c0 sx + n c0 m
        den = sxx - 2.0 * m * sx
        den += n * m * m  # sxx − 2 m sx + n m m
        k = num / np.where(den > 0.0, den, 1.0)
        k_cap = speed_c + speed_n
        k_cap /= safe
        k_cap *= k_cap
        k_cap *= K_MAX_FRACTION
        k_cap -= kappa  # ρ ((|v_c| + |v_n|)/Δ)² − kappa
        np.minimum(k, k_cap, out=k)
        k = np.where(np.isfinite(k), k, -kappa)
        sse = saa - 2.0 * c0 * sa
        sse += n_c0 * c0
        sse -= 2.0 * k * num
        sse += k * k * den  # saa − 2 c0 sa + n c0 c0 − 2 k num + k k den
        return k, np.maximum(sse, 0.0, out=sse)


class _Samples:
    """The smoothed samples of all ``D`` dimensions, laid out for vectorised work across them.

    ``t (T,)`` [s], ``dt`` [s]; ``x (D·T,)`` positions [unit] and ``v_knot (D·T,)`` via-point
    velocities [unit/s] of dimension ``d`` at ``[d·T, (d+1)·T)``, ``t_all (D·T,)`` [s] their
    times; ``sums`` their prefix sums.
    For the split search (while ``v_knot`` does not change): ``states (3, D·T)`` the rows ``x``,
    ``v_knot²``, ``|v_knot|``, and ``kappa_of_steps (T,)`` [1/s²] the stability margin
    ``(2μ/T_seg)²`` of a segment ``n`` samples long (:func:`psm.pstf.k_limit`).
    """

    def __init__(
        self, t: NDArray, x: NDArray, v_knot: NDArray, a: NDArray, dt: float, min_speed_ratio: float
    ) -> None:
        self.t, self.dt, self.T = t, dt, t.shape[0]
        self.states = np.empty((3, x.size))
        self.x = self.states[0]
        self.x[:] = x.T.reshape(-1)
        self.v_knot = np.ascontiguousarray(v_knot.T).reshape(-1)
        np.multiply(self.v_knot, self.v_knot, out=self.states[1])
        np.abs(self.v_knot, out=self.states[2])
        self.kappa_of_steps = (2.0 * min_speed_ratio / np.maximum(np.arange(self.T) * dt, 1e-12)) ** 2
        self.t_all = np.tile(t, x.shape[1])  # (D·T,): the time of every element of x
        self.sums = _PrefixSums(x, a)

    def set_velocities(self, d: int, samples: Sequence[int], velocities: NDArray) -> None:
        """Set the via-point velocities ``(n,)`` [unit/s] of dimension ``d`` at ``samples (n,)``,
        in ``v_knot`` and in the split search's ``states``."""
        flat = [d * self.T + i for i in samples]
        self.v_knot[flat] = velocities
        self.states[1, flat] = self.v_knot[flat] ** 2
        self.states[2, flat] = np.abs(self.v_knot[flat])


class _Segmenter:
    """Fits one segment of one dimension ``d`` between two sample indices (inclusive).

    ``x (T,)`` smoothed positions, ``v_knot (T,)`` velocities to use when a sample is a via-point
    (zero at reversals and at the end): views of the shared :class:`_Samples`.
    """

    def __init__(self, samples: _Samples, d: int, min_speed_ratio: float, k_fit: str) -> None:
        T = samples.T
        self.samples, self.d, self.offset = samples, d, d * T
        self.t, self.dt, self.sums = samples.t, samples.dt, samples.sums
        self.x = samples.x[d * T : (d + 1) * T]
        self.v_knot = samples.v_knot[d * T : (d + 1) * T]
        self.min_speed_ratio, self.k_fit = min_speed_ratio, k_fit
        # By (lo, hi): valid while v_knot[lo] and v_knot[hi] stay as they were (:meth:`set_velocities`
        # drops the entries a velocity change affects).
        self._slopes: dict[tuple[int, int], float] = {}
        self._lines: dict[tuple[int, int], tuple[float, ...]] = {}

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
        k = self._slopes.get((lo, hi))
        if k is None:
            k = self._slopes[(lo, hi)] = self._slope(lo, hi)
        return k

    def set_velocities(self, cuts: NDArray, velocities: NDArray) -> None:
        """Set ``v_knot`` at the samples ``cuts (n,)`` to ``velocities (n,)`` [unit/s] and forget
        the lines and slopes of the segments between consecutive cuts that this changes."""
        changed = (self.v_knot[cuts] != velocities).tolist()
        self.v_knot[cuts] = velocities
        bounds = cuts.tolist()
        for s in range(len(bounds) - 1):
            if changed[s] or changed[s + 1]:
                self._lines.pop((bounds[s], bounds[s + 1]), None)
                self._slopes.pop((bounds[s], bounds[s + 1]), None)

    def forget(self, samples: Sequence[int]) -> None:
        """Forget the lines and slopes of every segment that starts or ends at one of ``samples``
        (their ``v_knot`` changed)."""
        gone = set(samples)
        for cache in (self._lines, self._slopes):
            for key in [k for k in cache if k[0] in gone or k[1] in gone]:
                del cache[key]

    def _line(self, lo: int, hi: int) -> tuple[float, float, float, float, float, float, float]:
        """``(x_c, v_c, x_n, v_n, k_cap, k_ls, sse)`` of the segment: its :meth:`boundary`, the
        stability cap of its slope [1/s²] and the clamped least-squares line fit
        (:meth:`_PrefixSums.line`). The split search asks :meth:`within_budget` first and
        :meth:`slope` after; the line is computed once for both."""
        line = self._lines.get((lo, hi))
        if line is None:
            x_c, v_c, x_n, v_n = self.boundary(lo, hi)
            k_cap = k_limit(v_c, v_n, x_n - x_c, self.kappa(lo, hi))
            k_ls, sse = self.sums.line(self.d, lo, hi, x_c, v_c, x_n, v_n, k_cap)
            line = self._lines[(lo, hi)] = (x_c, v_c, x_n, v_n, k_cap, k_ls, sse)
        return line

    def _slope(self, lo: int, hi: int) -> float:
        x_c, v_c, x_n, v_n, k_cap, k_ls, _ = self._line(lo, hi)
        if self.k_fit == "duration":
            # The least-squares slope is usually close: it seeds the root-finding.
            return k_for_duration(x_c, v_c, x_n, v_n, (hi - lo) * self.dt, k_cap, k_guess=k_ls)
        return k_ls

    def within_budget(self, lo: int, hi: int, tolerance: float) -> bool:
        """The cheap O(1) acceptance test: an RMS acceleration residual ``e`` of the best line over
        a segment of duration ``T`` bends the path by about ``e T²/8``, so ``2 e T²/8 ≤ tolerance``
        [unit] (a factor 2 of safety) accepts it without computing the PSTF. Noise inflates ``e``,
        so the shortcut never accepts a noisy segment the exact test would reject."""
        sse = self._line(lo, hi)[6]
        duration = (hi - lo) * self.dt
        return 2.0 * math.sqrt(sse / (hi - lo + 1)) * duration * duration / 8.0 <= tolerance

    def split_candidates(self, lo: int, hi: int, min_samples: int, min_delta: float) -> NDArray:
        """Sample indices where ``lo..hi`` may be cut: each half has at least ``min_samples``
        samples and moves at least ``min_delta`` [unit]; at most ~128, evenly spaced. ``(n,)``."""
        first, last = lo + min_samples, hi - min_samples
        if last < first:
            return np.empty(0, dtype=np.intp)
        x_in = self.x[first : last + 1]
        # min(|x − x_lo|, |x_hi − x|) ≥ min_delta: both halves move enough (NaN fails either way).
        gap = np.abs(x_in - self.x[lo])
        np.minimum(gap, np.abs(self.x[hi] - x_in), out=gap)
        cand = np.flatnonzero(gap >= min_delta)
        cand += first
        if cand.size > 128:  # at most ~128 evenly spaced candidates
            cand = cand[:: math.ceil(cand.size / 128)]
        return cand


def _deviations(segments: Sequence[tuple[_Segmenter, int, int]]) -> list[float]:
    """Largest |PSTF − demonstration| [unit] over each segment's samples, the PSTF started at the
    segment's first via-point at its time (timing drift inside the segment counts).

    ``segments``: ``(segmenter, lo, hi)`` of any dimensions of one :class:`_Samples`. The ``k``,
    ``c`` and arrival time of each segment are scalar; the PSTF at its samples (at most ~32 evenly
    spaced ones, the deviation being smooth at the sample scale) is one vectorised evaluation of
    :func:`psm.pstf.positions_from_acceleration` over all segments at once.
    """
    if not segments:
        return []
    samples = segments[0][0].samples
    t = samples.t
    # Per segment, as floats (integers are exact): base, step (sample ``base + step·j`` of
    # samples.x is the batch's element j), x_c, v_c, k, a_c, t_lo, t_end, x_n.
    params = []
    counts = []
    starts = []  # position of each segment's first sample in the batch
    total = 0
    for seg, lo, hi in segments:
        x_c, v_c, x_n, v_n = seg._line(lo, hi)[:4]  # the boundary, as the budget check found it
        k = seg.slope(lo, hi)
        c = coefficient_c(x_c, v_c, x_n, v_n, k)
        t_end = time_to_reach(x_c, v_c, x_n, v_n, k)
        step = max(1, (hi - lo) // 32)
        count = (hi - lo) // step + 1
        base = lo + seg.offset - step * total
        params.append((base, step, x_c, v_c, k, k * x_c + c, float(t[lo]), t_end, x_n))
        counts.append(count)
        starts.append(total)
        total += count
    base, step, x_c, v_c, k, a_c, t_lo, t_end, x_n = np.repeat(np.array(params), counts, axis=0).T
    i = (base + step * np.arange(total)).astype(np.intp)  # the samples evaluated in samples.x
    elapsed = samples.t_all.take(i) - t_lo
    # Past its arrival the PSTF would continue; the chain moves on to the next segment.
    x_model = np.where(elapsed <= t_end, positions_from_acceleration(elapsed, x_c, v_c, k, a_c), x_n)
    error = np.subtract(x_model, samples.x.take(i), out=x_model)
    np.abs(error, out=error)
    # fmax skips NaN samples (a degenerate least-squares k) as max(worst, nan) does; all NaN -> 0.
    worst = np.fmax.reduceat(error, starts).tolist()
    return [w if w == w else 0.0 for w in worst]


def _errors(segments: Sequence[tuple[_Segmenter, int, int]], tolerance: float) -> list[float]:
    """Each segment's :func:`_deviations` [unit], skipped (0) when
    :meth:`_Segmenter.within_budget` already accepts it; the deviations needed are one batch."""
    out = [0.0] * len(segments)
    todo = [s for s, (seg, lo, hi) in enumerate(segments) if not seg.within_budget(lo, hi, tolerance)]
    for s, dev in zip(todo, _deviations([segments[s] for s in todo]), strict=True):
        out[s] = dev
    return out


def _split_points(splits: Sequence[tuple[_Segmenter, int, int, NDArray]]) -> list[int]:
    """For each ``(segmenter, lo, hi, cand)``, the candidate cut ``c`` in ``cand (n,)`` that
    minimises the residual sums of squares of the acceleration line fits of ``lo..c`` plus
    ``c..hi`` (the first one on ties). All candidates of all segments are one vectorised fit."""
    samples = splits[0][0].samples
    stride = samples.sums.stride
    sizes = [cand.size for *_, cand in splits]
    # Per candidate: the segment's ends and the offsets of its dimension in samples.x / sums.rows.
    lo, hi, offset, base = np.repeat(
        np.array([(lo, hi, seg.offset, seg.d * stride) for seg, lo, hi, _ in splits]).T, sizes, axis=1
    )
    cand = np.concatenate([cand for *_, cand in splits])
    first = np.concatenate([lo, cand])  # the two halves lo..c and c..hi of every candidate c
    last = np.concatenate([cand, hi])
    offset = np.concatenate([offset, offset])
    base = np.concatenate([base, base])
    steps = last - first
    _, sse = samples.sums.fit(
        first + base,
        last + base + 1,
        steps,
        samples.states.take(first + offset, axis=1),
        samples.states.take(last + offset, axis=1),
        samples.kappa_of_steps.take(steps),
    )
    n_c = cand.size
    total = sse[:n_c] + sse[n_c:]
    out = []
    start = 0
    for size in sizes:
        out.append(int(cand[start + int(total[start : start + size].argmin())]))
        start += size
    return out


class _Greedy:
    """The greedy top-down splitting of one dimension, replayed on a tree of known splits.

    Whether and where a segment ``(lo, hi)`` is split depends on that segment alone, so the splits
    can be computed ahead of the greedy order (:attr:`split`, :attr:`node_error`) and the greedy
    choice (the worst segment first, the earliest on ties) replayed on them: :meth:`advance`.
    """

    def __init__(self, cuts: list[int], tolerance: float, max_segments: int) -> None:
        self.cuts, self.tolerance, self.max_segments = cuts, tolerance, max_segments
        self.error: dict[int, float] = {}  # by the first sample of each current segment
        self.blocked: set[int] = set()
        #: Split sample of every segment examined, ``None`` when it cannot be split.
        self.split: dict[tuple[int, int], int | None] = {}
        self.node_error: dict[tuple[int, int], float] = {}

    def advance(self) -> list[tuple[int, int]]:
        """Split greedily as far as the known splits allow. Returns ``[]`` when done, otherwise the
        segments to examine next: the one the greedy order needs now, then the others it may split
        later (the worst first, at most as many as splits remain)."""
        cuts, error = self.cuts, self.error
        while len(cuts) - 1 < self.max_segments:
            worst, worst_err = -1, self.tolerance
            for idx, lo in enumerate(cuts[:-1]):
                if lo not in self.blocked and error[lo] > worst_err:
                    worst, worst_err = idx, error[lo]
            if worst < 0:
                return []
            lo, hi = cuts[worst], cuts[worst + 1]
            if (lo, hi) not in self.split:
                open_ = [
                    (-error[a], a, b)
                    for a, b in itertools.pairwise(cuts)
                    if a not in self.blocked and error[a] > self.tolerance and (a, b) not in self.split
                ]
                open_.sort()
                return [(a, b) for _, a, b in open_[: self.max_segments - (len(cuts) - 1)]]
            s = self.split[(lo, hi)]
            if s is None:
                self.blocked.add(lo)
                continue
            cuts.insert(worst + 1, s)
            error[lo] = self.node_error[(lo, s)]
            error[s] = self.node_error[(s, hi)]
        return []


def _auto_cuts(
    cuts: Sequence[list[int]],
    segmenters: Sequence[_Segmenter],
    tolerance: float,
    min_samples: int,
    min_delta: float,
    max_segments: int,
    check: Sequence[set[tuple[int, int]]] | None = None,
) -> list[list[int]]:
    """The ``"auto"`` cuts of several dimensions (``cuts[g]`` of ``segmenters[g]``) at once.

    Per dimension the cuts are those of greedy top-down splitting, the worst segment first, until
    every segment is within ``tolerance`` or ``max_segments`` is reached (:class:`_Greedy`), but
    the numerical work is done level by level of the splitting tree: each round splits every
    segment the greedy order needs or may need next, in all dimensions, as one vectorised split
    search and one vectorised deviation check of all new halves. Splits computed ahead are wasted
    only when ``max_segments`` stops the greedy order first. ``check`` (per dimension, optional):
    the only segments of ``cuts`` whose deviation is checked; the others are taken as within
    ``tolerance``.
    """
    greedy = [_Greedy(sorted(set(c)), tolerance, max_segments) for c in cuts]
    first = [(g, lo, hi) for g, gr in enumerate(greedy) for lo, hi in itertools.pairwise(gr.cuts)]
    if check is not None:  # the other segments are accepted as they are
        for g, lo, _ in first:
            greedy[g].error[lo] = 0.0
        first = [(g, lo, hi) for g, lo, hi in first if (lo, hi) in check[g]]
    errors = _errors([(segmenters[g], lo, hi) for g, lo, hi in first], tolerance)
    for (g, lo, _), err in zip(first, errors, strict=True):
        greedy[g].error[lo] = err
    pending = {g: gr.advance() for g, gr in enumerate(greedy)}
    while any(pending.values()):
        splits = []  # (dimension, lo, hi, candidates)
        for g, segments in pending.items():
            for lo, hi in segments:
                cand = segmenters[g].split_candidates(lo, hi, min_samples, min_delta)
                if cand.size:
                    splits.append((g, lo, hi, cand))
                else:
                    greedy[g].split[(lo, hi)] = None
        halves = []
        if splits:
            points = _split_points([(segmenters[g], lo, hi, cand) for g, lo, hi, cand in splits])
            for (g, lo, hi, _), s in zip(splits, points, strict=True):
                greedy[g].split[(lo, hi)] = s
                halves += [(g, lo, s), (g, s, hi)]
        errors = _errors([(segmenters[g], lo, hi) for g, lo, hi in halves], tolerance)
        for (g, lo, hi), err in zip(halves, errors, strict=True):
            greedy[g].node_error[(lo, hi)] = err
        pending = {g: greedy[g].advance() for g in pending if pending[g]}
    return [gr.cuts for gr in greedy]


def check_via_point_times(times: Sequence[float] | None, duration: float) -> list[float]:
    """``via_point_times`` [s] as a sorted list; raises :class:`ParameterError` naming the field
    unless every time is finite and strictly inside ``(0, duration)`` [s] and none repeats."""
    if times is None:
        return []
    try:
        arr = np.asarray(times, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"via_point_times must be a list of times in s, got {times!r}") from None
    if arr.ndim != 1:
        raise ParameterError(f"via_point_times must be a list of times in s, got shape {arr.shape}")
    bad = ~np.isfinite(arr) | (arr <= 0.0) | (arr >= duration)
    if bad.any():
        raise ParameterError(
            f"via_point_times must lie strictly inside (0, {duration:g}) s (the demonstration), "
            f"got {float(arr[int(np.argmax(bad))]):g} s"
        )
    out = sorted(float(tc) for tc in arr)
    if any(b == a for a, b in itertools.pairwise(out)):
        raise ParameterError("via_point_times has the same time twice")
    return out


def task_via_points(
    cuts: set[int],
    user: Sequence[int],
    extrema: Sequence[int],
    x: NDArray,
    min_samples: int,
    min_delta: float,
) -> list[int]:
    """The via-points of one dimension that keep a demonstrated state, besides ``cuts`` (its ends
    and reversals): the user's samples ``user``, then the velocity extrema ``extrema``.

    A candidate is kept when it moves at least ``min_delta`` [unit] from the via-points already
    kept on both sides of it (a dimension at rest there has no state to keep: the segment would
    have no length); a velocity extremum must also lie at least ``min_samples`` samples from
    them (a user's point is kept however close). ``x (T,)``. Returns the kept samples, sorted."""
    return insert_task_via_points(sorted(cuts), set(), user, extrema, x, min_samples, min_delta)[1]


def insert_task_via_points(
    cuts: Sequence[int],
    movable: set[int],
    user: Sequence[int],
    extrema: Sequence[int],
    x: NDArray,
    min_samples: int,
    min_delta: float,
) -> tuple[list[int], list[int]]:
    """:func:`task_via_points` into a segmentation ``cuts`` of which the samples ``movable`` (the
    ``"auto"`` segmentation's own cuts) give way: a movable cut closer to a candidate than the
    candidate's spacing is replaced by it (a cut moved by less than ``min_samples`` samples).
    Returns ``(cuts, added)``: the new cuts and the kept candidates, both sorted."""
    kept = sorted(cuts)
    movable = set(movable)
    added: list[int] = []
    for group, spacing in ((user, 0), (extrema, min_samples)):
        gap = max(spacing, 1)
        for c in group:
            if c in movable:  # already a cut of the segmentation: it now keeps the state
                movable.discard(c)
                added.append(c)
                continue
            trial = [k for k in kept if not (k in movable and abs(k - c) < gap)]
            i = int(np.searchsorted(trial, c))
            if i == 0 or i == len(trial) or trial[i] == c:
                continue
            lo, hi = trial[i - 1], trial[i]
            if c - lo < gap or hi - c < gap:
                continue
            if abs(x[c] - x[lo]) < min_delta or abs(x[hi] - x[c]) < min_delta:
                continue
            trial.insert(i, c)
            movable.difference_update(set(kept) - set(trial))
            kept = trial
            added.append(c)
    return kept, sorted(added)


def _merge_short(cuts: list[int], fixed: set[int], x: NDArray, min_delta: float) -> list[int]:
    """Drop optional cuts that leave a segment moving less than ``min_delta`` [unit]."""
    out = [cuts[0]]
    for c in cuts[1:-1]:
        if c in fixed or (abs(x[c] - x[out[-1]]) >= min_delta and abs(x[cuts[-1]] - x[c]) >= min_delta):
            out.append(c)
    out.append(cuts[-1])
    return out


def _hold(x: NDArray, duration: float) -> DimensionFit:
    """A dimension that barely moves, ``x (T,)``: one rest-to-rest segment, ``k = −(π/T_demo)²``."""
    knots = np.array([x[0], x[-1]])
    kappa = np.array([(math.pi / duration) ** 2])
    k = -kappa.copy()
    dur = np.array([time_to_reach(x[0], 0.0, x[-1], 0.0, k[0]) if x[-1] != x[0] else 0.0])
    return DimensionFit(
        knots=knots,
        velocities=np.zeros(2),
        k=k,
        kappa=kappa,
        durations=dur,
        cut_indices=np.array([0, x.shape[0] - 1]),
        hold=True,
    )


def _chain(segmenter: _Segmenter, cuts: list[int]) -> DimensionFit:
    """The learned PSTF chain of one dimension through the via-points at samples ``cuts``."""
    x = segmenter.x
    cut_idx = np.asarray(cuts, dtype=np.int64)
    bounds = [segmenter.boundary(lo, hi) for lo, hi in itertools.pairwise(cuts)]
    knots = x[cut_idx].copy()
    # A via-point's velocity must suit both segments it joins (noise can flip a near-zero one).
    vel = np.array([b[1] for b in bounds] + [0.0])
    vel[1:-1] = np.where(vel[1:-1] * np.array([b[3] for b in bounds[:-1]]) > 0.0, vel[1:-1], 0.0)
    kappa = np.array([segmenter.kappa(lo, hi) for lo, hi in itertools.pairwise(cuts)])
    segmenter.set_velocities(cut_idx, vel)  # the split search is over: only slope() reads them now
    k = np.array([segmenter.slope(lo, hi) for lo, hi in itertools.pairwise(cuts)])
    durations = np.array(
        [time_to_reach(knots[s], vel[s], knots[s + 1], vel[s + 1], k[s]) for s in range(k.size)]
    )
    return DimensionFit(
        knots=knots,
        velocities=vel,
        k=k,
        kappa=kappa,
        durations=durations,
        cut_indices=cut_idx,
        hold=False,
    )


def _task_velocities(
    v: NDArray, raw: RawDemo | None, demo_t: NDArray, task: Sequence[int], d: int, user: Sequence[int]
) -> NDArray:
    """The demonstrated velocities ``(n,)`` [unit/s] of the task via-points ``task`` (samples) of
    dimension ``d``: that of ``raw`` (the unsmoothed demonstration; ``None``: the smoothed
    ``v (T, D)`` everywhere) at the user's samples ``user`` and at the velocity extrema at least
    :data:`RAW_VELOCITY_MIN_SPEED` of the top speed fast, the smoothed one at the others."""
    idx = list(task)
    out = v[idx, d].copy()
    if raw is not None and idx:
        users = set(user)
        top = RAW_VELOCITY_MIN_SPEED * raw.speed_scale
        keep = [n for n, i in enumerate(idx) if i in users or abs(v[i, d]) >= top]
        if keep:
            out[keep] = raw.velocity(demo_t[[idx[n] for n in keep]], d)
    return out


def _add_task_via_points(
    cuts: dict[int, list[int]],
    fixed: dict[int, set[int]],
    user: Sequence[int],
    extrema: dict[int, list[int]],
    samples: _Samples,
    segmenters: dict[int, _Segmenter],
    v: NDArray,
    raw: RawDemo | None,
    demo_t: NDArray,
    tolerance: float,
    min_samples: int,
    min_delta: float,
    max_segments: int,
) -> list[list[int]]:
    """The ``"auto"`` segmentation ``cuts`` (by dimension) with the task via-points added.

    The task via-points join the segmentation found without them
    (:func:`insert_task_via_points`: an automatic cut closer than the spacing to one moves onto
    it), so the fit is at least as fine as without them: no segment is merged. The task
    via-points then get their demonstrated velocities (:func:`_task_velocities`), and a segment
    next to one that those velocities push beyond ``tolerance`` is split further as
    :func:`_auto_cuts` does (up to ``max_segments`` plus the most task via-points added to any
    one dimension); the segments away from them keep the fit they had."""
    redo: dict[int, list[int]] = {}
    near: list[set[tuple[int, int]]] = []  # per dimension redone: the segments next to a new one
    added_most = 0
    for d, c in cuts.items():
        new, added = insert_task_via_points(
            c, set(c) - fixed[d], user, extrema[d], segmenters[d].x, min_samples, min_delta
        )
        if not added:
            continue
        samples.set_velocities(d, added, _task_velocities(v, raw, demo_t, added, d, user))
        segmenters[d].forget(added)
        redo[d] = new
        task = set(added)
        near.append({(lo, hi) for lo, hi in itertools.pairwise(new) if lo in task or hi in task})
        added_most = max(added_most, len(added))
    if redo:
        again = _auto_cuts(
            list(redo.values()),
            [segmenters[d] for d in redo],
            tolerance,
            min_samples,
            min_delta,
            max_segments + added_most,
            check=near,
        )
        cuts.update(zip(redo, again, strict=True))
    return list(cuts.values())


def fit_dimensions(
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
    k_fit: str,
    *,
    raw: RawDemo | None = None,
    extremum_tolerance: float | None = None,
    via_point_times: Sequence[float] = (),
) -> list[DimensionFit]:
    """Learn the PSTF chain of every dimension from smoothed samples ``x, v, a (T, D)``.

    The dimensions are independent: each result equals fitting that dimension alone (a ``(T, 1)``
    call); learning them together lets ``"auto"`` batch its numerical work across dimensions.
    ``segments``: ``"auto"``, a number of segments uniform in time (the paper's choice; direction
    reversals are added as cuts), or a sequence of cut times [s] from the demonstration's start.
    A dimension whose range is below ``hold_tolerance`` [unit] becomes one rest-to-rest hold.
    ``k_fit``: one of :data:`K_FIT_MODES`.
    Task via-points (:func:`task_via_points`), kept whatever ``segments`` says, with their
    demonstrated velocities (:func:`_task_velocities`; ``raw`` ``None``: the smoothed ``v``): the
    velocity extrema of every moving dimension with the hysteresis ``extremum_tolerance``
    [unit/s], at least 8 times the noise left in the velocity (:func:`velocity_extremum_points`;
    ``None``: none), and the samples nearest to ``via_point_times`` [s] (checked by
    :func:`check_via_point_times`). With ``"auto"`` they join the segmentation found without
    them (:func:`_add_task_via_points`); otherwise they are fixed cuts beside ``segments``.
    """
    T, D = x.shape
    duration = float(demo_t[-1])
    holds = [bool(float(np.ptp(x[:, d])) < hold_tolerance) for d in range(D)]
    # Motions start and end at rest (a robot starts a skill standing still; a demonstration's
    # first and last velocities are sensor noise around zero), and reverse at rest.
    v_knot = v.copy()
    v_knot[0] = 0.0
    v_knot[-1] = 0.0
    fixed: dict[int, set[int]] = {}
    # A reversal smaller than the noise left in a dimension is noise (a demonstration learned
    # with little or no smoothing would otherwise get a cut at every wiggle).
    reversal_tolerance = np.maximum(hold_tolerance, REVERSAL_NOISE_FACTOR * noise_level(x))
    user = sorted({min(T - 1, max(0, round(tc / dt))) for tc in via_point_times})
    # A velocity swing smaller than the noise left in the velocity is noise, as for reversals.
    extremum_tol = (
        np.maximum(extremum_tolerance, REVERSAL_NOISE_FACTOR * noise_level(v))
        if extremum_tolerance
        else np.zeros(D)
    )
    auto = isinstance(segments, str)
    if auto and segments != "auto":
        raise ParameterError(f"segments must be 'auto', an int or cut times, got {segments!r}")
    candidates: dict[int, list[int]] = {}  # the velocity extrema of each dimension
    for d in range(D):
        if not holds[d]:
            turns = turning_points(x[:, d], float(reversal_tolerance[d]))
            fixed[d] = {0, T - 1, *turns}
            v_knot[turns, d] = 0.0
            candidates[d] = velocity_extremum_points(v[:, d], float(extremum_tol[d]))
            if not auto:  # "auto" adds them to its own segmentation, below
                task = task_via_points(
                    fixed[d], user, candidates[d], x[:, d], min_segment_samples, hold_tolerance
                )
                fixed[d].update(task)
                v_knot[task, d] = _task_velocities(v, raw, demo_t, task, d, user)
    if not fixed:  # nothing moves (segments is not even looked at, as for one hold dimension)
        return [_hold(x[:, d], duration) for d in range(D)]
    samples = _Samples(demo_t, x, v_knot, a, dt, min_speed_ratio)
    segmenters = {d: _Segmenter(samples, d, min_speed_ratio, k_fit) for d in fixed}
    if auto:
        cuts = [_merge_short(sorted(fixed[d]), fixed[d], x[:, d], hold_tolerance) for d in fixed]
        cuts = _auto_cuts(
            cuts,
            list(segmenters.values()),
            auto_tolerance,
            min_segment_samples,
            hold_tolerance,
            max_segments,
        )
        if user or any(candidates.values()):
            cuts = _add_task_via_points(
                dict(zip(fixed, cuts, strict=True)), fixed, user, candidates, samples, segmenters,
                v, raw, demo_t, auto_tolerance, min_segment_samples, hold_tolerance, max_segments,
            )
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
        cuts = [_merge_short(sorted(fixed[d] | extra), fixed[d], x[:, d], hold_tolerance) for d in fixed]
    chains = iter(_chain(segmenters[d], c) for d, c in zip(fixed, cuts, strict=True))
    return [_hold(x[:, d], duration) if holds[d] else next(chains) for d in range(D)]
