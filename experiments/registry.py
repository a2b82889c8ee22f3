"""The experiments by name: each module exposes ``EXPERIMENT``, an :class:`Experiment`.

Modules are imported only when an experiment is run, so listing them stays fast.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.result import ExperimentResult

__all__ = ["EXPERIMENT_MODULES", "Experiment", "Progress", "load", "run"]

#: Experiment name -> module, in the order ``psm experiments --all`` runs them.
EXPERIMENT_MODULES: dict[str, str] = {
    "feeding": "experiments.feeding",
    "collision": "experiments.collision",
    "cylinder": "experiments.cylinder",
    "robustness": "experiments.robustness",
    "scale": "experiments.scale",
}

#: ``progress(done, total, label)``: called as trials finish (the CLI draws a progress bar).
Progress = Callable[[int, int, str], None]


@dataclass(frozen=True)
class Experiment:
    """An experiment: ``run(out_dir, seed=..., quick=..., progress=...)`` runs it into
    ``out_dir`` (plots, recordings) and returns its result (the caller writes ``result.json``).
    ``quick`` runs a reduced set of trials with the same code (tests, smoke runs)."""

    name: str
    title: str
    run: Callable[..., ExperimentResult]
    description: str = ""


def load(name: str) -> Experiment:
    """The experiment called ``name``; ValueError naming the known ones otherwise."""
    if name not in EXPERIMENT_MODULES:
        raise ValueError(f"no experiment {name!r}; known: {', '.join(EXPERIMENT_MODULES)}")
    module: Any = importlib.import_module(EXPERIMENT_MODULES[name])
    exp = module.EXPERIMENT
    assert isinstance(exp, Experiment) and exp.name == name
    return exp


def run(name: str, out_root: Path, *, seed: int = 0, quick: bool = False,
        progress: Progress | None = None) -> ExperimentResult:
    """Run experiment ``name`` into ``out_root/name`` and write its ``result.json``."""
    import time

    exp = load(name)
    out_dir = out_root / name
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    res = exp.run(out_dir, seed=seed, quick=quick, progress=progress or (lambda *_: None))
    res.duration_s = time.perf_counter() - t0
    res.write(out_dir)
    return res
