"""The phase space transition function (PSTF) of one segment in one dimension.

A PSTF drives a unit point mass with the linear law ``ẍ = k x + c`` from a current phase-space
state ``(x_c, v_c)`` to a target state ``(x_n, v_n)``. Everything here follows ``docs/psm.md``
("The maths, as implemented": the paper's equations 4–12 with their typos corrected):

* energy: ``v²/2 = v_c²/2 + ∫ (k s + c) ds`` from ``x_c`` to ``x``;
* eq. 5 (sign fixed): ``c = (v_n² − v_c²)/(2Δ) − k (x_n + x_c)/2`` with ``Δ = x_n − x_c``;
* written around the segment mid-point ``m = (x_c + x_n)/2``: ``ẍ = c₀ + k (x − m)`` with
  ``c₀ = (v_n² − v_c²)/(2Δ)``, so the acceleration at the two ends is ``c₀ ∓ kΔ/2``;
* stability: the target is reached iff the kinetic energy stays positive inside the interval,
  i.e. iff ``k < k_max = ((|v_c| + |v_n|)/Δ)²`` (and both velocities point along ``Δ`` or are 0).

The functions are written with ``math`` on Python floats because the online controller calls them
every control tick (1–2 ms) and scalar ``math`` is several times faster than numpy on one number.
:func:`propagate` and :func:`kinetic_energy` accept numpy arrays for plots and tests.

Units: positions [m] (or any length unit), velocities [unit/s], accelerations [unit/s²],
``k`` [1/s²], times [s].
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Below this |k|·T₀² the segment is treated as k = 0 (T₀ = 2|Δ|/(|v_c|+|v_n|)); the relative
#: error of the k = 0 time formula there is below 1e-9.
K_ZERO_TOL = 1e-8
#: Fraction of k_max a segment's k may use (see :func:`k_limit`).
K_MAX_FRACTION = 0.97
#: Below this |z| = |k| t² the series expansions of cosh/sinh are used (error < 1e-13).
_Z_SERIES = 1e-5
_TWO_PI = 2.0 * math.pi
#: A k < 0 segment's phase advance above this is rounding around 0 (a monotone segment covers at
#: most half a period; see :func:`time_to_reach`).
_THREE_HALVES_PI = 1.5 * math.pi
_INF = math.inf
_sqrt, _log, _atan2 = math.sqrt, math.log, math.atan2


def mid_point_form(x_c: float, v_c: float, x_n: float, v_n: float) -> tuple[float, float]:
    """Return ``(c₀, m)`` of the law ``ẍ = c₀ + k (x − m)`` for the segment ``x_c → x_n``.

    ``c₀ = (v_n² − v_c²)/(2Δ)`` [unit/s²] is the acceleration at the mid-point ``m`` whatever
    ``k`` is. Requires ``Δ = x_n − x_c ≠ 0``.
    """
    delta = x_n - x_c
    return (v_n * v_n - v_c * v_c) / (2.0 * delta), 0.5 * (x_n + x_c)


def coefficient_c(x_c: float, v_c: float, x_n: float, v_n: float, k: float) -> float:
    """Eq. 5, corrected: the constant ``c`` [unit/s²] for which ``ẍ = k x + c`` reaches ``v_n``
    at ``x_n`` starting from ``(x_c, v_c)``. Requires ``x_n ≠ x_c``."""
    c0, m = mid_point_form(x_c, v_c, x_n, v_n)
    return c0 - k * m


def k_max(v_c: float, v_n: float, delta: float) -> float:
    """Stability bound ``((|v_c| + |v_n|)/Δ)²`` [1/s²]: every ``k`` strictly below it reaches the
    target (when both velocities point along ``Δ`` or are zero); ``+inf`` for ``Δ = 0``."""
    if delta == 0.0:
        return math.inf
    r = (abs(v_c) + abs(v_n)) / delta
    return r * r


def k_limit(v_c: float, v_n: float, delta: float, kappa: float) -> float:
    """The largest ``k`` [1/s²] allowed for a segment: ``ρ k_max − kappa`` (``ρ`` =
    :data:`K_MAX_FRACTION`).

    ``ρ < 1`` keeps a segment away from the unstable equilibrium at ``k_max``: there a state that
    starts at rest escapes exponentially slowly (how the PSM encodes a dimension that waits), so
    its timing would amplify any perturbation by ``e^{√k t}`` without bound; with ``ρ = 0.97`` a
    start from rest reaches the via-point within about ``6 Δ/v_n`` (amplification below ~e⁶).

    ``kappa ≥ 0`` [1/s²] is the second margin. With ``kappa = (2μ/T)²`` the kinetic energy is
    kept above the parabola ``2 (μ Δ/T)² · 4s(1−s)`` (``s`` the fraction of the segment done), so
    the speed at the segment's mid-point never drops below ``μ`` times the mean speed ``Δ/T``: the
    segment cannot stall, and a rest-to-rest segment takes ``π T / (2μ)``. Since the kinetic energy
    of a sub-interval is that of the interval, the bound only grows along an unperturbed segment.
    """
    return K_MAX_FRACTION * k_max(v_c, v_n, delta) - kappa


def is_stable(v_c: float, v_n: float, delta: float, k: float) -> bool:
    """True iff the PSTF from velocity ``v_c`` reaches velocity ``v_n`` after a displacement
    ``delta`` with this ``k``: both velocities along ``delta`` (or zero) and ``k < k_max``."""
    if delta == 0.0:
        return False
    if v_c * delta < 0.0 or v_n * delta < 0.0:
        return False
    return k < k_max(v_c, v_n, delta)


def kinetic_energy(s: ArrayLike, v_c: float, v_n: float, delta: float, k: float) -> NDArray[np.float64]:
    """Kinetic energy per unit mass ``v²/2`` [unit²/s²] at the fraction ``s ∈ [0, 1]`` of the segment:
    ``KE(s) = (1 − s) E_c + s E_n − (k Δ²/2) s (1 − s)``. ``s``: any shape."""
    s = np.asarray(s, dtype=float)
    e_c, e_n = 0.5 * v_c * v_c, 0.5 * v_n * v_n
    return (1.0 - s) * e_c + s * e_n - 0.5 * k * delta * delta * s * (1.0 - s)


def _cs_g(z: NDArray[np.float64], k: float) -> tuple[NDArray, NDArray, NDArray]:
    """Return ``C(z), S(z), G(z)`` with ``C = cosh √z``, ``S = sinh(√z)/√z``, ``G = (C − 1)/z``
    (their analytic continuations cos, sin for ``z < 0``) for ``z = k t²`` (one sign, that of
    ``k``), using series expansions where ``|z|`` is small so the forms stay exact through 0."""
    if k == 0.0:
        return np.ones_like(z), np.ones_like(z), np.full_like(z, 0.5)
    if k > 0.0:
        r = np.sqrt(z)
        c = np.cosh(r)
        s = np.divide(np.sinh(r), r, out=np.ones_like(r), where=r > 0.0)
    else:
        r = np.sqrt(-z)
        c = np.cos(r)
        s = np.divide(np.sin(r), r, out=np.ones_like(r), where=r > 0.0)
    g = np.divide(c - 1.0, z, out=np.full_like(z, 0.5), where=z != 0.0)
    small = np.abs(z) < _Z_SERIES
    if small.any():
        zs = z[small]
        c[small] = 1.0 + zs / 2.0 + zs * zs / 24.0
        s[small] = 1.0 + zs / 6.0 + zs * zs / 120.0
        g[small] = 0.5 + zs / 24.0 + zs * zs / 720.0
    return c, s, g


def propagate(
    t: ArrayLike, x_c: float, v_c: float, k: float, c: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Closed-form solution of ``ẍ = k x + c`` from ``(x_c, v_c)`` at ``t = 0`` (eq. 6, corrected).

    Written as ``x(t) = x_c + v_c t S(kt²) + a_c t² G(kt²)`` with ``a_c = k x_c + c``, which equals
    the exponential (k > 0), trigonometric (k < 0) and parabolic (k = 0) forms of eq. 6 but
    stays exact as ``k → 0`` (no ``c/k``). ``t``: any shape [s]; returns ``(x, v)`` of that shape.
    """
    t = np.asarray(t, dtype=float)
    a_c = k * x_c + c
    c_, s_, g_ = _cs_g(np.atleast_1d(k * t * t), k)
    c_, s_, g_ = (q.reshape(t.shape) for q in (c_, s_, g_))
    x = x_c + v_c * t * s_ + a_c * t * t * g_
    v = v_c * c_ + a_c * t * s_
    return x, v


