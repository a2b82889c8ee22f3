"""Smoke test of the learner benchmark: two LASA shapes in quick mode into a temporary dir."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from benchmarks.learner import METHODS, METRICS, list_shapes, main


def test_lasa_has_thirty_shapes() -> None:
    shapes = list_shapes()
    assert len(shapes) == 30
    assert {"GShape", "Angle", "heee", "Multi_Models_4"} <= set(shapes)


@pytest.mark.slow
def test_quick_run_on_two_shapes_writes_numbers_for_both_methods(tmp_path: Path) -> None:
    assert main(["--quick", "--shapes", "Angle", "Line", "--out", str(tmp_path)]) == 0

    report = json.loads((tmp_path / "learner.json").read_text(encoding="utf-8"))
    assert list(report["shapes"]) == ["Angle", "Line"]
    for name, shape in report["shapes"].items():
        for method in METHODS:
            entry = shape["methods"][method]
            assert entry["fit_s"] > 0, (name, method)
            runs = entry["runs"]
            assert [r["demo"] for r in runs] == [0, 1, 2], (name, method)
            for run in runs:
                for metric in METRICS:
                    value = run.get(metric)
                    assert isinstance(value, float) and math.isfinite(value), (
                        name,
                        method,
                        run["demo"],
                        metric,
                        run.get("error"),
                    )
                    assert value >= 0.0
    for name, shape in report["shapes"].items():
        reproduction = {m: shape["methods"][m]["runs"][0] for m in METHODS}
        for method, run in reproduction.items():
            # the path metrics on arc-length-resampled curves: finite, and DTW <= Fréchet
            assert 0.0 <= run["dtw_arc"] <= run["frechet_arc"] < 5.0, (name, method)
        # the error budget of the default PSM: the smoothing and the learned chain alone, both
        # well below a millimetre on these 40-mm shapes (auto_tolerance 0.5 % of the range)
        for control in ("smoothed_demo", "psm_nominal"):
            assert 0.0 < shape[control]["dtw"] <= shape[control]["frechet"] < 1.0, (name, control)
        copy = shape["half_sample_copy"]
        # the control is the demo itself: the raw-sample metrics see its sampling phase,
        # the arc-length ones (almost) do not
        assert copy["dtw_arc"] < 0.05 * copy["dtw"], (name, copy)
        assert copy["frechet_arc"] < 0.05 * copy["frechet"], (name, copy)
    check = report["aggregate"]["sampling_check"]
    assert check["dtw_arc"]["shapes_compared"] == 2
    assert 0 <= check["frechet_arc"]["le_dmp50"]["psm"] <= 2
    agg = report["aggregate"]["reproduction"]["rmse"]
    for method in METHODS:
        assert agg[method]["n"] == 2
    speed = report["speed"]
    for key in ("D1", "D3"):
        assert speed["step"][key]["psm"]["median_us"] > 0
        assert speed["step"][key]["dmp10_rk4-cython"]["median_us"] > 0
        assert speed["step"][key]["ratio"] > 0
    assert speed["fit_5000x3"]["psm_s"] > 0
    assert {t["met"] for t in report["targets"]} <= {True, False}

    md = (tmp_path / "learner.md").read_text(encoding="utf-8")
    assert "## Method" in md
    assert "| Fréchet, arc-length (median) |" in md
    per_shape = md[md.index("## Per shape") : md.index("## Largest PSM")]
    for name in ("Angle", "Line"):
        # one row per condition: "PSM / DMP-10 / DMP-50" triples of numbers for each metric
        rows = [line for line in per_shape.splitlines() if line.startswith(f"| {name} |")]
        assert len(rows) == 2, rows
        for row in rows:
            triples = re.findall(r"([-+\d.e]+) / ([-+\d.e]+) / ([-+\d.e]+)", row)
            assert len(triples) == 4, row
            for triple in triples:
                for v in triple:
                    float(v)
    assert "FAIL" not in per_shape  # no failed cells on these shapes
    assert (tmp_path / "learner_lasa.png").stat().st_size > 10_000
