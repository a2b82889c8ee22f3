"""A throwaway experiment for the CLI tests (never registered in EXPERIMENT_MODULES)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments import plots
from experiments.registry import Experiment, Progress
from experiments.result import Column, ExperimentResult, Figure, Headline


def run(out_dir: Path, *, seed: int, quick: bool, progress: Progress) -> ExperimentResult:
    """Three (quick: two) seeded trials of a sine; one plot, one table, one verdict."""
    rng = np.random.default_rng(seed)
    n = 2 if quick else 3
    res = ExperimentResult(name="tiny", title="Tiny <test> experiment", seed=seed, config={"trials": n})
    tab = res.table("Trials", [Column("trial", "trial"), Column("amp", "amplitude", "m", 2)])
    t = np.linspace(0.0, 1.0, 50)
    amps = []
    for i in range(n):
        amp = float(rng.uniform(0.1, 0.2))
        amps.append(amp)
        tab.add(trial=i, amp=amp)
        progress(i + 1, n, f"trial {i + 1}")
    plots.plot_trajectories(out_dir / "sine.png", [plots.Curve("sine", t, np.sin(t)[:, None] * amps[0])],
                            dims=("q",))
    res.figures.append(Figure("sine.png", "a sine"))
    res.headline["amp"] = Headline("largest amplitude", max(amps), "m")
    res.verdict("amplitude below 0.2 m", max(amps) < 0.2, "< 0.2 m", f"{max(amps):.3f} m")
    return res


EXPERIMENT = Experiment("tiny", "Tiny <test> experiment", run, "A sine.")
