"""The plots: files written, and the PSTF lines drawn are the model's segments."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from experiments import plots
from psm import PhaseSpaceModel
from psm.pstf import propagate


@pytest.fixture(scope="module")
def reach() -> tuple[np.ndarray, np.ndarray, PhaseSpaceModel]:
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    s = t / 2.0
    s = 10 * s**3 - 15 * s**4 + 6 * s**5
    X = np.stack([0.4 * s, 0.2 * np.sin(np.pi * s)], axis=1)
    # No acceleration limit: the controller then runs each learned k unchanged. Three uniform
    # segments exactly (no velocity-extremum via-point added to them).
    return t, X, PhaseSpaceModel.fit(t, X, segments=3, max_acceleration=np.inf, velocity_extrema=False)


def test_pstf_lines_are_the_model_segments(reach) -> None:
    _t, _X, model = reach
    goal = np.array([0.5, -0.1])
    lines = plots.pstf_lines(model, goal)
    checked = 0
    for d, (vp, k) in enumerate(zip(model.via_points, model.k, strict=True)):
        assert len(lines[d]) == len(k)
        for j, ln in enumerate(lines[d]):
            assert ln.x_c == pytest.approx(goal[d] + vp.position[j]) and ln.k == k[j]
            # the line's law a = k x + c, propagated from (x_c, v_c), reaches (x_n, v_n): it is the PSTF
            c = ln.c0 - ln.k * ln.m
            tt = np.linspace(0.0, model.segment_durations[d][j], 2001)
            xs, vs = propagate(tt, ln.x_c, ln.v_c, ln.k, c)[:2]
            assert abs(xs[-1] - ln.x_n) < 1e-6 * max(1.0, abs(ln.x_n)) + 1e-9
            assert abs(vs[-1] - ln.v_n) < 1e-5
            # and the controller, given a state on that PSTF, commands the line's law: the constant
            # acceleration that gives the PSTF's velocity one tick later (tends to the line's a(x))
            mid = len(tt) // 2
            ctrl = model.controller(goal, sync_gain=0.0)
            state_x, state_v = goal.copy(), np.zeros(2)
            state_x[d], state_v[d] = xs[mid], vs[mid]
            other = 1 - d
            state_x[other] = goal[other]  # the other dimension at rest on its goal
            dt = 0.002
            a = ctrl.step(state_x, state_v, dt)
            if ctrl.segment[d] != j:
                # a dimension that reverses: a fresh controller cannot tell the way out from the
                # way back (x, monotone, always can)
                assert d == 1
                continue
            checked += int(d == 0)
            v_next = propagate(np.array([dt]), xs[mid], vs[mid], ln.k, c)[1][0]
            assert a[d] == pytest.approx((v_next - vs[mid]) / dt, rel=1e-6, abs=1e-9)
            assert a[d] == pytest.approx(float(ln.acceleration(xs[mid])), rel=5e-3, abs=5e-3)
    assert checked == len(lines[0]) == 3


def test_the_phase_plot_draws_those_lines(reach, tmp_path: Path) -> None:
    t, X, model = reach
    lines = plots.pstf_lines(model)
    fig = plots.phase_space_figure([plots.PhaseCurve("demo", X, np.gradient(X, t, axis=0), None)], lines)
    drawn = {ln.get_gid(): ln.get_xydata() for ax in fig.axes for ln in ax.lines if ln.get_gid()}
    assert len(drawn) == sum(len(seg) for seg in lines)
    for d, seg in enumerate(lines):
        for j, ln in enumerate(seg):
            xy = drawn[f"pstf-{d}-{j}"]
            np.testing.assert_allclose(xy[:, 0], [ln.x_c, ln.x_n])
            np.testing.assert_allclose(xy[:, 1], ln.c0 + ln.k * (xy[:, 0] - ln.m))
    labels = [ax.get_xlabel() + "|" + ax.get_ylabel() for ax in fig.axes]
    assert "x [m]|velocity [m/s]" in labels and "y [m]|acceleration [m/s²]" in labels
    out = plots.save_figure(fig, tmp_path / "phase.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_time_to_go_along_a_rollout_and_every_plot_file(reach, tmp_path: Path) -> None:
    t, X, model = reach
    goal = np.array([0.45, 0.05])
    r = model.rollout(X[0], goal=goal, dt=0.002)
    te = plots.time_to_go_along(model, r.x, r.v, 0.002, goal)
    ctrl = model.controller(goal)
    for i in range(len(r.t)):
        ctrl.step(r.x[i], r.v[i], 0.002)
        if i % 97 == 0:
            np.testing.assert_array_equal(te[i], ctrl.time_to_go)
    assert te[0, 0] > 1.0 and np.all(te[-1] < 0.05)
    files = [
        plots.plot_trajectories(tmp_path / "a.png", [plots.Curve("run", r.t, r.x), plots.Curve("demo", t, X)],
                                goal=goal, marks={"goal": 1.0}),
        plots.plot_path(tmp_path / "b.png", [plots.Curve("run", r.t, r.x)], points={"goal": goal}),
        plots.plot_path(tmp_path / "b3.png", [plots.Curve("run", r.t, np.c_[r.x, r.x[:, 0]])]),
        plots.plot_time_to_go(tmp_path / "c.png", r.t, te, recorded=(r.t[::50], te[::50])),
        plots.plot_cylinder_phase(tmp_path / "d.png", {"PSM": [(r.x[:, 1], r.v[:, 1])], "DMP": []},
                                  (X[:, 1], np.gradient(X[:, 1], t)), contact=0.1, target_speed=0.3),
    ]
    for f in files:
        assert f.stat().st_size > 5_000
