"""The pure parts of the feeding benchmark (benchmarks/feeding.py): the grids, the moved scene
and its task file, the camera-frame face centre, the criteria, aggregation and targets on
synthetic numbers, the joint-limit attribution; and one grid point in process end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.feeding import (
    CARTESIAN_ACCEL_LIMIT_MPS2,
    adaptation,
    aggregate,
    away_from,
    face_centre_m,
    grid,
    limited_by_step,
    live_figures,
    main,
    moved_config,
    moved_scene,
    run_adaptations,
    scene_toml,
    targets,
)
from services.bus.config import read_toml
from services.goal_tracker.geometry import Transform
from services.stack import DEFAULT_STACK, load_stack
from services.tasks.feeding import DEFAULT_FEEDING_CONFIG, load_feeding, parse_feeding

SCENE = {"neutral": [0.4, 0.0, 0.4], "spoon": [0.5, -0.25, 0.06], "bowl": [0.55, 0.2, 0.1],
         "person": [0.35, 0.5, 0.45], "cylinder_contact": [0.45, -0.1, 0.04]}


def test_the_grid_has_nine_points_of_the_spacing() -> None:
    g = grid(0.05)
    assert len(g) == 9 == len(set(g))
    assert {a for a, _ in g} == {b for _, b in g} == {-0.05, 0.0, 0.05}
    assert g[4] == (0.0, 0.0) and g[8] == (0.05, 0.05)


def test_a_grid_point_moves_spoon_and_bowl_in_the_table_plane_and_the_person_in_y_z() -> None:
    m = moved_scene(SCENE, (0.05, -0.05))
    assert m["spoon"] == pytest.approx([0.55, -0.30, 0.06])
    assert m["bowl"] == pytest.approx([0.60, 0.15, 0.10])
    assert m["person"] == pytest.approx([0.35, 0.55, 0.40])
    assert m["neutral"] == SCENE["neutral"] and m["cylinder_contact"] == SCENE["cylinder_contact"]


def test_the_moved_task_file_parses_back_to_the_moved_scene(tmp_path: Path) -> None:
    text = DEFAULT_FEEDING_CONFIG.read_text()
    moved = {k: v for k, v in moved_scene(SCENE, (-0.05, 0.05)).items()
             if k in ("spoon", "bowl", "person")}
    out = scene_toml(text, moved)
    path = tmp_path / "feeding.toml"
    path.write_text(out)
    cfg, shipped = load_feeding(path), load_feeding()
    for k, v in moved.items():
        assert getattr(cfg.scene, k) == pytest.approx(v)
    assert cfg.scene.neutral == shipped.scene.neutral and cfg.task == shipped.task
    assert out.count("\n") == text.count("\n") and "# grasp point of the spoon handle" in out
    with pytest.raises(ValueError, match=r"scene\.plate"):
        scene_toml(text, {"plate": [0.0, 0.0, 0.0]})


def test_the_face_centre_puts_the_tracked_mouth_on_the_person() -> None:
    sec = load_stack(DEFAULT_STACK).configs["goal_tracker"].goal_tracker  # type: ignore[attr-defined]
    t, rpy, offset = sec.mount.translation_m, sec.mount.rpy_deg, sec.face.offset_m
    # The shipped scene: the stack file's own face centre.
    shipped = load_feeding().scene.person
    assert face_centre_m(shipped, t, rpy, offset) == pytest.approx(sec.synthetic.centre_m, abs=1e-9)
    # By hand (camera at (0.35, 0, 0.45) looking along base +y): x = bx - 0.35, y = -(bz - 0.45), z = by.
    person = [0.35, 0.55, 0.40]
    c = face_centre_m(person, t, rpy, offset)
    mouth_cam = [person[0] - 0.35, -(person[2] - 0.45), person[1]]
    assert c == pytest.approx(np.asarray(mouth_cam) - np.asarray(offset), abs=1e-9)
    # And back through the mount.
    back = Transform.from_rpy(t, rpy).apply(np.asarray(c) + np.asarray(offset))
    assert back == pytest.approx(person, abs=1e-9)


def _step(**kw: Any) -> dict[str, Any]:
    base = {"step": "reach_bowl", "success": True, "outcome": "reached", "position_error_m": 0.004,
            "velocity_error_mps": 0.02, "duration_s": 3.0, "peak_speed_mps": 0.25,
            "demo_peak_speed_mps": 0.24,
            "peak_speed_ratio": 1.04, "peak_accel_mps2": 1.9, "extra_away_m": [0.0, 0.002, 0.0]}
    return {**base, **kw}


def test_the_criteria_of_one_adaptation() -> None:
    assert adaptation(_step())["all_ok"]
    assert not adaptation(_step(success=False))["all_ok"]
    a = adaptation(_step(peak_speed_ratio=1.51))
    assert not a["speed_ok"] and not a["all_ok"] and a["complete"]
    assert adaptation(_step(peak_speed_ratio=1.5))["speed_ok"]
    a = adaptation(_step(extra_away_m=[0.0, 0.0101, 0.0]))
    assert not a["away_ok"] and not a["all_ok"]
    assert adaptation(_step(extra_away_m=[0.01, 0.01, 0.01]))["away_ok"]
    assert not adaptation(_step(peak_accel_mps2=CARTESIAN_ACCEL_LIMIT_MPS2 + 0.1))["accel_ok"]
    assert not adaptation(_step(peak_speed_ratio=None))["speed_ok"]


def test_a_step_never_reached_counts_as_not_completed() -> None:
    rows = run_adaptations({"steps": [_step(step="grasp_spoon")]}, ["grasp_spoon", "back_to_neutral"])
    assert [r["complete"] for r in rows] == [True, False]
    assert rows[1]["outcome"] == "not reached" and not rows[1]["all_ok"]
    assert [r["complete"] for r in run_adaptations(None, ["a"])] == [False]


def test_aggregate_and_targets_on_synthetic_adaptations() -> None:
    rows = [{**adaptation(_step(step=s, peak_speed_ratio=r, extra_away_m=e)), "point": i}
            for i, (s, r, e) in enumerate([
                ("reach_bowl", 1.1, [0.0, 0.0, 0.0]),
                ("reach_bowl", 1.6, [0.0, 0.0, 0.0]),
                ("scoop", 1.0, [0.0, 0.0, 0.012]),
            ])]
    a = aggregate(rows)
    assert a["n"] == 3 and a["complete"] == 3 and a["all_ok"] == 1
    assert a["worst_peak_speed_ratio"] == 1.6 and a["worst_ratio_at"] == "reach_bowl @ point 1"
    assert a["worst_extra_away_m"] == 0.012 and a["worst_extra_away_axis"] == "z"
    t = targets(rows, 3, clamp_free_runs=None, runs=3)
    assert t["complete"]["ok"] and not t["peak_speed"]["ok"] and not t["extra_away"]["ok"]
    assert t["accel"]["ok"] and t["all"]["value"] == 1 and not t["all"]["ok"]
    assert t["joint_limits"]["ok"] and t["joint_limits"]["limited_ticks_by_step"] is None
    assert not targets(rows, 4, clamp_free_runs=2, runs=3)["complete"]["ok"]
    assert not targets(rows, 3, clamp_free_runs=2, runs=3)["joint_limits"]["ok"]
    assert math.isnan(aggregate([])["worst_peak_speed_ratio"])


def test_ticks_at_the_joint_limits_are_attributed_to_their_step() -> None:
    commanded = {k: [1.0, 0.0, 0.0] for k in range(10)}
    measured = {k + 1: [1.0, 0.0, 0.0] for k in range(10)}
    measured[4] = [0.5, 0.0, 0.0]  # the command of tick 3 was clamped
    measured[8] = [1.0, 0.2, 0.0]  # and that of tick 7
    measured[9] = [1.0, 0.04, 0.0]  # within the threshold
    out = limited_by_step(measured, commanded, [(0, "a"), (5, "b")])
    assert out == {"a": 1, "b": 1}


def test_distance_away_from_the_true_goal_and_the_live_figures() -> None:
    goal = [0.0, 0.5, 0.0]
    # y: starts 0.10 from the goal, goes to 0.12 (2 cm away), then reaches it; x never moves away.
    pos = [[0.0, 0.40, 0.0], [0.0, 0.38, 0.0], [0.0, 0.45, 0.0], [0.0, 0.5, 0.0]]
    assert away_from(pos, goal) == pytest.approx([0.0, 0.02, 0.0])
    assert all(math.isnan(v) for v in away_from(np.zeros((0, 3)), goal))
    run = {"person_m": [0.35, 0.5, 0.45],
           "recording": {"live_away_true_m": [0.0, 0.02, 0.001], "live_goal_mean_m": [0.35, 0.49, 0.45],
                         "live_goal_std_m": [0.001, 0.008, 0.001], "live_goal_samples": 120}}
    lv = live_figures(run, {"demo_away_m": [0.0, 0.015, 0.002]})
    assert lv["extra_away_true_m"] == pytest.approx([0.0, 0.005, 0.0])
    assert lv["estimate_bias_m"] == pytest.approx([0.0, -0.01, 0.0])
    assert "extra_away_true_m" not in live_figures(run, {})


def test_options_are_applied_to_every_step() -> None:
    cfg = moved_config((0.05, 0.0), {})
    assert all(s.controller == {} for s in cfg.task.steps)
    assert cfg.scene.spoon == pytest.approx((0.55, -0.25, 0.06))
    shipped = parse_feeding(read_toml(DEFAULT_FEEDING_CONFIG))
    assert moved_config((0.0, 0.0)).task == shipped.task


def test_one_grid_point_in_process_writes_the_report(tmp_path: Path) -> None:
    assert main(["--quick", "--in-process", "--no-options", "--point", "4", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "feeding.json").read_text())
    assert len(res["runs"]) == 1 and len(res["runs"][0]["adaptations"]) == 5
    assert res["targets"]["all"]["value"] == 5, res["targets"]
    md = (tmp_path / "feeding.md").read_text()
    assert "5 of 5" in md and "## Per sub-task" in md and "## Every adaptation" in md
