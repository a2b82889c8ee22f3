"""The rolling-cylinder physics of experiments.rolling against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiments import rolling
from experiments.rolling import Basket, Cylinder, G, StrikeScene

CYL = Cylinder(radius=0.04, length=0.12, mass=0.42, rolling_resistance=0.02, friction=0.4)
BASKET = Basket(edge_y=0.90, near_y=0.92, far_y=1.07, rim_z=-0.30)


def test_rolling_deceleration_is_the_rolling_resistance_formula() -> None:
    # About the contact line: (I + m r²) α = -m g c_rr r, I = m r²/2  ->  a = 2 c_rr g / 3.
    assert CYL.inertia_ratio == pytest.approx(0.5)
    assert CYL.rolling_deceleration == pytest.approx(2.0 / 3.0 * 0.02 * G)
    t = np.linspace(0.0, 10.0, 1001)
    s, v = rolling.roll(CYL, 0.5, t)
    a = CYL.rolling_deceleration
    assert v[0] == 0.5 and v[-1] == 0.0
    assert s[-1] == pytest.approx(0.25 / (2 * a))  # stopping distance v²/(2a)
    i = 100  # t = 1 s, still rolling
    assert v[i] == pytest.approx(0.5 - a * t[i])


@given(
    v1=st.floats(0.01, 3.0),
    v2=st.floats(-1.0, 1.0),
    m1=st.floats(0.1, 10.0),
    m2=st.floats(0.1, 10.0),
    e=st.floats(0.0, 1.0),
)
@settings(max_examples=200, deadline=None)
def test_collision_conserves_momentum_and_loses_the_restitution_energy(
    v1: float, v2: float, m1: float, m2: float, e: float
) -> None:
    a, b = rolling.collide(v1, v2, m1, m2, e)
    assert m1 * a + m2 * b == pytest.approx(m1 * v1 + m2 * v2, abs=1e-9)
    if v1 > v2:
        assert b - a == pytest.approx(e * (v1 - v2), abs=1e-9)
        mu = m1 * m2 / (m1 + m2)
        loss = 0.5 * (m1 * v1**2 + m2 * v2**2) - 0.5 * (m1 * a**2 + m2 * b**2)
        assert loss == pytest.approx(0.5 * mu * (1 - e * e) * (v1 - v2) ** 2, abs=1e-9)
    else:
        assert (a, b) == (v1, v2)


def test_a_hit_at_the_centre_height_rolls_on_at_two_thirds() -> None:
    # Angular momentum about the contact line: m v0 r = (m r² + I) v/r  ->  v = 2 v0/3.
    assert rolling.rolling_speed_after_slip(CYL, 0.6, 0.0) == pytest.approx(0.4)
    assert CYL.effective_mass(CYL.radius) == pytest.approx(CYL.mass)
    # Above the centre the face is lighter: 1/m + d²/I.
    assert CYL.effective_mass(0.06) == pytest.approx(1 / (1 / 0.42 + 0.02**2 / CYL.inertia))


def test_edge_departure_angle() -> None:
    theta, speed = rolling.edge_departure(0.0, 0.04)
    assert math.cos(theta) == pytest.approx(4.0 / 7.0)  # the classic 4/7 from rest
    assert speed == pytest.approx(math.sqrt(G * 0.04 * 4 / 7))
    theta, speed = rolling.edge_departure(1.0, 0.04)  # v² > g r: leaves at once
    assert theta == 0.0 and speed == 1.0
    theta, speed = rolling.edge_departure(0.3, 0.04)
    c = (3 * 0.09 / (G * 0.04) + 4) / 7
    assert math.cos(theta) == pytest.approx(c)
    # Energy while pivoting: (3/4) m v² + m g r (cos θ - 1) is conserved.
    assert 0.75 * speed**2 == pytest.approx(0.75 * 0.09 + G * 0.04 * (1 - c))


def test_ballistic_crossing_of_the_rim_height() -> None:
    fl = rolling.flight(CYL, BASKET, 0.7)  # fast enough to leave the edge at once (θ = 0)
    assert fl.theta == 0.0
    drop = CYL.radius - BASKET.rim_z
    t = math.sqrt(2 * drop / G)
    assert fl.t_rim == pytest.approx(t)
    assert fl.y_rim == pytest.approx(BASKET.edge_y + 0.7 * t)


def test_landing_window_brackets_the_outcomes() -> None:
    scene = StrikeScene(cylinder=CYL, basket=BASKET, start=(0.45, -0.06))
    y0 = 0.15
    lo, hi = rolling.landing_window(scene, y0)
    assert lo is not None and hi is not None and lo < hi
    # The lower end is reaching the edge: v² = 2 a_rr d (the basket's gap is cleared by any roll-off).
    assert lo == pytest.approx(math.sqrt(2 * CYL.rolling_deceleration * (BASKET.edge_y - y0)), abs=1e-4)
    assert rolling.outcome_for_release(scene, y0, lo - 0.01)[0] == rolling.STOPPED
    assert rolling.outcome_for_release(scene, y0, 0.5 * (lo + hi))[0] == rolling.LANDED
    assert rolling.outcome_for_release(scene, y0, hi + 0.01)[0] == rolling.OVER


def test_a_gap_before_the_basket_catches_slow_cylinders() -> None:
    wide_gap = Basket(edge_y=0.90, near_y=1.00, far_y=1.20, rim_z=-0.10)
    scene = StrikeScene(cylinder=CYL, basket=wide_gap, start=(0.45, -0.06))
    lo, _ = rolling.landing_window(scene, 0.15)
    assert lo is not None and lo > math.sqrt(2 * CYL.rolling_deceleration * 0.75) + 0.05
    v_slow = math.sqrt(2 * CYL.rolling_deceleration * 0.75) + 0.01
    assert rolling.outcome_for_release(scene, 0.15, v_slow)[0] == rolling.SHORT


def test_a_steady_push_releases_at_the_push_speed() -> None:
    # The effector meets the cylinder slowly and accelerates; it separates where the effector brakes.
    scene = StrikeScene(cylinder=CYL, basket=BASKET, start=(0.45, -0.06), effector_mass=1.9, restitution=0.3)
    dt = 0.002
    t = np.arange(0.0, 3.0, dt)
    # 0.1 m/s until the face (y = -0.10) at t = 1 s, then +0.4 m/s² to 0.5 m/s, then braking.
    v2 = np.where(
        t < 1.0, 0.1, np.where(t < 2.0, 0.1 + 0.4 * (t - 1.0), np.maximum(0.5 - 2.0 * (t - 2.0), 0))
    )
    y2 = -0.20 + np.concatenate([[0.0], np.cumsum(0.5 * (v2[1:] + v2[:-1]) * dt)])
    x2 = np.column_stack([np.full_like(t, 0.45), y2, np.full_like(t, 0.04)])
    res2 = rolling.simulate_strike(scene, t, x2, np.column_stack([np.zeros_like(t), v2, np.zeros_like(t)]))
    assert t[res2.meet_index] == pytest.approx(1.0, abs=0.01)
    assert res2.v_release == pytest.approx(0.5, rel=0.02)
    assert res2.outcome == rolling.LANDED


def test_an_effector_above_or_beside_the_cylinder_does_not_touch_it() -> None:
    scene = StrikeScene(cylinder=CYL, basket=BASKET, start=(0.45, -0.06))
    t = np.arange(0.0, 2.0, 0.002)
    y = -0.3 + 0.3 * t
    vel = np.column_stack([np.zeros_like(t), np.full_like(t, 0.3), np.zeros_like(t)])
    above = np.column_stack([np.full_like(t, 0.45), y, np.full_like(t, 0.09)])
    beside = np.column_stack([np.full_like(t, 0.55), y, np.full_like(t, 0.04)])
    for x in (above, beside):
        res = rolling.simulate_strike(scene, t, x, vel)
        assert res.outcome == rolling.MISSED and res.meet_index is None


def test_bad_parameters_name_the_field() -> None:
    with pytest.raises(ValueError, match="rolling_resistance"):
        Cylinder(rolling_resistance=-0.1)
    with pytest.raises(ValueError, match="restitution"):
        StrikeScene(restitution=1.5)
    with pytest.raises(ValueError, match="rim_z"):
        Basket(rim_z=0.1)
