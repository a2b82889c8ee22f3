"""The obstacle monitor without the bus: its config, the obstacle commands (add, move, remove,
rejections with their reasons), the prediction for an arm state, and the Foxglove scene."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.bus.config import ConfigError, load_config
from services.bus.messages import ArmState, Goal, Obstacle, ObstacleCommand, vec3
from services.obstacle_monitor.config import ObstacleMonitorConfig
from services.obstacle_monitor.scene import obstacle_from_message, obstacle_set_message, scene_update
from services.obstacle_monitor.service import ObstacleMonitorService

ROOT = Path(__file__).resolve().parents[2]
WALL_FILE = ROOT / "configs" / "obstacles" / "paper_wall.toml"


def _config(**monitor: Any) -> ObstacleMonitorConfig:
    overrides = {f"obstacle_monitor.{k}": v for k, v in monitor.items()}
    return load_config(ObstacleMonitorConfig, None, overrides=overrides, env={})


class _Svc:
    """The parts of the bus service the monitor's logic touches."""

    def __init__(self) -> None:
        self.rejections: list[str] = []

    def record_rejection(self, key: str, reason: str, kind: str = "invalid") -> None:
        self.rejections.append(reason)


def _monitor(**monitor: Any) -> ObstacleMonitorService:
    m = ObstacleMonitorService(_config(**monitor))
    m.svc = _Svc()  # type: ignore[assignment]
    m._state_key = "psm/arm/state"
    return m


def _add(shape: int, oid: str, position: Any, size: Any, velocity: Any = (0, 0, 0), stamp_ns: int = 0) -> Any:
    cmd = ObstacleCommand(action=ObstacleCommand.ADD, stamp_ns=stamp_ns)
    ob = cmd.obstacle
    ob.id, ob.shape = oid, shape
    ob.position.x, ob.position.y, ob.position.z = position
    ob.size.x, ob.size.y, ob.size.z = size
    ob.velocity.x, ob.velocity.y, ob.velocity.z = velocity
    return cmd


