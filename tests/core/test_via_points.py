"""Via-points that keep demonstrated states: velocity extrema and the user's via_point_times."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import betainc
from trajectories import minimum_jerk

from psm import ParameterError, PhaseSpaceModel
from psm.fitting import smooth

#: A velocity pulse of 80 ms width (Gaussian, 1/e half-width) at t = 1 s, peak 0.4 m/s.
PULSE_T, PULSE_W, PULSE_V = 1.0, 0.08, 0.4


def _pulse_demo() -> tuple[np.ndarray, np.ndarray]:
    """1-D demo at 500 Hz over 2 s whose velocity is a narrow pulse: the 20 ms smoothing rounds
    its peak down by 13 % (w / sqrt(w² + 2σ²))."""
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    x = PULSE_V * PULSE_W * math.sqrt(math.pi) / 2 * (1 + np.vectorize(math.erf)((t - PULSE_T) / PULSE_W))
    return t, x


def _speed_at(r_x: np.ndarray, r_v: np.ndarray, x0: float) -> float:
    """Velocity [m/s] where the 1-D path first crosses ``x0`` moving up (interpolated)."""
    j = int(np.flatnonzero((r_x[:-1] < x0) & (r_x[1:] >= x0))[0])
    w = (x0 - r_x[j]) / (r_x[j + 1] - r_x[j])
    return float((1 - w) * r_v[j] + w * r_v[j + 1])


def test_smoothing_rounds_the_pulse_off_but_the_via_point_keeps_the_raw_peak() -> None:
    t, x = _pulse_demo()
    smoothed_peak = float(smooth(t, x[:, None], 0.02).v.max())
    assert smoothed_peak == pytest.approx(PULSE_V * PULSE_W / math.hypot(PULSE_W, 2**0.5 * 0.02), rel=0.01)
    model = PhaseSpaceModel.fit(t, x, velocity_extrema=True)
    vp = model.via_points[0]
    i = int(np.argmax(vp.velocity))
    # the via-point sits at the peak (t = 1 s, x = half the travel) with the raw peak velocity
    assert model.cut_times[0][i] == pytest.approx(PULSE_T, abs=0.005)
    assert vp.position[i] + model.goal[0] == pytest.approx(x[-1] / 2, abs=2e-4)
    assert vp.velocity[i] == pytest.approx(PULSE_V, rel=0.005)
    # and the rollout from the demonstrated start passes there at that speed
    r = model.rollout(dt=0.002)
    assert r.done
    assert _speed_at(r.x[:, 0], r.v[:, 0], x[-1] / 2) == pytest.approx(PULSE_V, rel=0.02)


def test_without_velocity_extrema_the_peak_is_the_smoothed_one_or_none() -> None:
    t, x = _pulse_demo()
    model = PhaseSpaceModel.fit(t, x, segments=1, velocity_extrema=False)
    assert len(model.k[0]) == 1  # rest to rest: no via-point inside
    r = model.rollout(dt=0.002)
    assert _speed_at(r.x[:, 0], r.v[:, 0], x[-1] / 2) < 0.96 * PULSE_V
    assert model.parameters.velocity_extrema is False


def test_a_minimum_jerk_reach_gets_its_speed_peak_as_via_point() -> None:
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    x = 0.4 * minimum_jerk(t, 2.0)
    model = PhaseSpaceModel.fit(t, x, velocity_extrema=True)
    vp = model.via_points[0]
    i = int(np.argmax(vp.velocity))
    assert model.cut_times[0][i] == pytest.approx(1.0, abs=0.005)
    assert vp.velocity[i] == pytest.approx(1.875 * 0.4 / 2.0, rel=1e-3)  # 15/8 · Δ/T


def test_a_speed_dip_and_both_peaks_are_via_points() -> None:
    """Two strokes in the same direction with a slow-down to 0.05 m/s between them."""
    t = np.arange(0.0, 3.0 + 1e-9, 0.002)
    stroke = np.where(t < 1.5, 0.3, 0.5) * np.sin(np.pi * t / 1.5) ** 2
    v = stroke + 0.05 * np.sin(np.pi * t / 3.0)  # 0.05 m/s at t = 1.5 s: a dip, not a stop
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * 0.002)])
    model = PhaseSpaceModel.fit(t, x, velocity_extrema=True)
    cuts = np.asarray(model.cut_times[0])
    vel = model.via_points[0].velocity
    for t_e in (0.75, 2.25):  # the peaks
        i = int(np.argmin(np.abs(cuts - t_e)))
        assert abs(cuts[i] - t_e) < 0.02
        assert vel[i] == pytest.approx(np.interp(cuts[i], t, v), rel=0.01)
    i = int(np.argmin(np.abs(cuts - 1.5)))  # the dip
    assert abs(cuts[i] - 1.5) < 0.05
    assert vel[i] == pytest.approx(np.interp(cuts[i], t, v), abs=2e-3)


def test_noise_wiggles_are_not_via_points() -> None:
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    x = 0.4 * minimum_jerk(t, 2.0) + rng.normal(0.0, 1e-4, t.size)
    with_extrema = PhaseSpaceModel.fit(t, x, segments=1, velocity_extrema=True)
    assert len(with_extrema.k[0]) == 2  # the one speed peak, nothing else


@settings(max_examples=30, deadline=None)
@given(
    a=st.floats(1.0, 4.0),
    b=st.floats(1.0, 4.0),
    duration=st.floats(1.0, 4.0),
    travel=st.floats(-0.5, 0.5).filter(lambda d: abs(d) > 0.02),
)
def test_a_demo_with_one_speed_maximum_has_a_via_point_there(
    a: float, b: float, duration: float, travel: float
) -> None:
    """v ∝ s^a (1 − s)^b: one interior speed maximum at s = a / (a + b)."""
    t = np.linspace(0.0, duration, round(duration / 0.004) + 1)
    s = t / duration
    x = travel * betainc(a + 1, b + 1, s)
    v_peak_s = a / (a + b)
    beta = math.gamma(a + 1) * math.gamma(b + 1) / math.gamma(a + b + 2)
    v = travel * s**a * (1 - s) ** b / beta / duration
    v_max = travel * v_peak_s**a * (1 - v_peak_s) ** b / beta / duration
    model = PhaseSpaceModel.fit(t, x, velocity_extrema=True)
    cuts = np.asarray(model.cut_times[0])
    i = int(np.argmin(np.abs(cuts - v_peak_s * duration)))
    # on the fit's grid (4 ms here) the extremum is the sample nearest to the peak
    assert abs(cuts[i] - v_peak_s * duration) <= 0.006
    assert model.via_points[0].velocity[i] == pytest.approx(np.interp(cuts[i], t, v), rel=0.01)
    assert abs(model.via_points[0].velocity[i]) == pytest.approx(abs(v_max), rel=0.01)


def test_user_via_point_times_are_kept_with_the_raw_velocity() -> None:
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    s = minimum_jerk(t, 2.0)
    X = np.stack([0.4 * s, 0.2 * s**2], axis=1)
    V = np.gradient(X, t, axis=0)
    model = PhaseSpaceModel.fit(t, X, via_point_times=[0.5, 1.4])
    for d in range(2):
        cuts = model.cut_times[d]
        for tc in (0.5, 1.4):
            i = int(np.argmin(np.abs(np.asarray(cuts) - tc)))
            assert cuts[i] == pytest.approx(tc, abs=1e-9)
            assert model.via_points[d].velocity[i] == pytest.approx(np.interp(tc, t, V[:, d]), rel=1e-3)
    assert model.parameters.via_point_times == [0.5, 1.4]
    # rollout from the demonstrated start passes the named points at the demonstrated speed
    r = model.rollout(dt=0.002)
    for tc in (0.5, 1.4):
        x0 = float(np.interp(tc, t, X[:, 0]))
        assert _speed_at(r.x[:, 0], r.v[:, 0], x0) == pytest.approx(np.interp(tc, t, V[:, 0]), rel=0.02)
    # saved and loaded: the same model
    again = PhaseSpaceModel.from_dict(model.to_dict())
    assert again.to_dict() == model.to_dict()


@pytest.mark.parametrize(
    ("times", "message"),
    [
        ([0.0], "strictly inside"),
        ([2.0], "strictly inside"),
        ([-0.3], "strictly inside"),
        ([float("nan")], "strictly inside"),
        ([0.5, 0.5], "same time twice"),
        (["soon"], "list of times"),
        ([[0.5, 0.6]], "list of times"),
    ],
)
def test_invalid_via_point_times_raise_one_clear_error(times: list, message: str) -> None:
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    x = 0.4 * minimum_jerk(t, 2.0)
    with pytest.raises(ParameterError, match=f"via_point_times.*{message}|{message}.*via_point_times"):
        PhaseSpaceModel.fit(t, x, via_point_times=times)


def test_a_version_1_file_loads_as_fitted_without_the_new_via_points() -> None:
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    x = 0.4 * minimum_jerk(t, 2.0)
    model = PhaseSpaceModel.fit(t, x, velocity_extrema=False)
    data = model.to_dict()
    assert data["version"] == 2
    data["version"] = 1
    del data["parameters"]["velocity_extrema"], data["parameters"]["via_point_times"]
    old = PhaseSpaceModel.from_dict(data)
    assert old.parameters.velocity_extrema is False and old.parameters.via_point_times == []
    np.testing.assert_array_equal(old.rollout(dt=0.002).x, model.rollout(dt=0.002).x)


def test_velocity_extrema_are_on_by_default_and_join_the_plain_segmentation() -> None:
    """Two strokes with a slow-down between them (noisy): every cut of the automatic
    segmentation without the extrema is kept with them, or moved onto an extremum by less than
    the extremum's spacing; the peaks are added with the unsmoothed velocity, the slow dip keeps
    the smoothed one."""
    t = np.arange(0.0, 3.0 + 1e-9, 0.002)
    v = np.where(t < 1.5, 0.3, 0.5) * np.sin(np.pi * t / 1.5) ** 2 + 0.05 * np.sin(np.pi * t / 3.0)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * 0.002)])
    x = x + np.random.default_rng(3).normal(0.0, 2e-5, x.shape)
    plain = PhaseSpaceModel.fit(t, x, velocity_extrema=False, auto_tolerance=2e-4)
    model = PhaseSpaceModel.fit(t, x, auto_tolerance=2e-4)
    assert model.parameters.velocity_extrema is True and plain.parameters.velocity_extrema is False
    cuts, plain_cuts = np.asarray(model.cut_times[0]), np.asarray(plain.cut_times[0])
    assert len(cuts) > len(plain_cuts)
    spacing = 0.02 + 1e-9  # one smoothing width: the extrema's spacing
    assert all(np.min(np.abs(cuts - c)) < spacing for c in plain_cuts)
    vel = model.via_points[0].velocity
    peaks = ((0.75, 0.3 + 0.05 * math.sin(math.pi / 4)), (2.25, 0.5 + 0.05 * math.sin(3 * math.pi / 4)))
    for t_e, v_e in peaks:
        i = int(np.argmin(np.abs(cuts - t_e)))
        assert abs(cuts[i] - t_e) < 0.02 and vel[i] == pytest.approx(v_e, rel=0.02)
    # the dip between the strokes (0.05 m/s, below RAW_VELOCITY_MIN_SPEED of the top speed)
    i = int(np.argmin(np.abs(cuts - 1.5)))
    assert abs(cuts[i] - 1.5) < 0.03
    smoothed = smooth(t, x[:, None], model.parameters.smoothing).v[:, 0]
    assert vel[i] == pytest.approx(smoothed[round(cuts[i] / 0.002)], abs=1e-12)