def positions(
    t: ArrayLike, x_c: ArrayLike, v_c: ArrayLike, k: ArrayLike, c: ArrayLike
) -> NDArray[np.float64]:
    """The position of :func:`propagate`, vectorised over segments and times: element ``i`` is the
    PSTF of segment ``(x_c[i], v_c[i], k[i], c[i])`` at ``t[i]`` [s] (arguments broadcast together;
    ``x_c`` [unit], ``v_c`` [unit/s], ``k`` [1/s²], ``c`` [unit/s²]). Unlike :func:`propagate`,
    ``k`` may differ (and change sign) from element to element.

    The same formula and series as :func:`propagate`, so the two agree to rounding.
    Returns positions [unit] of the broadcast shape; an overflowing element is ``inf``/``nan``
    instead of raising.
    """
    t, x_c, v_c, k, c = np.broadcast_arrays(*(np.asarray(q, dtype=float) for q in (t, x_c, v_c, k, c)))
    return positions_from_acceleration(t, x_c, v_c, k, k * x_c + c)


def positions_from_acceleration(
    t: NDArray[np.float64],
    x_c: NDArray[np.float64],
    v_c: NDArray[np.float64],
    k: NDArray[np.float64],
    a_c: NDArray[np.float64],
) -> NDArray[np.float64]:
    """:func:`positions` given the initial accelerations ``a_c = k x_c + c`` [unit/s²] instead of
    ``c``, for float arrays of one shape (no conversion or broadcasting: the inner loop of the
    fit, where numpy's per-call cost matters). ``t`` [s], ``x_c`` [unit], ``v_c`` [unit/s],
    ``k`` [1/s²]; returns positions [unit] of that shape."""
    z = k * t * t
    abs_z = np.abs(z)
    r = np.sqrt(abs_z)
    grows = z > 0.0
    any_ = np.logical_or.reduce  # ndarray.any() without its Python-level wrapper
    with np.errstate(all="ignore"):
        # z > 0: S = sinh(r)/r, G = (cosh r − 1)/z; z < 0: sin(r)/r, (1 − cos r)/r²; small |z|: series
        # (z = 0 gets the series and NaN stays NaN on either branch, so one branch may serve all).
        if not any_(grows, axis=None):
            s_ = np.sin(r) / r
            g_ = (1.0 - np.cos(r)) / (r * r)
        elif not any_(z < 0.0, axis=None):
            s_ = np.sinh(r) / r
            g_ = (np.cosh(r) - 1.0) / z
        else:
            s_ = np.where(grows, np.sinh(r), np.sin(r)) / r
            g_ = np.where(grows, np.cosh(r) - 1.0, 1.0 - np.cos(r)) / np.where(grows, z, r * r)
    small = abs_z < _Z_SERIES
    s_ = np.where(small, 1.0 + z / 6.0 + z * z / 120.0, s_)
    g_ = np.where(small, 0.5 + z / 24.0 + z * z / 720.0, g_)
    return x_c + v_c * t * s_ + a_c * t * t * g_


