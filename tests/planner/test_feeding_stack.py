"""The main job end to end: ``psm up`` with the shipped feeding stack (router, recorder, arm,
synthetic camera, goal tracker, planner) in lockstep over real Zenoh on loopback runs the
feeding task to completion, stops by itself and leaves the summary and a consistent recording.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.supervisor import ManagedProcess, free_port, psm_argv

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
STACK = ROOT / "configs" / "stack.toml"
STEPS = ["grasp_spoon", "back_to_neutral", "reach_bowl", "scoop", "reach_person"]


def _up_args(tmp_path: Path, clock: str, *sets: str) -> list[str]:
    """``psm up`` of the shipped stack on a free port and prefix, everything written under
    ``tmp_path``, plus ``--set`` of each of ``sets``."""
    port = free_port()
    run = tmp_path / "run"
    values = [
        f'clock="{clock}"',
        f'prefix="feed{port}"',
        f'router.listen=["tcp/127.0.0.1:{port}"]',
        f'zenoh.connect=["tcp/127.0.0.1:{port}"]',
        f'stack.run_dir="{run}"',
        f'recorder.output="{tmp_path / "run.mcap"}"',
        f'planner.summary_file="{run / "task.json"}"',
        f'arm.stats_file="{run / "arm.json"}"',
        f'planner.cache_dir="{ROOT / "out" / "models"}"',
        *sets,
    ]
    return ["up", str(STACK), "--no-live", *(a for v in values for a in ("--set", v))]


def _up(tmp_path: Path, *sets: str, timeout_s: float = 240.0) -> tuple[int, str, dict[str, Any]]:
    run = tmp_path / "run"
    args = _up_args(tmp_path, "lockstep", *sets)
    up = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    try:
        rc = up.wait(timeout_s)
    finally:
        up.stop()
    log = up.log_text()
    summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else {}
    return (-1 if rc is None else rc), log, summary


def _check_task(summary: dict[str, Any], log: str) -> dict[str, Any]:
    task = summary.get("task")
    assert task is not None, log
    assert task["success"], json.dumps(task, indent=1)[:3000]
    assert [s["step"] for s in task["steps"]] == STEPS
    for s in task["steps"]:
        assert s["success"] and s["position_error_m"] <= 0.01, s
    assert summary["reason"] == "planner finished", summary["reason"]
    return task


@pytest.mark.parametrize("start_pose", ["ready", "neutral"])
def test_the_feeding_task_completes_through_the_stack(tmp_path: Path, start_pose: str) -> None:
    from services.bus.log import read_log
    from services.bus.messages import ArmCommand, ArmState, TaskEvent

    rc, log, summary = _up(tmp_path, f'arm.start_pose="{start_pose}"')
    assert rc == 0, log
    _check_task(summary, log)
    assert "task feeding: 5/5 steps, succeeded" in log and "recording:" in log
    states: set[int] = set()
    commands: list[int] = []
    topics: set[str] = set()
    events: list[TaskEvent] = []
    for key, msg, _t in read_log(tmp_path / "run.mcap"):
        topics.add(key.split("/", 1)[1])
        if isinstance(msg, ArmState):
            states.add(int(msg.tick))
        elif isinstance(msg, ArmCommand):
            commands.append(int(msg.tick))
        elif isinstance(msg, TaskEvent):
            events.append(msg)
    for topic in (
        "arm/state",
        "arm/command",
        "arm/transforms",
        "camera/cam0/image",
        "goals/person",
        "planner/status",
        "task/events",
        "gripper/command",
        "status/arm",
        "status/planner",
        "status/goal_tracker",
    ):
        assert topic in topics, sorted(topics)
    # Every command answers a recorded state, and (lockstep) every state while the planner ran
    # is answered (the arm steps on by its watchdog after the planner has exited).
    assert commands and set(commands) <= states
    during = {t for t in states if t <= max(commands)}
    assert len(set(commands)) >= 0.99 * len(during)
    for topic in ("collision", "obstacles", "viz/scene", "planner/goal", "status/obstacle_monitor"):
        assert topic in topics, sorted(topics)
    kinds = [TaskEvent.Kind.Name(e.kind) for e in events]
    assert kinds.count("STEP_COMPLETED") == 5 and kinds[-1] == "COMPLETED", kinds[-10:]
    assert "GRIPPER" in kinds


def test_the_person_lost_holds_the_motion_and_it_resumes(tmp_path: Path) -> None:
    from services.bus.log import read_log
    from services.bus.messages import PlannerStatus, TaskEvent

    # reach_person starts at about 12.7 s of sim time; the face is hidden for 1.5 s in it.
    rc, log, summary = _up(tmp_path, "goal_tracker.synthetic.hidden_s=[[13.2, 14.7]]")
    assert rc == 0, log
    task = _check_task(summary, log)
    assert task["steps"][-1]["hold_s"] > 0.5
    kinds, holding_speeds = [], []
    for _key, msg, _t in read_log(tmp_path / "run.mcap"):
        if isinstance(msg, TaskEvent):
            kinds.append((TaskEvent.Kind.Name(msg.kind), msg.step))
        elif (
            isinstance(msg, PlannerStatus)
            and msg.state == PlannerStatus.HOLDING
            and msg.step == "reach_person"
        ):
            holding_speeds.append(msg.speed_mps)
    assert ("GOAL_LOST", "reach_person") in kinds and ("RESUMED", "reach_person") in kinds, kinds
    assert kinds.index(("GOAL_LOST", "reach_person")) < kinds.index(("RESUMED", "reach_person"))
    # While holding the arm comes to rest.
    assert holding_speeds and min(holding_speeds) < 0.01, holding_speeds


def up_port(args: list[str]) -> int:
    """The router port of ``psm up`` arguments from :func:`_up_args`."""
    listen = next(a for a in args if a.startswith("router.listen="))
    return int(listen.rsplit(":", 1)[1].rstrip('"]'))


def client_session(port: int) -> Any:
    """A Zenoh client session on the router at 127.0.0.1:``port`` (multicast off)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def kill_mid_motion(tmp_path: Path, process: str) -> tuple[int | None, str, int]:
    """``psm up`` of the shipped stack in realtime; SIGKILL of ``process`` once the planner reports
    the arm moving faster than 0.1 m/s (grasp_spoon under way). Returns the supervisor's exit
    code, its log and the kill time (wall clock = the realtime stack's clock) [ns]."""
    import os
    import signal
    import time

    from services.bus.messages import Keys, PlannerStatus

    args = _up_args(tmp_path, "realtime")
    port = up_port(args)
    up = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    speed: list[float] = []
    try:
        deadline = time.monotonic() + 120
        pid = None
        while time.monotonic() < deadline and pid is None:
            text = up.log_text()
            if "started planner (pid " in text:  # the last process: the stack is up
                for line in text.splitlines():
                    if line.startswith(f"started {process} (pid "):
                        pid = int(line.rsplit("(pid ", 1)[1].rstrip(")"))
            time.sleep(0.1)
        assert pid is not None, up.log_text()
        session = client_session(port)
        sub = session.declare_subscriber(
            Keys(f"feed{port}").planner_status.key,
            lambda sample: speed.append(PlannerStatus.FromString(sample.payload.to_bytes()).speed_mps),
        )
        while time.monotonic() < deadline and not (speed and speed[-1] > 0.1):
            time.sleep(0.01)
        sub.undeclare()
        session.close()
        assert speed and speed[-1] > 0.1, up.log_text()
        killed_ns = time.time_ns()
        os.kill(pid, signal.SIGKILL)
        rc = up.wait(60)
    finally:
        up.stop()
    return rc, up.log_text(), killed_ns


