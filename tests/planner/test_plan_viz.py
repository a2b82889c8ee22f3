"""The planner's task in Foxglove's 3-D panel: PlanScene's entities, its bounded path, and the
in-process planner publishing it with its status (never from the control path)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.bus.config import load_config
from services.bus.messages import ArmState, PlannerStatus, SceneUpdate
from services.planner.config import PlannerConfig
from services.planner.service import PlannerService
from services.planner.viz import PlanScene

from .test_planner_inputs import _FakeService, _Pub, _state

ROOT = Path(__file__).resolve().parents[2]


def _entities(msg: SceneUpdate) -> dict[str, Any]:
    return {e.id: e for e in msg.entities}


def _points(line: Any) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in line.points])


def test_entities_goal_segment_path_and_static_goals() -> None:
    scene = PlanScene("base", {"bowl": (0.5, -0.2, 0.1), "spoon": (0.4, 0.3, 0.05)}, 100, 0.001)
    msg = scene.update(2_500_000_000, (0.3, 0.0, 0.5), (0.5, -0.2, 0.15), "bowl")
    e = _entities(msg)
    assert set(e) == {"plan/goal", "plan/segment", "plan/path", "plan/static_goals"}
    assert all(x.frame_id == "base" and (x.timestamp.seconds, x.timestamp.nanos) == (2, 500_000_000)
               for x in msg.entities)
    g = e["plan/goal"].spheres[0].pose.position
    assert (g.x, g.y, g.z) == (0.5, -0.2, 0.15) and e["plan/goal"].texts[0].text == "bowl"
    np.testing.assert_array_equal(_points(e["plan/segment"].lines[0]), [[0.3, 0.0, 0.5], [0.5, -0.2, 0.15]])
    statics = e["plan/static_goals"]
    assert [t.text for t in statics.texts] == ["bowl", "spoon"]
    assert [(s.pose.position.x, s.pose.position.y) for s in statics.spheres] == [(0.5, -0.2), (0.4, 0.3)]
    # The end effector moves: the segment follows, the path grows; no goal: goal and segment go.
    msg = scene.update(2_600_000_000, (0.35, 0.0, 0.45), (0.5, -0.2, 0.15), "bowl")
    e = _entities(msg)
    np.testing.assert_array_equal(_points(e["plan/segment"].lines[0])[0], [0.35, 0.0, 0.45])
    np.testing.assert_array_equal(_points(e["plan/path"].lines[0]), [[0.3, 0.0, 0.5], [0.35, 0.0, 0.45]])
    e = _entities(scene.update(2_700_000_000, (0.36, 0.0, 0.45), None, ""))
    assert not e["plan/goal"].spheres and not e["plan/goal"].texts and not e["plan/segment"].lines
    assert len(e["plan/path"].lines[0].points) == 3
    e = _entities(scene.update(2_800_000_000, (0.37, 0.0, 0.45), (0.1, 0.2, 0.3), "spoon"))
    assert len(e["plan/segment"].lines) == 1 and e["plan/goal"].texts[0].text == "spoon"
    np.testing.assert_array_equal(_points(e["plan/segment"].lines[0]), [[0.37, 0.0, 0.45], [0.1, 0.2, 0.3]])
    # One message changed in place: it round-trips through its bytes.
    assert SceneUpdate.FromString(msg.SerializeToString()) == msg


def test_the_path_is_bounded_and_keeps_its_ends() -> None:
    scene = PlanScene("base", {}, 16, 0.01)
    xs = np.linspace(0.0, 1.0, 501)  # 2 mm apart: only every 5th is 1 cm from the last point
    for k, x in enumerate(xs):
        line = _entities(scene.update(k, (x, 0.0, 0.0), None, ""))["plan/path"].lines[0]
        assert len(line.points) == scene.n_points <= 16
        np.testing.assert_array_equal(_points(line), scene.path)
    pts = scene.path[:, 0]
    assert pts[0] == 0.0 and pts[-1] == pytest.approx(1.0, abs=0.01)  # the whole path, both ends
    assert np.all(np.diff(pts) > 0) and np.all(np.diff(pts) >= 0.01 - 1e-12)
    with pytest.raises(ValueError):
        PlanScene("base", {}, 1, 0.0)


def test_the_planner_publishes_the_scene_with_its_status() -> None:
    cfg = load_config(PlannerConfig, env={}, overrides={"planner.cache_dir": str(ROOT / "out" / "models")})
    p = PlannerService(cfg)
    p.svc = _FakeService()  # type: ignore[assignment]
    p._state_key = "psm/arm/state"
    status, viz, cmd, goal = _Pub(), _Pub(), _Pub(), _Pub()
    p._status_pub, p._viz_pub, p._cmd_pub, p._goal_pub = status, viz, cmd, goal  # type: ignore[assignment]
    p._publish_status()
    assert len(status.sent) == 1 and not viz.sent  # no state answered yet: no end effector to show
    x = np.array([0.307, 0.0, 0.487])
    for k in range(200):
        assert p._answer(_state(k, tuple(x + np.array([0.0, 0.001 * k, 0.0])))) is not None  # type: ignore[arg-type]
        if k % 10 == 9:
            p._publish_status()
    assert len(viz.sent) == 20 and len(status.sent) == 21
    msg: SceneUpdate = SceneUpdate.FromString(viz.sent[-1].SerializeToString())
    st: PlannerStatus = status.sent[-1]
    e = _entities(msg)
    assert all(x.frame_id == p.frame_id == "base" for x in msg.entities)
    assert e["plan/goal"].texts[0].text == st.goal_name == p.runner.step_spec.goal  # type: ignore[union-attr]
    g = e["plan/goal"].spheres[0].pose.position
    assert (g.x, g.y, g.z) == (st.goal.x, st.goal.y, st.goal.z)
    seg = _points(e["plan/segment"].lines[0])
    np.testing.assert_allclose(seg, [x + np.array([0.0, 0.199, 0.0]), [st.goal.x, st.goal.y, st.goal.z]])
    path = _points(e["plan/path"].lines[0])
    assert len(path) == 20  # one point per status (10 mm apart, more than viz_path_step_m)
    np.testing.assert_allclose(path[:, 1], 0.009 + 0.01 * np.arange(20))
    assert {t.text for t in e["plan/static_goals"].texts} == set(p.task_config.scene.positions())
    assert msg.entities[0].timestamp.seconds * 10**9 + msg.entities[0].timestamp.nanos == st.stamp_ns


def test_the_control_path_never_touches_the_scene() -> None:
    """Answering states changes neither the scene's path nor its message."""
    cfg = load_config(PlannerConfig, env={}, overrides={"planner.cache_dir": str(ROOT / "out" / "models")})
    p = PlannerService(cfg)
    p.svc = _FakeService()  # type: ignore[assignment]
    p._state_key = "psm/arm/state"
    p._cmd_pub, p._goal_pub = _Pub(), _Pub()  # type: ignore[assignment]
    before = p.plan_scene.msg.SerializeToString()
    for k in range(50):
        assert p._answer(ArmState.FromString(_state(k).SerializeToString())) is not None
    assert p.plan_scene.n_points == 0 and p.plan_scene.msg.SerializeToString() == before
