"""The pure parts of the obstacle benchmark (benchmarks/obstacles.py): scenes, the inflated peer
shapes and capsules, statistics, the decimation arithmetic, verdicts and the report; plus a
quick smoke run (slow). No timed assertions."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.obstacles import (
    capsule_pose,
    cpu_fraction,
    decimation_table,
    inflated_dims,
    main,
    make_obstacles,
    make_segments,
    ratio,
    recommend_decimation,
    stop_margin_m,
    summarize,
    verdict,
)
from psm.obstacles import compile_obstacles, validate_obstacle


def test_scenes_are_deterministic_and_in_the_workspace() -> None:
    a, b = make_obstacles(30, seed=1), make_obstacles(30, seed=1)
    assert [o.id for o in a] == [o.id for o in b]
    assert all(np.array_equal(x.position, y.position) for x, y in zip(a, b, strict=True))
    assert {o.shape for o in a} == {"box", "sphere", "cylinder"}
    assert all(math.hypot(o.position[0], o.position[1]) > 0.3 for o in a)
    moving = make_obstacles(200, seed=2, moving_fraction=0.2, speed=0.3)
    speeds = np.array([np.linalg.norm(o.velocity) for o in moving])
    assert 0.1 < np.mean(speeds > 0) < 0.3 and np.allclose(speeds[speeds > 0], 0.3)
    segs = make_segments(10, seed=3)
    assert segs.shape == (10, 2, 3) and np.array_equal(segs, make_segments(10, seed=3))


def test_inflated_peer_shapes_match_the_compiled_inflation() -> None:
    m = 0.02
    box = validate_obstacle("b", "box", (0, 0, 0), size=(0.1, 0.2, 0.3))
    cyl = validate_obstacle("c", "cylinder", (0, 0, 0), size=(0.1, 0.0, 0.3))
    sph = validate_obstacle("s", "sphere", (0, 0, 0), size=(0.1, 0.0, 0.0))
    c = compile_obstacles([box, cyl, sph], m)
    kind, dims = inflated_dims(box, m)
    assert kind == "box" and np.allclose(np.array(dims) / 2, c.boxes.half_extents[0])
    kind, dims = inflated_dims(cyl, m)
    assert kind == "cylinder" and dims[0] == pytest.approx(c.cylinders.radius[0])
    assert dims[1] / 2 == pytest.approx(c.cylinders.half_height[0])
    assert inflated_dims(sph, m) == ("sphere", (pytest.approx(c.spheres.radius[0]),))


def test_capsule_lies_on_the_segment() -> None:
    s, g = np.array([0.1, 0.2, 0.3]), np.array([0.5, -0.2, 0.9])
    R, c, L = capsule_pose(s, g)
    assert L == pytest.approx(np.linalg.norm(g - s))
    np.testing.assert_allclose(c + R @ [0, 0, L / 2], g, atol=1e-12)
    np.testing.assert_allclose(c - R @ [0, 0, L / 2], s, atol=1e-12)
    _, c0, L0 = capsule_pose(s, s)
    assert L0 == 0.0 and np.array_equal(c0, s)


def test_statistics_ratio_and_verdict() -> None:
    st = summarize([1e-6] * 99 + [1e-4])
    assert st["p50_us"] == pytest.approx(1.0) and st["n"] == 100
    assert st["mean_us"] == pytest.approx((99 + 100) / 100)
    assert ratio(2.0, 4.0) == 0.5 and ratio(1.0, 0.0) == math.inf
    assert verdict(50.0, 50.0) == "met" and verdict(50.1, 50.0) == "missed"


def test_decimation_arithmetic() -> None:
    # 200 µs every tick at 500 Hz is 10 % of a core; every 4th tick 2.5 %.
    assert cpu_fraction(200.0, 500.0, 1) == pytest.approx(0.10)
    assert cpu_fraction(200.0, 500.0, 4) == pytest.approx(0.025)
    # 1 m/s over 5 ticks of 2 ms is 1 cm; braking from 1 m/s at 10 m/s² takes 5 cm.
    assert stop_margin_m(1.0, 10.0, 0.002, 5) == pytest.approx(0.06)
    table = decimation_table(300.0, rate_hz=500.0, v=1.0, a=10.0, decimations=(1, 2, 5))
    assert [r["N"] for r in table] == [1, 2, 5]
    assert table[0]["cpu"] == pytest.approx(0.15) and table[1]["period_ms"] == pytest.approx(4.0)
    assert recommend_decimation(table, target_cpu=0.20, headroom=2.0) == 2
    assert recommend_decimation(table, target_cpu=0.20, headroom=1.0) == 1
    assert recommend_decimation(decimation_table(1e5, decimations=(1, 2)), 0.2) == 2  # none fits: largest


@pytest.mark.slow
def test_quick_run_writes_the_report(tmp_path: Path) -> None:
    assert main(["--quick", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "obstacles.json").read_text(encoding="utf-8"))
    assert [c["obstacles"] for c in report["segments"]] == [1, 10, 100]
    assert [c["obstacles"] for c in report["clearance"]] == [1, 10, 100]
    for case in report["clearance"]:
        assert case["broad_vs_brute_max_abs_m"] < 1e-9
    md = (tmp_path / "obstacles.md").read_text(encoding="utf-8")
    assert "## Targets" in md and "segment test, 100 obstacles" in md