def arm_speeds(recording: Path) -> list[tuple[int, float]]:
    """``(stamp_ns, end-effector speed [m/s])`` of every recorded arm state."""
    from services.bus.log import read_log
    from services.bus.messages import ArmState

    out = []
    for _k, msg, _t in read_log(recording):
        if isinstance(msg, ArmState):
            v = msg.ee_linear_velocity
            out.append((int(msg.stamp_ns), float(np.linalg.norm([v.x, v.y, v.z]))))
    return out


def test_the_planner_killed_mid_motion_leaves_the_arm_braked_to_rest(tmp_path: Path) -> None:
    """Realtime stack; SIGKILL of the planner while the arm moves: the arm brakes to rest at
    once (the planner's liveliness token is watched; else its watchdog), the stack reports it."""
    rc, log, killed_ns = kill_mid_motion(tmp_path, "planner")
    assert rc == 1 and "planner died" in log, log
    speed = arm_speeds(tmp_path / "run.mcap")
    before = [v for t, v in speed if killed_ns - 300_000_000 < t < killed_ns]
    after = [(t - killed_ns) * 1e-9 for t, v in speed if t > killed_ns and v < 1e-3]
    assert before and max(before) > 0.05, "the arm was not moving when the planner was killed"
    assert after and after[0] < 0.5, after[:3]  # at rest within half a second
    assert all(v < 1e-3 for t, v in speed if (t - killed_ns) * 1e-9 > after[0] + 0.05)
