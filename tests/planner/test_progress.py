"""A restarted planner resumes its task (services/planner/progress.py, TaskRunner.resume): the
progress file's round trip and checks, and in process a task "killed" in its third step,
the arm braked to rest, then resumed by a new runner from the arm's state: the two completed
steps are not redone and the task completes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.planner.models import TaskModels
from services.planner.progress import (
    PROGRESS_FORMAT,
    ProgressError,
    TaskProgress,
    read_progress,
    write_progress,
)
from services.planner.sequencer import TaskRunner
from services.tasks.feeding import FeedingConfig

DT_NS = 2_000_000


def _progress(feeding: FeedingConfig, **kw: object) -> TaskProgress:
    base: dict[str, object] = dict(
        task=feeding.task.name, steps=list(feeding.task.sequence), next_index=1,
        arm_origin_ns=1_700_000_000_000_000_000, dt_ns=DT_NS, tick=1000,
        completed=[{"start_ns": 1, "end_ns": 2, "summary": {"step": "grasp_spoon", "success": True}}],
    )
    base.update(kw)
    return TaskProgress(**base)  # type: ignore[arg-type]


def test_the_progress_file_round_trips_and_knows_its_arm_run(feeding: FeedingConfig, tmp_path: Path) -> None:
    path = tmp_path / "sub" / "progress.json"
    assert read_progress(path, feeding.task) is None  # no file: start from the first step
    p = _progress(feeding)
    write_progress(path, p)
    assert json.loads(path.read_text())["format"] == PROGRESS_FORMAT
    assert [f.name for f in path.parent.iterdir()] == ["progress.json"]  # no temporary left
    back = read_progress(path, feeding.task)
    assert back is not None and back.next_index == 1 and back.completed == p.completed
    origin = p.arm_origin_ns
    assert back.same_arm_run(origin + 2000 * DT_NS, 2000, DT_NS, 500_000)
    assert not back.same_arm_run(origin + 900 * DT_NS, 900, DT_NS, 500_000)  # before the record
    assert not back.same_arm_run(origin + 5_000_000 + 2000 * DT_NS, 2000, DT_NS, 500_000)  # another run
    assert not back.same_arm_run(0, 0, DT_NS, 500_000)  # a lockstep arm started again
    assert not back.same_arm_run(origin + 2000 * 1_000_000, 2000, 1_000_000, 500_000)  # another period


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("{", "not JSON"),
        ('{"format": 99}', "not a progress record"),
        (json.dumps({"format": PROGRESS_FORMAT, "task": "other", "steps": []}), "a record of task 'other'"),
    ],
)
def test_an_unusable_progress_file_is_one_line(
    feeding: FeedingConfig, tmp_path: Path, text: str, reason: str
) -> None:
    path = tmp_path / "progress.json"
    path.write_text(text)
    with pytest.raises(ProgressError, match=reason) as exc:
        read_progress(path, feeding.task)
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)


def test_an_inconsistent_record_is_refused(feeding: FeedingConfig, tmp_path: Path) -> None:
    path = tmp_path / "progress.json"
    write_progress(path, _progress(feeding, next_index=3))  # three done, one record
    with pytest.raises(ProgressError, match="next step 3 with 1 completed"):
        read_progress(path, feeding.task)


def test_a_task_killed_in_its_third_step_resumes_there_from_the_arm_at_rest(
    feeding: FeedingConfig, models: TaskModels
) -> None:
    from services.arm.config import ArmSection
    from services.arm.sim import ArmSim
    from services.robot.protocol import Command, CommandMode

    section = ArmSection(dt_s=DT_NS * 1e-9, start_pose="ready")
    sim = ArmSim(section.load_robot(), section)
    dt = DT_NS * 1e-9

    def runner() -> TaskRunner:
        scene = feeding.scene.positions()
        return TaskRunner(feeding.task, scene, models.models, models.profiles, models.demos)

    def drive(r: TaskRunner, until: object, max_ticks: int) -> list[object]:
        events: list[object] = []
        for _ in range(max_ticks):
            snap = sim.snapshot()
            if snap.tick % 15 == 0:  # the person, still, at a camera's rate
                r.update_goal("person", feeding.scene.positions()["person"], snap.time_ns)
            ee = snap.ee
            out = r.step(snap.time_ns, ee.position, ee.linear_velocity, ee.quat_xyzw, dt, tick=snap.tick,
                         measured_accel=ee.linear_acceleration)
            events.extend(r.drain_events())
            if until(r, snap):  # type: ignore[operator]
                return events
            sim.submit(Command(snap.tick, CommandMode.CARTESIAN, out.acceleration, out.orientation,
                               out.angular_velocity))
            sim.step()
        raise AssertionError("the runner did not get there")

    first = runner()
    drive(first, lambda r, s: r.index == 2 and r.speed > 0.1, 20_000)  # reach_bowl under way
    done = first.completed_steps(2)
    assert [d["summary"]["step"] for d in done] == ["grasp_spoon", "back_to_neutral"]
    # The planner is gone: the arm brakes (no command) to rest.
    sim.drop_command()
    for _ in range(500):
        sim.step()
    rest = sim.snapshot()
    assert float(np.abs(rest.dq).max()) < 1e-9
    second = runner()
    second.resume(2, done)
    events = drive(second, lambda r, s: r.state in ("DONE", "FAULT"), 40_000)
    summary = second.summary()
    assert summary["success"], summary
    assert [s["step"] for s in summary["steps"]] == list(feeding.task.sequence)
    assert summary["steps"][:2] == [d["summary"] for d in done]  # reported as they were
    assert summary["resumes"] == [{"at_step": 2, "tick": rest.tick}]
    kinds = [(e.kind, e.step) for e in events]  # type: ignore[attr-defined]
    assert kinds[:2] == [("STARTED", ""), ("STARTED", "reach_bowl")]  # the task's, then the step's
    assert "resumed at step 3/5 (reach_bowl)" in events[0].detail  # type: ignore[attr-defined]
    assert ("GRIPPER", "grasp_spoon") not in kinds  # the spoon is not grasped again
    assert [k for k in kinds if k[0] == "STEP_COMPLETED"] == [
        ("STEP_COMPLETED", s) for s in ("reach_bowl", "scoop", "reach_person")]
    # From rest, the resumed step keeps the demonstration's pace.
    assert summary["steps"][2]["peak_speed_ratio"] <= 1.5


def test_a_resumed_task_that_was_done_holds_the_arm(feeding: FeedingConfig, models: TaskModels) -> None:
    r = TaskRunner(feeding.task, feeding.scene.positions(), models.models, models.profiles, models.demos)
    n = len(feeding.task.steps)
    done = [{"start_ns": i, "end_ns": i + 1, "summary": {"step": s.name, "success": True}}
            for i, s in enumerate(feeding.task.steps)]
    r.resume(n, done)
    x, v = np.array([0.4, 0.0, 0.4]), np.zeros(3)
    out = r.step(10, x, v, np.array([1.0, 0.0, 0.0, 0.0]), 0.002, tick=5)
    assert r.state == "DONE" and np.allclose(out.acceleration, 0.0)
    assert r.summary()["success"] and "all 5 steps were completed" in r.drain_events()[0].detail
    with pytest.raises(RuntimeError):
        r.resume(n, done)
