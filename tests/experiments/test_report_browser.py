"""The HTML report in a real headless Chromium: every image loads, no console error.

The report is made by ``psm report`` from small synthetic results and from a real recording of
the feeding stack (``psm up --clock lockstep``, bounded by ``--duration``), so the recording
report (trajectories, phase space with PSTF lines, time synchronisation, per-step table) is
tested end to end. Without Chromium the test skips, except under ``PSM_REQUIRE_BROWSER=1``
(``.ci/run``), where it fails.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from cdp_browser import chromium_path, open_page

from experiments.result import Column, ExperimentResult, Figure, Headline

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


def _require_browser() -> None:
    if chromium_path() is None:
        if os.environ.get("PSM_REQUIRE_BROWSER") == "1":
            pytest.fail("PSM_REQUIRE_BROWSER=1 but no Chromium on PATH (apt-get install chromium)")
        pytest.skip("no Chromium on PATH")


def _recording(tmp: Path) -> Path:
    """A lockstep run of the shipped feeding stack, recorded; at most 60 s of wall clock."""
    from services.supervisor import ManagedProcess, free_port, psm_argv

    port = free_port()
    run = tmp / "run"
    sets = [
        'clock="lockstep"', f'prefix="rep{port}"', f'router.listen=["tcp/127.0.0.1:{port}"]',
        f'zenoh.connect=["tcp/127.0.0.1:{port}"]', f'stack.run_dir="{run}"',
        f'planner.summary_file="{run / "task.json"}"', f'planner.progress_file="{run / "progress.json"}"',
        f'arm.stats_file="{run / "arm.json"}"', f'planner.cache_dir="{ROOT / "out" / "models"}"',
    ]
    mcap = tmp / "run.mcap"
    args = ["up", str(ROOT / "configs" / "stack.toml"), "--no-live", "--duration", "60",
            "--record", str(mcap), *(a for v in sets for a in ("--set", v))]
    proc = ManagedProcess("up", psm_argv(args), tmp / "up.log", cwd=ROOT)
    try:
        rc = proc.wait(120.0)
    finally:
        proc.stop()
    assert rc is not None and mcap.exists(), proc.log_text()[-3000:]
    return mcap


def _synthetic(folder: Path) -> None:
    import numpy as np

    from experiments import plots

    res = ExperimentResult(name="synthetic", title="Synthetic <check> & co", seed=1,
                           description="Two trials.\n\nA `code` span.", config={"trials": 2})
    tab = res.table("Trials", [Column("trial", "trial"), Column("err", "error", "mm", 2)])
    tab.add(trial=1, err=0.5)
    tab.add(trial=2, err=None)
    res.headline["err"] = Headline("worst error", 0.5, "mm")
    res.verdict("error below 1 mm", True, "< 1 mm", "0.50 mm")
    res.verdict("every trial measured", False, "2/2", "1/2")
    t = np.linspace(0, 1, 100)
    X = np.c_[t, t**2, np.sin(t)]
    plots.plot_trajectories(folder / "t.png", [plots.Curve("run", t, X)])
    plots.plot_path(folder / "p.png", [plots.Curve("run", t, X)], points={"goal": X[-1]})
    res.figures += [Figure("t.png", "per dimension"), Figure("p.png", "3-D & top view")]
    res.write(folder)


def test_the_report_loads_in_chromium(tmp_path: Path) -> None:
    _require_browser()
    mcap = _recording(tmp_path)
    _synthetic(tmp_path / "results" / "synthetic")
    out = tmp_path / "report"
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", "report", str(mcap), str(tmp_path / "results"),
         "--out", str(out), "--cache-dir", str(ROOT / "out" / "models")],
        capture_output=True, text=True, timeout=240, cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rec = ExperimentResult.read(out / "run")
    steps = rec.tables[0].rows
    assert steps and steps[0]["step"] == "grasp_spoon", steps
    for row in steps:
        assert row["duration"] > 0 and row["peak_speed"] > 0.05
        if row["outcome"] == "reached":
            assert row["final_error"] < 10.0
        # the reconstructed time to go is the planner's own (the same controller on the same states)
        assert row["te_diff"] is None or row["te_diff"] < 1e-3, row
    assert len(rec.figures) == 4 * len(steps)

    page = open_page(out / "report.html")
    assert page.errors == []
    expected = len(rec.figures) + 2
    assert len(page.images) == expected, page.images
    broken = [(src, ok, w) for src, ok, w in page.images if not ok or w <= 0]
    assert broken == []
    assert page.tables >= 6 and page.title == "Experiments"


def test_the_check_sees_a_broken_page(tmp_path: Path) -> None:
    """The checker itself: a missing image and a console error are reported."""
    _require_browser()
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><html><head><meta charset="utf-8"><title>bad</title></head><body>'
                   '<img src="missing.png"><script>console.error("boom")</script></body></html>')
    page = open_page(bad)
    assert page.images == [("missing.png", True, 0)]
    assert any("boom" in e for e in page.errors), page.errors