def time_to_reach(x_c: float, v_c: float, x_n: float, v_n: float, k: float) -> float:
    """Time [s] the PSTF with slope ``k`` takes from ``(x_c, v_c)`` to ``(x_n, v_n)`` (eqs. 11–12).

    ``c`` follows from eq. 5. Returns a finite positive time for every stable segment and ``inf``
    for an unstable one (``k ≥ k_max``, a velocity pointing away from ``x_n``) or a stalled one
    (``v_c = v_n = 0`` with ``k ≥ 0``); ``0`` when ``x_c = x_n``.

    * ``k > 0``, ``ω = √k``: ``t = ln[(a_n/ω + v_n)/(a_c/ω + v_c)]/ω`` (the paper's log form,
      written with the end accelerations ``a = k x + c`` so that no ``c/k`` appears); the mirror
      form ``−ln[(a_n/ω − v_n)/(a_c/ω − v_c)]/ω`` is used when its denominator is larger.
    * ``k < 0``, ``ω = √−k``: ``θ = atan2(−v ω, −a)`` at both ends, ``t = ((θ_n − θ_c) mod 2π)/ω``.
    * ``k ≈ 0``: ``t = 2Δ/(v_c + v_n)``.
    """
    delta = x_n - x_c
    if delta == 0.0:
        return 0.0
    if not is_stable(v_c, v_n, delta, k):
        return math.inf
    return stable_segment_time(delta, (v_n * v_n - v_c * v_c) / (2.0 * delta), v_c, v_n, k)


