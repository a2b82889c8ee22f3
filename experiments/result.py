"""What an experiment run leaves behind: tables of metrics with units, headline figures, plots.

:class:`ExperimentResult` is written as ``result.json`` in the run's folder and read back by the
report writer, so a report can be rebuilt without running the experiment again.

    res = ExperimentResult(name="feeding", title="Feeding task goal adaptation", seed=0)
    tab = res.table("Per sub-task", [Column("step", "sub-task"), Column("err", "final error", "mm")])
    tab.add(step="grasp_spoon", err=1.2)
    res.headline["success"] = Headline("success rate", 1.0, "", "45/45 adaptations")
    res.figures.append(Figure("grid.png", "Final positions on the 3x3 grids"))
    res.write(out_dir)                  # out_dir/result.json
    ExperimentResult.read(out_dir)
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["Column", "ExperimentResult", "Figure", "Headline", "Table", "json_ready"]

RESULT_FILE = "result.json"


@dataclass
class Column:
    """A table column: ``key`` in each row, ``label`` as printed, ``unit`` ("" when none), and
    ``digits`` after the decimal point for floats."""

    key: str
    label: str
    unit: str = ""
    digits: int = 3


@dataclass
class Table:
    """Rows of metrics: each row maps column keys to numbers, strings or booleans (None: n/a)."""

    title: str
    columns: list[Column]
    rows: list[dict[str, Any]] = field(default_factory=list)
    note: str = ""

    def add(self, **row: Any) -> None:
        """Append a row; every key must be a column's."""
        unknown = set(row) - {c.key for c in self.columns}
        if unknown:
            raise KeyError(f"table {self.title!r}: no column {sorted(unknown)}")
        self.rows.append(row)


@dataclass
class Figure:
    """A plot file of the run's folder and what it shows."""

    file: str
    caption: str


@dataclass
class Headline:
    """One headline figure: ``label``, ``value`` in ``unit``, and a short ``detail``."""

    label: str
    value: float | int | str | bool | None
    unit: str = ""
    detail: str = ""


@dataclass
class ExperimentResult:
    """One experiment run. ``config``: every parameter that made the run (JSON-ready);
    ``verdicts``: named pass/fail checks against the paper or a target, with the reason."""

    name: str
    title: str
    seed: int
    description: str = ""
    config: dict[str, Any] = field(default_factory=dict)
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    headline: dict[str, Headline] = field(default_factory=dict)
    verdicts: dict[str, dict[str, Any]] = field(default_factory=dict)
    recordings: list[str] = field(default_factory=list)
    duration_s: float = 0.0

    def table(self, title: str, columns: list[Column], note: str = "") -> Table:
        """A new table, appended to :attr:`tables`."""
        tab = Table(title, columns, note=note)
        self.tables.append(tab)
        return tab

    def verdict(self, key: str, ok: bool, target: str, measured: str) -> None:
        """Record a check: ``target`` as stated (e.g. "within 2 %"), ``measured`` as found."""
        self.verdicts[key] = {"ok": bool(ok), "target": target, "measured": measured}

    def write(self, out_dir: Path) -> Path:
        """Write ``out_dir/result.json`` (the folder is created); returns its path."""
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / RESULT_FILE
        path.write_text(json.dumps(json_ready(asdict(self)), indent=2, allow_nan=False) + "\n")
        return path

    @classmethod
    def read(cls, out_dir: Path) -> ExperimentResult:
        """Read ``out_dir/result.json``."""
        raw = json.loads((out_dir / RESULT_FILE).read_text())
        tables = [
            Table(t["title"], [Column(**c) for c in t["columns"]], t["rows"], t.get("note", ""))
            for t in raw.pop("tables", [])
        ]
        figures = [Figure(**f) for f in raw.pop("figures", [])]
        headline = {k: Headline(**h) for k, h in raw.pop("headline", {}).items()}
        return cls(tables=tables, figures=figures, headline=headline, **raw)


def json_ready(obj: Any) -> Any:
    """``obj`` with numpy scalars/arrays as Python numbers/lists and non-finite floats as None."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_ready(v) for v in obj]
    if hasattr(obj, "tolist"):
        return json_ready(obj.tolist())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj
