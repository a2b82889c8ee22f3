"""The report writer: escaping, n/a, units, digits, verdicts, figures; and the CLI paths."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments import plots
from experiments.report import ReportEntry, find_results, format_value, write_report
from experiments.result import Column, ExperimentResult, Figure, Headline


def _result(folder: Path) -> ExperimentResult:
    import numpy as np

    res = ExperimentResult(name="demo", title="A <b>bold</b> & title", seed=3,
                           description="Uses `k_max` & <script>alert(1)</script>.", config={"n": 2})
    tab = res.table("Errors | per trial", [Column("name", "trial"), Column("err", "final error", "mm", 1),
                                           Column("ok", "ok"), Column("n", "samples")])
    tab.add(name="a|b", err=1.23456, ok=True, n=5)
    tab.add(name="c", err=None, ok=False, n=None)
    res.headline["rate"] = Headline("success rate", 0.5, "", "1/2")
    res.verdict("error small", True, "< 2 mm", "1.2 mm")
    res.verdict("all ok", False, "2/2", "1/2")
    t = np.linspace(0, 1, 20)
    plots.plot_trajectories(folder / "p.png", [plots.Curve("c", t, t[:, None])], dims=("q",))
    res.figures += [Figure("p.png", "a <plot>"), Figure("gone.png", "missing one")]
    res.write(folder)
    return res


def test_format_value() -> None:
    assert format_value(None) == "n/a" and format_value(float("nan"), 2) == "n/a"
    assert format_value(1.23456, 2) == "1.23" and format_value(2.0, 0) == "2"
    assert format_value(True) == "yes" and format_value(7) == "7" and format_value(float("inf")) == "inf"
    assert format_value([1.0, None], 1) == "1.0, n/a"


def test_markdown_and_html(tmp_path: Path) -> None:
    folder = tmp_path / "demo"
    res = _result(folder)
    md, page = write_report([ReportEntry(ExperimentResult.read(folder), folder)], tmp_path / "rep")
    text, doc = md.read_text(), page.read_text()
    # units in the headers, digits per column, None as n/a, pipes escaped in Markdown cells
    assert "| trial | final error [mm] | ok | samples |" in text
    assert "| a\\|b | 1.2 | yes | 5 |" in text and "| c | n/a | no | n/a |" in text
    assert "<th>final error [mm]</th>" in doc and '<td class="num">1.2</td>' in doc
    # HTML escaping of every text; code spans kept
    assert "<script>" not in doc and "&lt;script&gt;alert(1)&lt;/script&gt;" in doc
    assert "A &lt;b&gt;bold&lt;/b&gt; &amp; title" in doc and "<code>k_max</code>" in doc
    # verdicts with target and measured, pass and fail marked
    assert '<tr class="fail"><td>all ok</td><td class="result">FAIL</td><td>2/2</td><td>1/2</td></tr>' in doc
    assert "| all ok | **FAIL** | 2/2 | 1/2 |" in text and "1 pass, 1 fail." in text
    # the figure outside the report folder is copied in and linked relatively; the missing one noted
    assert (tmp_path / "rep" / "figures" / "demo" / "p.png").stat().st_size > 1000
    assert 'src="figures/demo/p.png"' in doc and "gone.png</code> is missing" in doc
    assert "http" not in doc.replace("http-equiv", "") and "<link" not in doc
    assert json.loads(text.split("```json")[1].split("```")[0]) == {"n": 2}
    assert res.title in text


def test_find_results_and_the_report_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from services.cli import main

    _result(tmp_path / "b")
    _result(tmp_path / "a")
    assert find_results(tmp_path) == [tmp_path / "a", tmp_path / "b"]
    assert main(["report", str(tmp_path)]) == 0
    assert (tmp_path / "report.html").exists() and 'src="a/p.png"' in (tmp_path / "report.html").read_text()
    assert main(["report", str(tmp_path / "nothing")]) == 2
    assert "psm report: error:" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["report", str(tmp_path / "empty")]) == 2
    assert "no result.json" in capsys.readouterr().err


def test_experiments_cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                         capsys: pytest.CaptureFixture[str]) -> None:
    from experiments import registry
    from services.cli import main

    monkeypatch.setattr(registry, "EXPERIMENT_MODULES", {"tiny": "tiny_experiment", "ghost": "no_such_mod"})
    assert main(["experiments", "--list"]) == 0
    out = capsys.readouterr().out
    assert "tiny" in out and "ghost" in out and "(not installed)" in out
    cases = ((["experiments"], "name an experiment"), (["experiments", "nope"], "no experiment 'nope'"),
             (["experiments", "ghost"], "not installed"))
    for argv, why in cases:
        assert main([*argv, "--out", str(tmp_path)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("psm experiments: error:") and why in err
    assert main(["experiments", "tiny", "--quick", "--seed", "4", "--out", str(tmp_path)]) == 0
    res = ExperimentResult.read(tmp_path / "tiny")
    assert res.seed == 4 and len(res.tables[0].rows) == 2 and res.duration_s > 0
    doc = (tmp_path / "report.html").read_text()
    assert 'src="tiny/sine.png"' in doc and "Tiny &lt;test&gt; experiment" in doc
