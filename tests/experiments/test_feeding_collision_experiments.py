"""Quick runs of the feeding and collision experiments (the same code as the full runs, fewer
trials): the result's structure and what the runs must show physically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments import registry
from experiments.result import ExperimentResult


def _check_structure(res: ExperimentResult, out: Path) -> None:
    back = ExperimentResult.read(out)
    assert back.name == res.name and back.tables and back.headline and back.verdicts
    for fig in res.figures:
        assert (out / fig.file).stat().st_size > 10_000, fig.file
    for rec in res.recordings:
        assert (out / rec).stat().st_size > 0, rec
    for tab in res.tables:
        keys = {c.key for c in tab.columns}
        assert tab.rows and all(set(r) <= keys for r in tab.rows), tab.title


def test_quick_feeding_reaches_every_moved_goal(tmp_path: Path) -> None:
    from services.bus.log import read_log
    from services.bus.messages import ArmState, TaskEvent

    seen: list[tuple[int, int, str]] = []
    res = registry.run("feeding", tmp_path, seed=0, quick=True,
                       progress=lambda d, t, s: seen.append((d, t, s)))
    out = tmp_path / "feeding"
    _check_structure(res, out)
    assert seen and seen[-1][0] == seen[-1][1]
    rows = next(t for t in res.tables if t.title == "Every adaptation").rows
    steps = ["grasp_spoon", "back_to_neutral", "reach_bowl", "scoop", "reach_person"]
    assert [r["step"] for r in rows] == steps
    for r in rows:  # every sub-task reaches its goal within its 1 cm / 30 mm/s tolerance
        assert r["success"] and r["final_error_mm"] <= 10.0 and r["final_speed_mm_s"] <= 30.0, r
        assert 0.0 < r["peak_accel_mps2"] < 13.0 and 0.5 < r["peak_speed_ratio"] < 1.5, r
    # Steps with a dwell or a follow phase end at rest on the goal.
    by = {r["step"]: r for r in rows}
    assert by["grasp_spoon"]["final_error_mm"] < 1.0 and by["reach_person"]["final_error_mm"] < 3.0
    assert res.headline["success_rate"].value == 1.0
    assert all(v["ok"] for v in res.verdicts.values()), res.verdicts
    # The recording is a stack-like run: one arm state per tick and the task's events.
    ticks, kinds = [], []
    for key, msg, _t in read_log(out / res.recordings[0]):
        if isinstance(msg, ArmState):
            assert key == "psm/arm/state"
            ticks.append(int(msg.tick))
        elif isinstance(msg, TaskEvent):
            kinds.append(TaskEvent.Kind.Name(msg.kind))
    assert np.array_equal(ticks, np.arange(len(ticks)))
    assert kinds.count("STEP_COMPLETED") == 5 and kinds[-1] == "COMPLETED"


def test_quick_collision_keeps_clear_of_the_wall_and_slows_the_lateral_motion(tmp_path: Path) -> None:
    res = registry.run("collision", tmp_path, seed=0, quick=True, progress=lambda *_: None)
    _check_structure(res, tmp_path / "collision")
    (row,) = res.tables[0].rows
    assert row["run"] == "y465_h230" and row["success"]
    assert row["arm_clearance_m"] > 0.0 and row["ee_clearance_m"] > 0.0
    assert row["safety_volume_m"] > -1e-4  # the end effector stops on the safety volume's face
    assert 0.0 < row["held_ratio"] < 0.5  # y slowed while the stop held it below the wall's top
    assert row["slowdown_ratio"] < 0.5  # below the top, released or not: the paper's wall
    assert abs(row["release_m"]) < 2e-3  # the paper's wall: y released as z reaches the top
    assert row["peak_vy_ratio"] > 0.5  # and resumed once it had cleared it
    assert row["collision_stops"] >= 1 and row["extra_s"] > 0.0
    free = res.tables[1].rows[0]
    assert free["free_ee_clearance_m"] < 0.18  # without the monitor the path runs through the safety volume
    assert all(v["ok"] for v in res.verdicts.values()), res.verdicts