def stable_segment_time(delta: float, c0: float, v_c: float, v_n: float, k: float) -> float:
    """:func:`time_to_reach` [s] of a segment already known to be stable, without the checks:
    ``delta = x_n − x_c ≠ 0``, both velocities along it or zero, ``k < k_max``;
    ``c0 = (v_n² − v_c²)/(2Δ)`` [unit/s²] its mid-point acceleration. The reference for the two
    places that write the same closed form out for speed: :func:`k_for_duration`'s root-finder
    (in its closure) and the controller's hot path (:meth:`psm.PSMController.step`, reusing what
    its law computes; ``tests/core/test_model.py`` checks it against :func:`time_to_reach`)."""
    speed_sum = abs(v_c) + abs(v_n)
    t0 = 2.0 * abs(delta) / speed_sum if speed_sum > 0.0 else _INF
    if k == 0.0 or (t0 != _INF and abs(k) * t0 * t0 < K_ZERO_TOL):
        return t0  # k ≈ 0: t = 2Δ/(v_c + v_n)
    a_c = c0 - 0.5 * k * delta
    a_n = c0 + 0.5 * k * delta
    if k > 0.0:
        w = _sqrt(k)
        p_c, q_c = a_c / w + v_c, a_c / w - v_c
        ratio = (a_n / w + v_n) / p_c if abs(p_c) >= abs(q_c) else q_c / (a_n / w - v_n)
        if not ratio > 0.0:
            return _INF
        t = _log(ratio) / w
        return 0.0 if 0.0 > t else t  # max(t, 0)
    w = _sqrt(-k)
    dtheta = (_atan2(-v_n * w, -a_n) - _atan2(-v_c * w, -a_c)) % _TWO_PI
    # A monotone segment covers at most half a period; 2π − ε only arises from rounding near 0.
    return 0.0 if dtheta > _THREE_HALVES_PI else dtheta / w


