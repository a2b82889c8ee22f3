"""Obstacles end to end: ``psm up`` with the shipped stack (router, recorder, arm, camera, goal
tracker, obstacle monitor, planner) over real Zenoh on loopback.

* the paper's second experiment in lockstep: a wall between the scoop and the person; the end
  effector never enters its safety volume, y brakes at its face while z rises, then resumes, and
  the person is still reached;
* an obstacle moved into the path mid-motion by a bus message;
* an obstacle next to the forearm but far from the end effector's line: the whole-arm clearance
  stops the arm (the planner holds, the arm rests outside the margin);
* the monitor killed mid-motion: the planner brakes the arm to rest.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from stack_helpers import (
    ROOT,
    arm_speeds,
    check_task,
    client_session,
    kill_mid_motion,
    up,
    up_args,
    up_port,
)

from services.supervisor import ManagedProcess, psm_argv

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]

WALL_FILE = ROOT / "configs" / "obstacles" / "paper_wall.toml"
WALL_CENTRE = np.array([0.50, 0.465, 0.115])
WALL_HALF = np.array([0.20, 0.015, 0.115])
MARGIN = 0.03 + 0.15  # configs/stack.toml [obstacle_monitor] margin_m + tool_radius_m
#: The stop lands on the inflated face to within this [m] (the braking law's last tick).
FACE_TOL = 1e-4


def _read(path: Path) -> dict[str, list[Any]]:
    from services.bus.log import read_log

    out: dict[str, list[Any]] = {}
    for key, msg, _t in read_log(path):
        out.setdefault(key.split("/", 1)[1], []).append(msg)
    return out


def _ee(states: list[Any]) -> np.ndarray:
    return np.array([(m.ee_position.x, m.ee_position.y, m.ee_position.z) for m in states])


def _depth_inside(x: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """How deep each row of ``x (N, 3)`` is inside the box (negative: outside) [m]."""
    return np.min(half - np.abs(x - centre), axis=1)


def _kinds(events: list[Any]) -> list[str]:
    from services.bus.messages import TaskEvent

    return [TaskEvent.Kind.Name(e.kind) for e in events]


def test_the_papers_obstacle_scenario_through_the_stack(tmp_path: Path) -> None:
    rc, log, summary = up(tmp_path, f'obstacle_monitor.obstacles_file="{WALL_FILE}"', timeout_s=400)
    assert rc == 0, log
    task = check_task(summary, log)
    rec = _read(tmp_path / "run.mcap")
    x = _ee(rec["arm/state"])
    depth = _depth_inside(x, WALL_CENTRE, WALL_HALF + MARGIN)
    assert depth.max() < FACE_TOL, f"entered the safety volume by {depth.max() * 1e3:.2f} mm"
    kinds = _kinds(rec["task/events"])
    assert "COLLISION_PREDICTED" in kinds and "PATH_CLEAR" in kinds
    assert kinds.index("COLLISION_PREDICTED") < kinds.index("PATH_CLEAR")
    # y waits at the face until z is above the wall's safety volume.
    face, top = WALL_CENTRE[1] - WALL_HALF[1] - MARGIN, WALL_CENTRE[2] + WALL_HALF[2] + MARGIN
    crossing = int(np.argmax(x[:, 1] > face + FACE_TOL))
    assert x[crossing, 2] > top - 0.01
    # Every prediction answers a recorded state; the planner acted on them and reached the person.
    last_answered = max(int(m.tick) for m in rec["arm/command"])  # the arm runs on after the planner
    ticks = {int(m.tick) for m in rec["arm/state"] if m.tick <= last_answered}
    preds = [p for p in rec["collision"] if p.state_tick <= last_answered]
    assert {int(p.state_tick) for p in preds} <= ticks and len(preds) >= 0.95 * len(ticks)
    assert any(p.collision and p.obstacle_id == "wall" for p in preds)
    # The whole arm never came within the safety margin of the wall.
    assert min(p.min_clearance_m for p in preds) > 0.0
    (obset,) = rec["obstacles"][:1]
    assert [o.id for o in obset.obstacles] == ["wall"]
    assert rec["viz/scene"][0].entities[0].id == "obstacle/wall"
    assert task["steps"][-1]["success"]
    assert summary["task"]["planner"]["collision_stops"] >= 1


def test_an_obstacle_moved_into_the_path_mid_motion_is_avoided(tmp_path: Path) -> None:
    """The wall starts out of the way; when reach_person starts a bus message moves it between
    the arm and the person. The arm never enters its safety volume and still reaches the person."""
    import zenoh

    from services.bus.messages import Keys, ObstacleCommand, TaskEvent, encode

    away = '{id = "wall", shape = "box", position_m = [0.5, -0.6, 0.115], size_m = [0.4, 0.03, 0.23]}'
    args = up_args(tmp_path, "lockstep", f"obstacle_monitor.obstacles=[{away}]")
    port = up_port(args)
    prefix = f"feed{port}"
    up = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    moved: list[int] = []
    try:
        deadline = time.monotonic() + 60
        session = None
        while session is None and time.monotonic() < deadline:
            try:
                session = client_session(port)
            except Exception:
                time.sleep(0.2)
        assert session is not None, up.log_text()
        keys = Keys(prefix)
        cmd = ObstacleCommand(action=ObstacleCommand.MOVE, source="test")
        cmd.obstacle.id = "wall"
        cmd.obstacle.position.x, cmd.obstacle.position.y, cmd.obstacle.position.z = WALL_CENTRE
        payload, encoding = encode(cmd)
        pub = session.declare_publisher(keys.obstacles_command.key, encoding=zenoh.Encoding(encoding))

        def on_event(sample: Any) -> None:
            ev = TaskEvent()
            ev.ParseFromString(sample.payload.to_bytes())
            if ev.kind == TaskEvent.STARTED and ev.step == "reach_person" and not moved:
                moved.append(int(ev.state_tick))
                pub.put(payload)

        sub = session.declare_subscriber(keys.task_events.key, on_event)
        rc = up.wait(400)
        sub.undeclare()
        session.close()
    finally:
        up.stop()
    log = up.log_text()
    assert rc == 0, log
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    check_task(summary, log)
    assert moved, "reach_person never started"
    rec = _read(tmp_path / "run.mcap")
    sets = rec["obstacles"]
    assert np.allclose(
        [sets[-1].obstacles[0].position.x, sets[-1].obstacles[0].position.y], WALL_CENTRE[:2]
    ), "the move did not reach the monitor"
    x = _ee(rec["arm/state"])
    depth = _depth_inside(x, WALL_CENTRE, WALL_HALF + MARGIN)
    preds = [p for p in rec["collision"] if p.collision and p.obstacle_id == "wall"]
    first = min((int(p.state_tick) for p in preds), default=-1)
    assert depth.max() < FACE_TOL, (
        f"entered the safety volume by {depth.max() * 1e3:.2f} mm; moved at tick {moved[0]}, "
        f"first prediction at tick {first}"
    )
    assert preds and first >= moved[0] - 5
    assert "COLLISION_PREDICTED" in _kinds(rec["task/events"])


def test_an_obstacle_next_to_the_forearm_stops_the_arm(tmp_path: Path) -> None:
    """A sphere beside the forearm's path during grasp_spoon, far from the end effector's line:
    the whole-arm clearance asks for a protective stop, the arm rests outside the margin and the
    planner holds with the link and the obstacle named."""
    from services.bus.messages import PlannerStatus

    post = '{id = "post", shape = "sphere", position_m = [0.123, -0.183, 0.539], size_m = [0.08, 0, 0]}'
    args = [*up_args(tmp_path, "lockstep", f"obstacle_monitor.obstacles=[{post}]"), "--duration", "45"]
    up = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    try:
        rc = up.wait(120)
    finally:
        up.stop()
    log = up.log_text()
    assert rc == 0, log
    rec = _read(tmp_path / "run.mcap")
    preds = rec["collision"]
    assert any(p.protective_stop and p.clearance_obstacle_id == "post" for p in preds), log
    assert not any(p.collision for p in preds)  # the segment test never saw it
    assert min(p.min_clearance_m for p in preds) > 0.0  # never inside the margin
    last = [m for m in rec["planner/status"] if isinstance(m, PlannerStatus)][-1]
    assert last.state == PlannerStatus.HOLDING and "protective stop" in last.detail and "post" in last.detail
    v = rec["arm/state"][-1].ee_linear_velocity
    assert float(np.linalg.norm([v.x, v.y, v.z])) < 1e-3


def test_the_monitor_killed_mid_motion_brakes_the_arm_to_rest(tmp_path: Path) -> None:
    """Realtime stack; SIGKILL of the obstacle monitor while the arm moves: the planner loses the
    monitor's liveliness and brakes every axis to rest (it never moves blind)."""
    rc, log, killed_ns = kill_mid_motion(tmp_path, "obstacle_monitor")
    assert rc == 1 and "obstacle_monitor died" in log, log
    assert "obstacle monitor gone" in (tmp_path / "run" / "planner.log").read_text()
    speed = arm_speeds(tmp_path / "run.mcap")
    before = [v for t, v in speed if killed_ns - 300_000_000 < t < killed_ns]
    after = [(t - killed_ns) * 1e-9 for t, v in speed if t > killed_ns and v < 2e-3]
    assert before and max(before) > 0.05, "the arm was not moving when the monitor was killed"
    assert after and after[0] < 1.0, after[:3]