def _state(tick: int, x: Any, v: Any = (0.0, 0.0, 0.0), dt: float = 0.002) -> ArmState:
    st = ArmState(tick=tick, stamp_ns=round(tick * dt * 1e9), dt_s=dt)
    st.ee_position.x, st.ee_position.y, st.ee_position.z = x
    st.ee_linear_velocity.x, st.ee_linear_velocity.y, st.ee_linear_velocity.z = v
    st.ee_orientation.w = 1.0
    st.q.extend([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    st.dq.extend([0.0] * 7)
    return st


# ---------------------------------------------------------------------------- config
def test_the_start_set_comes_from_the_section_and_the_obstacles_file() -> None:
    cfg = _config(
        obstacles=[
            {"id": "post", "shape": "cylinder", "position_m": [0.5, 0.0, 0.2], "size_m": [0.05, 0, 0.4]}
        ],
        obstacles_file=str(WALL_FILE),
    )
    ids = [o.id for o in cfg.obstacle_monitor.start_obstacles()]
    assert ids == ["post", "wall"]


@pytest.mark.parametrize(
    ("obstacle", "field"),
    [
        ({"size_m": [0.1, -0.1, 0.1]}, "obstacle_monitor.obstacles[0].size_m"),
        ({"shape": "cone"}, "obstacle_monitor.obstacles[0].shape"),
        ({"position_m": [0.1, 0.2]}, "obstacle_monitor.obstacles[0].position_m"),
    ],
)
def test_a_bad_start_obstacle_is_one_error_naming_the_field(obstacle: dict[str, Any], field: str) -> None:
    ob = {"id": "a", "shape": "box", "position_m": [0.5, 0.0, 0.2], "size_m": [0.1, 0.1, 0.1]} | obstacle
    with pytest.raises(ConfigError) as err:
        _config(obstacles=[ob]).obstacle_monitor.check()
    assert field in str(err.value)


def test_duplicate_start_ids_are_an_error() -> None:
    ob = {"id": "a", "shape": "sphere", "position_m": [0.5, 0.0, 0.2], "size_m": [0.1, 0, 0]}
    with pytest.raises(ConfigError, match=r"obstacles\[1\]\.id.*duplicate"):
        _config(obstacles=[ob, ob]).obstacle_monitor.check()


def test_resume_below_stop_is_rejected() -> None:
    with pytest.raises(ConfigError, match="clearance_resume_m"):
        _config(clearance_stop_m=0.05, clearance_resume_m=0.01)


# ---------------------------------------------------------------------------- commands
def test_add_move_remove_and_every_rejection_reason() -> None:
    m = _monitor(clearance=False)
    assert m.apply_command(_add(Obstacle.BOX, "box", (0.5, 0.3, 0.2), (0.2, 0.04, 0.3))) == ""
    assert m.apply_command(_add(Obstacle.BOX, "box", (0.5, 0.3, 0.2), (0.2, 0.04, 0.3))) == "duplicate_id"
    assert m.apply_command(_add(Obstacle.SPHERE, "s", (math.nan, 0.3, 0.2), (0.1, 0, 0))) == "nan"
    assert m.apply_command(_add(Obstacle.SPHERE, "s", (0.5, 0.3, 0.2), (-0.1, 0, 0))) == "size"
    assert m.apply_command(_add(Obstacle.SHAPE_UNSPECIFIED, "s", (0.5, 0.3, 0.2), (0.1, 0, 0))) == "shape"
    assert m.apply_command(_add(7, "s", (0.5, 0.3, 0.2), (0.1, 0, 0))) == "shape"
    bad_q = _add(Obstacle.SPHERE, "s", (0.5, 0.3, 0.2), (0.1, 0, 0))
    bad_q.obstacle.orientation.w = 2.0
    assert m.apply_command(bad_q) == "orientation"
    assert m.apply_command(_add(Obstacle.SPHERE, "", (0.5, 0.3, 0.2), (0.1, 0, 0))) == "id"
    move = ObstacleCommand(action=ObstacleCommand.MOVE)
    move.obstacle.id = "ghost"
    move.obstacle.position.x = 0.4
    assert m.apply_command(move) == "unknown_id"
    assert m.apply_command(ObstacleCommand(action=ObstacleCommand.REMOVE, id="ghost")) == "unknown_id"
    # Only the valid box made it in.
    assert [o.id for o in m.current_obstacles()] == ["box"]
    # MOVE keeps shape and size.
    move.obstacle.id = "box"
    move.obstacle.position.x, move.obstacle.position.y, move.obstacle.position.z = 0.4, 0.1, 0.1
    assert m.apply_command(move) == ""
    (box,) = m.current_obstacles()
    assert box.shape == "box" and np.allclose(box.size, [0.2, 0.04, 0.3])
    assert np.allclose(box.position, [0.4, 0.1, 0.1])
    assert m.apply_command(ObstacleCommand(action=ObstacleCommand.REMOVE, id="box")) == ""
    assert m.current_obstacles() == []


# ---------------------------------------------------------------------------- predictions
def test_the_wall_stops_y_at_its_inflated_face() -> None:
    m = _monitor(clearance=False, obstacles_file=str(WALL_FILE), margin_m=0.03, tool_radius_m=0.15)
    m.monitor.set_goal([0.35, 0.5, 0.45])
    pred = m.predict(_state(10, (0.55, 0.25, 0.16), (0.0, 0.1, 0.1)))
    assert pred is not None and pred.collision and pred.obstacle_id == "wall"
    assert pred.state_tick == 10 and pred.stamp_ns == 20_000_000 and pred.goal_known
    stop = list(pred.stop_position)
    assert math.isnan(stop[0]) and math.isnan(stop[2]) and stop[1] == pytest.approx(0.465 - 0.015 - 0.18)
    assert 0.0 < pred.time_to_collision_s < math.inf
    assert not pred.protective_stop and pred.obstacle_count == 1


def test_the_stopping_path_holds_an_axis_at_a_face_the_segment_to_the_goal_clears() -> None:
    """Over the wall's top (inflated to z = 0.41) with the goal beyond it and above: the segment
    to the goal is clear, but the end effector sinks towards the top. The stopping check stops z
    at the top face and holds the stop while the end effector stays within stopping_release_m
    (1 cm) above it over the wall; 1.5 cm above, or beside the wall, it is released."""
    m = _monitor(clearance=False, obstacles_file=str(WALL_FILE), margin_m=0.03, tool_radius_m=0.15)
    m.monitor.set_goal([0.5, 0.75, 0.45])
    top = 0.115 + 0.115 + 0.18
    pred = m.predict(_state(1, (0.5, 0.40, top + 0.005), (0.0, 0.1, -0.2)))
    assert pred is not None and pred.collision and pred.obstacle_id == "wall" and not pred.inside
    stop = list(pred.stop_position)
    assert math.isnan(stop[0]) and math.isnan(stop[1]) and stop[2] == pytest.approx(top)
    # Sliding along the top (grazing): the stop is held.
    pred = m.predict(_state(2, (0.5, 0.45, top + 0.001), (0.0, 0.1, 0.0)))
    assert pred is not None and pred.collision and list(pred.stop_position)[2] == pytest.approx(top)
    pred = m.predict(_state(3, (0.5, 0.46, top + 0.015), (0.0, 0.1, 0.0)))
    assert pred is not None and not pred.collision  # released
    # Caught again, then released beside the wall (out of its y extent).
    assert m.predict(_state(4, (0.5, 0.50, top + 0.004), (0.0, 0.1, -0.3))).collision
    assert m.predict(_state(5, (0.5, 0.60, top + 0.001), (0.0, 0.1, 0.0))).collision
    assert not m.predict(_state(6, (0.5, 0.67, top + 0.001), (0.0, 0.1, 0.0))).collision
    # Off: the segment to the goal alone.
    off = _monitor(clearance=False, obstacles_file=str(WALL_FILE), stopping_check=False)
    off.monitor.set_goal([0.5, 0.75, 0.45])
    assert not off.predict(_state(1, (0.5, 0.40, top + 0.005), (0.0, 0.1, -0.2))).collision


def test_inside_the_top_an_axis_sinking_deeper_is_held_though_the_goal_is_above() -> None:
    """Just inside the wall's inflated top (z = 0.41) with the goal above and beyond it, the
    segment to the goal leaves the volume at once: no axis goes deeper towards the goal. An end
    effector whose own path still sinks (its z segment dips, the goal moved down) would go on
    into the volume if nothing were held: z is held where it is (a stopping-check stop, inside),
    and nothing is held once it rises or rests."""
    m = _monitor(clearance=False, obstacles_file=str(WALL_FILE), margin_m=0.03, tool_radius_m=0.15)
    m.monitor.set_goal([0.32, 0.48, 0.44])
    top = 0.115 + 0.115 + 0.18
    x = (0.41, 0.35, top - 1e-5)
    pred = m.predict(_state(1, x, (0.0, 0.08, -0.008)))
    assert pred is not None and pred.collision and pred.inside and pred.obstacle_id == "wall"
    stop = list(pred.stop_position)
    assert math.isnan(stop[0]) and math.isnan(stop[1]) and stop[2] == x[2]
    for v in ((0.0, 0.08, 0.008), (0.0, 0.08, 0.0)):  # rising, or level: the path leaves
        pred = m.predict(_state(2, x, v))
        assert pred is not None and pred.collision and pred.inside
        assert np.isnan(list(pred.stop_position)).all()
    # Off: the segment to the goal alone, as before.
    off = _monitor(clearance=False, obstacles_file=str(WALL_FILE), stopping_check=False)
    off.monitor.set_goal([0.32, 0.48, 0.44])
    assert np.isnan(list(off.predict(_state(1, x, (0.0, 0.08, -0.008))).stop_position)).all()


def test_no_goal_no_segment_test() -> None:
    m = _monitor(clearance=False, obstacles_file=str(WALL_FILE))
    pred = m.predict(_state(1, (0.55, 0.26, 0.16)))
    assert pred is not None and not pred.goal_known and not pred.collision
    assert all(math.isnan(c) for c in pred.stop_position)


def test_a_moving_obstacle_is_predicted_forward_on_the_stack_clock() -> None:
    """A sphere 0.3 m beside the path moving at 0.3 m/s towards it: no hit with the horizon off,
    a hit with a 1.5 s horizon, and at t = 1 s it sits on the path."""
    still = _monitor(clearance=False, horizon_s=0.0)
    moving = _monitor(clearance=False, horizon_s=1.5)
    for m in (still, moving):
        m.monitor.set_goal([0.5, 0.5, 0.3])
        m.predict(_state(0, (0.5, 0.0, 0.3)))
        ball = _add(Obstacle.SPHERE, "ball", (0.2, 0.25, 0.3), (0.06, 0, 0), (0.3, 0, 0))
        assert m.apply_command(ball) == ""
    p = still.predict(_state(1, (0.5, 0.0, 0.3)))
    assert p is not None and not p.collision
    p = moving.predict(_state(1, (0.5, 0.0, 0.3)))
    assert p is not None and p.collision and p.obstacle_id == "ball"
    (ball,) = still.current_obstacles()
    for k in range(50, 500, 50):  # the arm's stream goes on (a state at most 50 ticks apart)
        still.predict(_state(k, (0.5, 0.0, 0.3)))
    p = still.predict(_state(500, (0.5, 0.0, 0.3)))  # t = 1 s: the ball is at x = 0.5
    assert p is not None and p.collision
    assert np.allclose(still.current_obstacles()[0].position, [0.5, 0.25, 0.3], atol=1e-9)
    assert np.allclose(ball.position, [0.2 + 0.3 * 0.002, 0.25, 0.3])


def test_a_non_finite_state_gets_no_prediction() -> None:
    m = _monitor(clearance=False)
    assert m.predict(_state(1, (math.nan, 0.0, 0.3))) is None
    assert m.svc.rejections  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------- messages
def test_set_and_scene_messages_round_trip() -> None:
    cfg = _config(obstacles_file=str(WALL_FILE))
    obs = cfg.obstacle_monitor.start_obstacles()
    msg = obstacle_set_message(obs, 5, 1, "base")
    back = obstacle_from_message(msg.obstacles[0])
    assert back.id == "wall" and np.allclose(back.position, obs[0].position)
    assert np.allclose(back.size, obs[0].size)
    scene = scene_update(obs, 0.18, 5, "base", removed=["old"])
    (e,) = scene.entities
    assert e.id == "obstacle/wall" and e.frame_id == "base" and len(e.cubes) == 2
    assert e.cubes[1].size.y == pytest.approx(0.03 + 0.36) and e.cubes[1].color.a < 1.0
    assert scene.deletions[0].id == "obstacle/old"


def test_states_off_the_arms_stream_get_no_prediction() -> None:
    """A tick that goes back or jumps, or a stamp that disagrees with the tick, is rejected by
    reason; the stream goes on with the real states."""
    m = _monitor(clearance=False)
    assert m.predict(_state(10, (0.5, 0.0, 0.3))) is not None
    jumped = _state(10_000, (0.5, 0.0, 0.3))
    back = _state(3, (0.5, 0.0, 0.3))
    stamped = _state(11, (0.5, 0.0, 0.3))
    stamped.stamp_ns += 10_000_000
    for bad in (jumped, back, stamped):
        assert m.predict(bad) is None
    assert len(m.svc.rejections) == 3  # type: ignore[attr-defined]
    assert m.predict(_state(11, (0.5, 0.0, 0.3))) is not None


def test_planner_goals_that_are_stale_or_absurd_are_rejected() -> None:
    m = _monitor(clearance=False)
    m._on_goal(Goal(stamp_ns=100, valid=True, position=vec3(0.5, 0.5, 0.3)), "psm/planner/goal")
    for bad in (Goal(stamp_ns=50, valid=True, position=vec3(0.4, 0.4, 0.3)),
                Goal(stamp_ns=200, valid=True, position=vec3(1e308, 0.0, 0.0)),
                Goal(stamp_ns=200, valid=True, position=vec3(math.nan, 0.0, 0.0))):
        m._on_goal(bad, "psm/planner/goal")
    assert m.monitor._goal is not None and np.allclose(m.monitor._goal, [0.5, 0.5, 0.3])
    assert len(m.svc.rejections) == 3  # type: ignore[attr-defined]