def k_for_duration(
    x_c: float,
    v_c: float,
    x_n: float,
    v_n: float,
    duration: float,
    k_high: float,
    k_guess: float | None = None,
) -> float:
    """The slope ``k`` [1/s²] whose PSTF goes from ``(x_c, v_c)`` to ``(x_n, v_n)`` in ``duration`` [s].

    The time to reach grows strictly with ``k`` (a larger ``k`` lowers the kinetic energy at every
    interior point) from 0 as ``k → −∞`` to ``∞`` at ``k_max``, so the answer is unique; it is found
    by the Illinois method (modified regula falsi) on ``(−4(π/duration)², k_high]`` (at
    ``−4(π/duration)²`` even a rest-to-rest segment takes only ``duration/2``). Returns ``k_high``
    when even that is faster than asked. Both velocities must point along ``x_n − x_c`` (or be
    0) and ``k_high`` must be below ``k_max``. ``k_guess`` [1/s²], optional, a slope believed
    close to the answer (the fit passes the least-squares one): the bracket is then grown from
    it, which saves most of the iterations; the answer is the same to the tolerance.
    """
    delta = x_n - x_c
    c0 = (v_n * v_n - v_c * v_c) / (2.0 * delta)
    t0 = 2.0 * abs(delta) / (abs(v_c) + abs(v_n)) if v_c or v_n else math.inf

    # excess_time is stable_segment_time(delta, c0, v_c, v_n, k) − duration written out (the same
    # operations in the same order, so the same result): the root-finding evaluates it ~7 times
    # per segment of a fit, and the extra call and re-derived constants cost ~15 % of a solve.
    t0_finite = t0 != math.inf
    t0_excess = t0 - duration
    sqrt, log, atan2 = math.sqrt, math.log, math.atan2

    def excess_time(k: float) -> float:
        if k == 0.0 or (t0_finite and abs(k) * t0 * t0 < K_ZERO_TOL):
            return t0_excess
        a_c = c0 - 0.5 * k * delta
        a_n = c0 + 0.5 * k * delta
        if k > 0.0:
            w = sqrt(k)
            p_c, q_c = a_c / w + v_c, a_c / w - v_c
            ratio = (a_n / w + v_n) / p_c if abs(p_c) >= abs(q_c) else q_c / (a_n / w - v_n)
            if not ratio > 0.0:
                return math.inf
            return max(log(ratio) / w, 0.0) - duration
        w = sqrt(-k)
        dtheta = (atan2(-v_n * w, -a_n) - atan2(-v_c * w, -a_c)) % _TWO_PI
        return (0.0 if dtheta > _THREE_HALVES_PI else dtheta / w) - duration

    tol = 1e-9 * duration
    scale = (math.pi / duration) ** 2
    f_high = math.nan  # not evaluated yet
    k_low, f_low = -math.inf, -math.inf  # no lower bracket end yet
    if k_guess is not None and k_guess < k_high and math.isfinite(k_guess):
        # Secant steps from the guess (usually within a few per cent of the answer), keeping
        # the tightest bracket seen; the Illinois method below finishes from that bracket.
        k_a, f_a = k_guess, excess_time(k_guess)
        k_b = k_guess - math.copysign(0.02 * max(abs(k_guess), scale), f_a)
        for _ in range(6):
            if abs(f_a) <= tol:
                return k_a
            # k_a lies strictly inside the bracket (k_guess < k_high, and every later k_a passed
            # the test below), so it is always the tighter end.
            if f_a > 0.0:
                k_high, f_high = k_a, f_a
            else:
                k_low, f_low = k_a, f_a
            if not k_low < k_b < k_high:
                break
            f_b = excess_time(k_b)
            k_next = k_b - f_b * (k_b - k_a) / (f_b - f_a) if f_b != f_a else k_b
            k_a, f_a, k_b = k_b, f_b, k_next
    if math.isnan(f_high):
        f_high = excess_time(k_high)
        if f_high <= 0.0:
            return k_high  # even the steepest allowed slope is faster than asked
    if k_low == -math.inf:
        k_low = min(-4.0 * scale, k_high - 1.0)
        f_low = excess_time(k_low)
        while f_low >= 0.0:
            k_low *= 4.0
            f_low = excess_time(k_low)
    # Illinois (modified regula falsi) on the bracket: superlinear, never leaves the bracket.
    # f_high may be +inf (k_high at the bound): bisect until it is finite.
    side = 0
    for _ in range(200):
        if math.isinf(f_high):
            k = 0.5 * (k_low + k_high)
        else:
            k = (k_low * f_high - k_high * f_low) / (f_high - f_low)
        f = excess_time(k)
        if abs(f) <= tol or k_high - k_low <= 1e-12 * max(1.0, abs(k)):
            return k
        if f > 0.0:
            k_high, f_high = k, f
            if side == 1:
                f_low *= 0.5
            side = 1
        else:
            k_low, f_low = k, f
            if side == -1 and not math.isinf(f_high):
                f_high *= 0.5
            side = -1
    return k
