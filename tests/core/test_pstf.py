"""The PSTF closed forms against the corrected equations of docs/psm.md and against numerical
integration."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from psm import pstf

finite = dict(allow_nan=False, allow_infinity=False)


@st.composite
def segments(draw: st.DrawFn) -> tuple[float, float, float, float, float]:
    """A random stable segment (x_c, v_c, x_n, v_n, k) with k below k_max by a margin."""
    x_c = draw(st.floats(-2.0, 2.0, **finite))
    delta = draw(st.floats(0.01, 2.0, **finite)) * draw(st.sampled_from([-1.0, 1.0]))
    speed_c = draw(st.floats(0.0, 3.0, **finite))
    speed_n = draw(st.floats(0.0, 3.0, **finite))
    if speed_c + speed_n < 1e-3:
        speed_n = 0.0
        speed_c = 0.0
    sign = math.copysign(1.0, delta)
    kmax = pstf.k_max(speed_c, speed_n, delta)
    scale = max(kmax, 1.0)
    # fraction of k_max (positive k) or a negative k down to -20 k_max
    frac = draw(st.floats(-20.0, 0.98, **finite))
    k = frac * scale if frac < 0 else frac * kmax
    if speed_c + speed_n == 0.0:
        k = -abs(frac) * scale - 0.5  # rest-to-rest needs k < 0
    return x_c, sign * speed_c, x_c + delta, sign * speed_n, k


@settings(max_examples=300, deadline=None)
@given(segments())
def test_closed_form_reaches_target_and_progresses_monotonically(seg: tuple) -> None:
    x_c, v_c, x_n, v_n, k = seg
    T = pstf.time_to_reach(x_c, v_c, x_n, v_n, k)
    assert math.isfinite(T) and T > 0.0
    c = pstf.coefficient_c(x_c, v_c, x_n, v_n, k)
    x_T, v_T = pstf.propagate(T, x_c, v_c, k, c)
    scale = abs(x_n - x_c)
    assert abs(float(x_T) - x_n) <= 1e-6 * max(scale, 1.0)
    assert abs(float(v_T) - v_n) <= 1e-5 * max(abs(v_c) + abs(v_n), 1.0)
    t = np.linspace(0.0, T, 400)
    x, v = pstf.propagate(t, x_c, v_c, k, c)
    direction = math.copysign(1.0, x_n - x_c)
    assert np.all(np.diff(x) * direction >= -1e-9 * max(scale, 1.0))
    assert np.all(v * direction >= -1e-6 * max(abs(v_c) + abs(v_n), 1.0))


@settings(max_examples=60, deadline=None)
@given(segments())
def test_time_to_reach_matches_numerical_integration(seg: tuple) -> None:
    x_c, v_c, x_n, v_n, k = seg
    c = pstf.coefficient_c(x_c, v_c, x_n, v_n, k)
    T = pstf.time_to_reach(x_c, v_c, x_n, v_n, k)

    sol = solve_ivp(
        lambda _t, y: [y[1], k * y[0] + c], (0.0, T), [x_c, v_c], t_eval=[0.98 * T, T],
        rtol=1e-11, atol=1e-13, max_step=T / 50.0,
    )
    scale = max(abs(x_n - x_c), 1.0)
    # At the closed-form time the integrated state is the target ...
    assert float(sol.y[0][-1]) == pytest.approx(x_n, abs=1e-6 * scale)
    assert float(sol.y[1][-1]) == pytest.approx(v_n, abs=1e-4 * max(1.0, abs(v_c)))
    # ... and shortly before it the target was not yet reached (so T is the first arrival).
    assert (x_n - float(sol.y[0][0])) * math.copysign(1.0, x_n - x_c) > 0.0


@settings(max_examples=100, deadline=None)
@given(
    st.floats(0.1, 2.0, **finite),
    st.floats(0.0, 2.0, **finite),
    st.floats(0.05, 2.0, **finite),
    st.floats(1.02, 5.0, **finite),
)
def test_above_k_max_the_target_is_not_reached(delta: float, v_c: float, v_n: float, f: float) -> None:
    x_c, x_n = 0.0, delta
    k = f * pstf.k_max(v_c, v_n, delta)
    assert pstf.time_to_reach(x_c, v_c, x_n, v_n, k) == math.inf
    assert not pstf.is_stable(v_c, v_n, delta, k)
    # The kinetic energy goes negative inside the interval: the motion turns back before x_n.
    s = np.linspace(0.0, 1.0, 2001)
    assert np.min(pstf.kinetic_energy(s, v_c, v_n, delta, k)) < 0.0
    c = pstf.coefficient_c(x_c, v_c, x_n, v_n, k)
    horizon = 6.0 * delta / (v_c + v_n)  # three times the k = 0 crossing time
    sol = solve_ivp(
        lambda _t, y: [y[1], k * y[0] + c], (0.0, horizon), [x_c, v_c], rtol=1e-10, atol=1e-12,
        max_step=horizon / 500.0,
    )
    assert np.max(sol.y[0]) < x_n


def test_closed_forms_of_eq_6() -> None:
    """propagate equals the exponential, trigonometric and parabolic forms of eq. 6 (docs/psm.md)."""
    t = np.linspace(0.0, 1.3, 50)
    x_c, v_c, c = 0.3, -0.7, 1.9
    k = 2.5
    w = math.sqrt(k)
    A = (x_c + v_c / w + c / k) / 2
    B = (x_c - v_c / w + c / k) / 2
    np.testing.assert_allclose(
        pstf.propagate(t, x_c, v_c, k, c)[0], A * np.exp(w * t) + B * np.exp(-w * t) - c / k,
        rtol=1e-12, atol=1e-12,
    )
    k = -3.1
    w = math.sqrt(-k)
    expected = (x_c + c / k) * np.cos(w * t) + (v_c / w) * np.sin(w * t) - c / k
    np.testing.assert_allclose(pstf.propagate(t, x_c, v_c, k, c)[0], expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        pstf.propagate(t, x_c, v_c, 0.0, c)[0], x_c + v_c * t + c * t * t / 2, rtol=1e-14, atol=1e-14
    )
    # Continuity through k = 0 (the series branch): tiny k equals the parabola to first order.
    x_small = pstf.propagate(t, x_c, v_c, 1e-9, c)[0]
    np.testing.assert_allclose(x_small, x_c + v_c * t + c * t * t / 2, atol=1e-8)


def test_eq5_sign_corrected_energy_balance() -> None:
    """v_n²/2 = v_c²/2 + ∫ (k s + c) ds over [x_c, x_n] with c from the corrected eq. 5."""
    x_c, v_c, x_n, v_n, k = -0.2, 0.4, 0.9, 1.3, 0.7
    c = pstf.coefficient_c(x_c, v_c, x_n, v_n, k)
    work = k * (x_n**2 - x_c**2) / 2 + c * (x_n - x_c)
    assert v_c**2 / 2 + work == pytest.approx(v_n**2 / 2, rel=1e-12)
    c0, m = pstf.mid_point_form(x_c, v_c, x_n, v_n)
    assert c == pytest.approx(c0 - k * m)


def test_k_max_bound_rest_to_rest_and_time_formulas() -> None:
    assert pstf.k_max(0.0, 0.0, 1.0) == 0.0
    assert pstf.time_to_reach(0.0, 0.0, 1.0, 0.0, 0.0) == math.inf  # stalls
    # rest to rest with k = -w^2 is half a period
    w = 3.0
    assert pstf.time_to_reach(0.0, 0.0, 1.0, 0.0, -w * w) == pytest.approx(math.pi / w)
    assert pstf.time_to_reach(0.0, 0.0, -1.0, 0.0, -w * w) == pytest.approx(math.pi / w)
    # k = 0: t = 2Δ/(v_c+v_n)
    assert pstf.time_to_reach(0.0, 1.0, 2.0, 3.0, 0.0) == pytest.approx(1.0)
    # wrong-direction velocities are not a PSTF segment
    assert pstf.time_to_reach(0.0, -1.0, 1.0, 1.0, -1.0) == math.inf
    assert pstf.time_to_reach(0.5, 0.3, 0.5, 0.3, 1.0) == 0.0


def test_kinetic_energy_matches_propagated_velocity() -> None:
    x_c, v_c, x_n, v_n, k = 0.0, 0.5, 1.0, 0.2, -2.0
    c = pstf.coefficient_c(x_c, v_c, x_n, v_n, k)
    T = pstf.time_to_reach(x_c, v_c, x_n, v_n, k)
    x, v = pstf.propagate(np.linspace(0, T, 30), x_c, v_c, k, c)
    ke = pstf.kinetic_energy((x - x_c) / (x_n - x_c), v_c, v_n, x_n - x_c, k)
    np.testing.assert_allclose(ke, v * v / 2, rtol=1e-9, atol=1e-12)


@settings(max_examples=80, deadline=None)
@given(segments(), st.floats(0.05, 5.0, **finite))
def test_k_for_duration_inverts_time_to_reach(seg: tuple, duration: float) -> None:
    x_c, v_c, x_n, v_n, _ = seg
    k_high = pstf.k_limit(v_c, v_n, x_n - x_c, 1e-3)
    k = pstf.k_for_duration(x_c, v_c, x_n, v_n, duration, k_high)
    assert k <= k_high
    T = pstf.time_to_reach(x_c, v_c, x_n, v_n, k)
    if k < k_high:
        assert T == pytest.approx(duration, rel=1e-4)
    else:
        assert T <= duration * (1 + 1e-9)


@settings(max_examples=150, deadline=None)
@given(segments(), st.floats(0.05, 5.0, **finite), st.floats(-3.0, 3.0, **finite))
def test_k_for_duration_from_a_guess_finds_the_same_slope(seg: tuple, duration: float, spread: float) -> None:
    """A guess anywhere (near the answer, far below, far above, beyond k_high) changes the path
    of the root-finding, not its answer."""
    x_c, v_c, x_n, v_n, _ = seg
    k_high = pstf.k_limit(v_c, v_n, x_n - x_c, 1e-3)
    k_plain = pstf.k_for_duration(x_c, v_c, x_n, v_n, duration, k_high)
    scale = max(abs(k_plain), (math.pi / duration) ** 2)
    k_guess = k_plain + spread * scale * abs(spread)  # from 0 to ±9 scales away
    k = pstf.k_for_duration(x_c, v_c, x_n, v_n, duration, k_high, k_guess=k_guess)
    assert k <= k_high
    T = pstf.time_to_reach(x_c, v_c, x_n, v_n, k)
    if k_plain < k_high:
        assert k < k_high
        assert T == pytest.approx(duration, rel=1e-6)
        assert k == pytest.approx(k_plain, rel=1e-4, abs=1e-6 * scale)
    else:
        assert k == k_high


@settings(max_examples=200, deadline=None)
@given(segments())
def test_stable_segment_time_is_time_to_reach_without_the_checks(seg: tuple) -> None:
    x_c, v_c, x_n, v_n, k = seg
    delta = x_n - x_c
    c0 = (v_n * v_n - v_c * v_c) / (2.0 * delta)
    assert pstf.stable_segment_time(delta, c0, v_c, v_n, k) == pstf.time_to_reach(x_c, v_c, x_n, v_n, k)
