"""The main job end to end: ``psm up`` with the shipped feeding stack (router, recorder, arm,
synthetic camera, goal tracker, planner) in lockstep over real Zenoh on loopback runs the
feeding task to completion, stops by itself and leaves the summary and a consistent recording.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from stack_helpers import check_task, up

pytestmark = pytest.mark.integration


@pytest.mark.parametrize("start_pose", ["ready", "middle"])  # not "neutral": docs/arm.md, "Known limits"
def test_the_feeding_task_completes_through_the_stack(tmp_path: Path, start_pose: str) -> None:
    from services.bus.log import read_log
    from services.bus.messages import ArmCommand, ArmState, TaskEvent

    rc, log, summary = up(tmp_path, f'arm.start_pose="{start_pose}"')
    assert rc == 0, log
    check_task(summary, log)
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
    rc, log, summary = up(tmp_path, "goal_tracker.synthetic.hidden_s=[[13.2, 14.7]]")
    assert rc == 0, log
    task = check_task(summary, log)
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
