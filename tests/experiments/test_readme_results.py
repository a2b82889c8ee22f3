"""scripts/readme_results.py: the README's results block is written from result.json files."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

from experiments.result import ExperimentResult, Figure, Headline

ROOT = Path(__file__).resolve().parents[2]


def _script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("readme_results", ROOT / "scripts" / "readme_results.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_block_holds_each_results_figures_verdicts_and_plots(tmp_path: Path) -> None:
    rr = _script()
    results = tmp_path / "out" / "experiments"
    res = ExperimentResult(name="cylinder", title="Cylinder | strike", seed=3, duration_s=12.4)
    res.headline["landed"] = Headline("PSM landed", "9/9", "runs", "worst release 0.5 % off")
    res.headline["error"] = Headline("worst final error", 9.987716111982698, "mm", "")
    res.verdict("speed", True, "within 2 %", "0.5 %")
    res.verdict("dmp", False, "DMP fails", "DMP lands 9/9")
    res.figures.append(Figure("cylinder_phase.png", "Phase plots"))
    res.write(results / "cylinder")
    (results / "cylinder" / "cylinder_phase.png").write_bytes(b"\x89PNG fake")
    readme = tmp_path / "README.md"
    readme.write_text(f"# Title\n\nbefore\n\n{rr.BEGIN}\nold text\n{rr.END}\n\nafter\n")

    block = rr.results_block(results, tmp_path / "docs" / "img", tmp_path)
    rr.update_readme(readme, block)
    text = readme.read_text()

    assert text.startswith("# Title\n\nbefore\n\n") and text.endswith("\n\nafter\n")
    assert "old text" not in text
    assert "**Cylinder \\| strike** (seed 3, 12 s): 1/2 verdicts pass." in text
    assert "| PSM landed | 9/9 runs | worst release 0.5 % off |" in text
    assert "| worst final error | 9.988 mm |  |" in text  # as the report prints it
    assert "Not met: dmp (target DMP fails; measured DMP lands 9/9)." in text
    # The experiments that did not run say so; the plot is copied and linked relative to the README.
    assert "* **feeding**: no result in" in text
    assert (tmp_path / "docs" / "img" / "cylinder_cylinder_phase.png").read_bytes() == b"\x89PNG fake"
    assert "![Phase plots](docs/img/cylinder_cylinder_phase.png)" in text


def test_the_readme_has_the_markers() -> None:
    rr = _script()
    text = (ROOT / "README.md").read_text()
    assert text.count(rr.BEGIN) == 1 and text.count(rr.END) == 1
    assert text.index(rr.BEGIN) < text.index(rr.END)
