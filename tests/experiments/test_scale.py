"""The ``scale`` experiment's quick run: its result's structure and the properties it measures
(fit cost grows with segments, two cells on one router complete with their own keys only and
the same trajectory). Starts two stacks on loopback."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments import registry
from experiments.result import ExperimentResult
from experiments.scale import cell_processes, linear_law, toml_value

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_linear_law_recovers_a_line() -> None:
    law = linear_law([1, 2, 4, 8], [3.0, 5.0, 9.0, 17.0])  # 1 + 2 x
    assert law["intercept"] == pytest.approx(1.0) and law["slope"] == pytest.approx(2.0)
    assert law["r2"] == pytest.approx(1.0)


def test_cell_processes_disable_the_router_and_parse_as_toml() -> None:
    import tomllib

    procs = tomllib.loads(f"v = {toml_value(cell_processes(['camera']))}")["v"]
    enabled = {p["name"]: p.get("enabled", True) for p in procs}
    assert enabled["router"] is False and enabled["camera"] is False and enabled["planner"] is True
    with pytest.raises(ValueError, match="no process"):
        cell_processes(["nope"])


def test_quick_run(tmp_path: Path) -> None:
    seen: list[tuple[int, int]] = []
    res = registry.run("scale", tmp_path, seed=0, quick=True, progress=lambda d, t, _l: seen.append((d, t)))
    out = tmp_path / "scale"
    back = ExperimentResult.read(out)
    assert back.name == "scale" and seen[-1][0] == seen[-1][1]
    for fig in res.figures:
        assert (out / fig.file).stat().st_size > 10_000
    for rec in res.recordings:
        assert (out / rec).exists()
    # Fit cost grows with the number of segments (same run, interleaved): 2 vs ~46 per dimension.
    seg = res.config["raw"]["segment_sweep"]["rows"]
    assert seg[-1]["segments"] > 10 * seg[0]["segments"]
    assert seg[-1]["fit"]["median_ms"] > seg[0]["fit"]["median_ms"]
    assert all(r["done"] for r in seg)
    dim = res.config["raw"]["dimension_sweep"]["rows"]
    assert [r["dim"] for r in dim] == [1, 3, 7]
    assert dim[-1]["psm_step"]["median_us"] > dim[0]["psm_step"]["median_us"]
    # Two cells: both complete, each recording holds only its own prefix, same trajectory.
    pair = res.config["cells"]["pairs"][0]
    assert [c["prefix"] for c in pair] == ["cell_a", "cell_b"]
    for c in pair:
        assert c["success"] and c["exit_code"] == 0
        assert c["messages"] > 1000 and c["foreign_messages"] == 0 and c["other_cell_messages"] == 0
    assert res.verdicts["no_cross_talk"]["ok"] and res.verdicts["both_cells_complete"]["ok"]
    assert res.verdicts["same_trajectory"]["ok"], res.verdicts["same_trajectory"]
    assert pair[1]["vs_reference"]["last_tick"] >= pair[1]["task_end_tick"]
