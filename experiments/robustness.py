"""Robustness: the same perturbations applied to the PSM and to DMPs (10 / 50 weights), side by side.

Each method learns one demonstration (the committed arm demonstrations of the feeding task and
LASA shapes) and is rolled out as a Cartesian point mass at the demonstration's dt
(:mod:`experiments.methods`), unperturbed and under: pushes against the motion, goal jumps
mid-motion, starts far from the demonstration's, noise on the goal estimate and the motion held
still for a while. Sizes are relative to the demonstration (its extent ``E`` = largest range of a
coordinate, its peak speed ``V``, its duration ``T``), so the same trial means the same on an arm
demonstration in metres and on a LASA shape in millimetres.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.learner import Demo, load_shape
from benchmarks.metrics import discrete_frechet_distance, dtw_distance
from experiments.methods import (
    METHODS,
    Hold,
    PushAgainstMotion,
    fit_method,
    load_arm_demo,
    run_method,
    write_tracks_mcap,
)
from experiments.registry import Experiment, Progress
from experiments.result import Column, ExperimentResult, Figure, Headline

ROBUST_METHODS = ("psm", "dmp10", "dmp50")
ARM_DEMOS = ("grasp_spoon", "reach_bowl", "reach_person")
LASA_SHAPES = ("GShape", "Angle", "Sshape")
QUICK_ARM, QUICK_LASA = ("reach_bowl",), ("Angle",)
#: Time limit: this many demonstration durations.
TIME_LIMIT = 2.0
#: Success: within this fraction of the extent of the goal at the time limit.
TOLERANCE = 0.02
PUSH_AT, PUSH_WINDOW = 0.4, 0.1  # fraction of T; s
PUSH_SIZES = (1.0, 2.0)  # velocity change, × V
GOAL_JUMP_AT, GOAL_JUMP = 0.5, 0.15  # fraction of T; × E
FAR_START = 0.30  # × E
GOAL_NOISE, GOAL_RATE_HZ = 0.005, 15.0  # σ per axis × E; estimates per second
HOLD_AT, HOLD_FOR = 0.3, 0.2  # fractions of T
TRIALS, QUICK_TRIALS = 3, 1  # seeded trials of the random perturbations
PERTURBATIONS = ("none", "push 1×V", "push 2×V", "goal jump", "far start", "goal noise", "held")
METRIC_POINTS = 600  # samples per curve for the path metrics


@dataclass
class Trial:
    """One perturbation of one demonstration: a start, a goal, optional disturbance / goal
    function factories (fresh state per rollout) and the goal success is judged against."""

    perturbation: str
    index: int
    x0: np.ndarray
    goal: np.ndarray
    true_goal: np.ndarray
    disturbance: Callable[[], Any] | None = None
    goal_fn: Callable[[], Any] | None = None


def _unit(rng: np.random.Generator, d: int) -> np.ndarray:
    u = rng.normal(size=d)
    return u / np.linalg.norm(u)


def make_trials(demo: Demo, rng: np.random.Generator, n_trials: int) -> list[Trial]:
    """The trials of :data:`PERTURBATIONS` for ``demo`` (sizes in the module's constants)."""
    x0, g = demo.x[0].copy(), demo.x[-1].copy()
    extent = float(np.ptp(demo.x, axis=0).max())
    speed = float(np.linalg.norm(np.gradient(demo.x, demo.t, axis=0), axis=1).max())
    T, d = demo.duration, demo.x.shape[1]
    trials = [Trial("none", 0, x0, g, g)]
    for size in PUSH_SIZES:
        trials.append(
            Trial(
                f"push {size:g}×V",
                0,
                x0,
                g,
                g,
                disturbance=lambda s=size: PushAgainstMotion(PUSH_AT * T, PUSH_WINDOW, s * speed),
            )
        )
    for i in range(n_trials):
        new_goal = g + GOAL_JUMP * extent * _unit(rng, d)
        trials.append(
            Trial(
                "goal jump",
                i,
                x0,
                g,
                new_goal,
                goal_fn=lambda ng=new_goal: lambda t: g if t < GOAL_JUMP_AT * T else ng,
            )
        )
    for i in range(n_trials):
        trials.append(Trial("far start", i, x0 + FAR_START * extent * _unit(rng, d), g, g))
    for i in range(n_trials):
        n_est = int(TIME_LIMIT * T * GOAL_RATE_HZ) + 2
        noise = rng.normal(scale=GOAL_NOISE * extent, size=(n_est, d))
        trials.append(
            Trial(
                "goal noise",
                i,
                x0,
                g,
                g,
                goal_fn=lambda nz=noise: lambda t: g + nz[min(int(t * GOAL_RATE_HZ), len(nz) - 1)],
            )
        )
    trials.append(Trial("held", 0, x0, g, g, disturbance=lambda: Hold(HOLD_AT * T, HOLD_FOR * T)))
    return trials


def _sub(x: np.ndarray) -> np.ndarray:
    return x[:: max(1, len(x) // METRIC_POINTS)]


def evaluate(run: Any, demo: Demo, trial: Trial, extent: float) -> dict[str, Any]:
    """Success, final error, time to reach the goal and path deviations of one rollout."""
    err = np.linalg.norm(run.x - trial.true_goal, axis=1)
    tol = TOLERANCE * extent
    outside = np.nonzero(err > tol)[0]
    reached = len(outside) == 0 or outside[-1] < len(err) - 1
    t_goal = (float(run.t[outside[-1] + 1]) if len(outside) else 0.0) if reached else None
    return {
        "success": bool(err[-1] <= tol),
        "final_error": float(err[-1]),
        "final_error_pct": 100.0 * float(err[-1]) / extent,
        "time_to_goal": t_goal,
        "frechet": discrete_frechet_distance(_sub(run.x), _sub(demo.x)),
        "dtw": dtw_distance(_sub(run.x), _sub(demo.x)),
    }


def run(out_dir: Path, *, seed: int, quick: bool, progress: Progress) -> ExperimentResult:
    """Run the experiment into ``out_dir`` (see the module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    rng = np.random.default_rng(seed)
    arm, lasa = (QUICK_ARM, QUICK_LASA) if quick else (ARM_DEMOS, LASA_SHAPES)
    n_trials = QUICK_TRIALS if quick else TRIALS
    demos: dict[str, tuple[Demo, str]] = {n: (load_arm_demo(n), "m") for n in arm}
    demos.update({f"LASA {n}": (load_shape(n)[0], "mm") for n in lasa})
    plan = {name: make_trials(d, rng, n_trials) for name, (d, _) in demos.items()}
    total = sum(len(v) for v in plan.values()) * len(ROBUST_METHODS)
    res = ExperimentResult(
        name="robustness",
        title=EXPERIMENT.title,
        seed=seed,
        description=EXPERIMENT.description,
        config={
            "demos": list(demos),
            "methods": [METHODS[k].label for k in ROBUST_METHODS],
            "time_limit_T": TIME_LIMIT,
            "tolerance_E": TOLERANCE,
            "push": {"at_T": PUSH_AT, "window_s": PUSH_WINDOW, "delta_v_V": list(PUSH_SIZES)},
            "goal_jump": {"at_T": GOAL_JUMP_AT, "size_E": GOAL_JUMP},
            "far_start_E": FAR_START,
            "goal_noise": {"sigma_E": GOAL_NOISE, "rate_hz": GOAL_RATE_HZ},
            "hold": {"at_T": HOLD_AT, "for_T": HOLD_FOR},
            "trials": n_trials,
            "quick": quick,
            "rollout": "Cartesian point mass at the demonstration's dt",
        },
    )
    rows: list[dict[str, Any]] = []
    examples: dict[tuple[str, str, str], Any] = {}
    tracks: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    done = 0
    for name, (demo, unit) in demos.items():
        extent = float(np.ptp(demo.x, axis=0).max())
        fitted = {k: fit_method(k, demo) for k in ROBUST_METHODS}
        for trial in plan[name]:
            for key in ROBUST_METHODS:
                r = run_method(
                    fitted[key],
                    trial.x0,
                    TIME_LIMIT * demo.duration,
                    goal=trial.goal if trial.goal_fn is None else None,
                    disturbance=trial.disturbance() if trial.disturbance else None,
                    goal_fn=trial.goal_fn() if trial.goal_fn else None,
                )
                met = evaluate(r, demo, trial, extent)
                met.update(
                    demo=name, unit=unit, perturbation=trial.perturbation, trial=trial.index, method=key
                )
                rows.append(met)
                if trial.index == 0:
                    examples[(name, trial.perturbation, key)] = (r, trial)
                scale = 1e-3 if unit == "mm" else 1.0
                x3 = np.column_stack([r.x, np.zeros((len(r.x), 3 - r.x.shape[1]))]) * scale
                slug = "".join(c if c.isalnum() else "_" for c in f"{name}/{trial.perturbation}")
                tracks[f"psm/experiments/robustness/{slug}_{trial.index}/{key}"] = (r.t, x3)
                done += 1
                progress(done, total, f"{name}: {trial.perturbation} #{trial.index}, {METHODS[key].label}")

    # ---- tables
    per_demo = res.table(
        "Per demonstration and perturbation",
        [
            Column("demo", "demonstration"),
            Column("perturbation", "perturbation"),
            Column("method", "method"),
            Column("success", "success", "of trials"),
            Column("final_error", "final error (mean)", "unit", 3),
            Column("final_error_pct", "final error", "% of E", 2),
            Column("frechet", "Fréchet to the demo", "unit", 3),
            Column("dtw", "DTW to the demo", "unit", 3),
            Column("time_to_goal", "time to the goal (mean)", "s", 2),
        ],
        note="unit: m for the arm demonstrations, mm for LASA; E = the demonstration's extent.",
    )
    for name in demos:
        for pert in PERTURBATIONS:
            for key in ROBUST_METHODS:
                sel = [
                    m for m in rows if m["demo"] == name and m["perturbation"] == pert and m["method"] == key
                ]
                if not sel:
                    continue
                ttg = [m["time_to_goal"] for m in sel if m["time_to_goal"] is not None]
                per_demo.add(
                    demo=name,
                    perturbation=pert,
                    method=METHODS[key].label,
                    success=f"{sum(m['success'] for m in sel)}/{len(sel)}",
                    final_error=float(np.mean([m["final_error"] for m in sel])),
                    final_error_pct=float(np.mean([m["final_error_pct"] for m in sel])),
                    frechet=float(np.mean([m["frechet"] for m in sel])),
                    dtw=float(np.mean([m["dtw"] for m in sel])),
                    time_to_goal=float(np.mean(ttg)) if ttg else None,
                )
    summ = res.table(
        "Per perturbation (all demonstrations)",
        [
            Column("perturbation", "perturbation"),
            Column("method", "method"),
            Column("success_rate", "success rate", "", 2),
            Column("n", "trials"),
            Column("final_error_pct", "final error (median)", "% of E", 2),
            Column("final_error_pct_max", "final error (max)", "% of E", 2),
            Column("frechet_pct", "Fréchet to the demo (median)", "% of E", 2),
            Column("time_to_goal_T", "time to the goal (median)", "× T", 2),
        ],
    )
    rates: dict[tuple[str, str], float] = {}
    for pert in PERTURBATIONS:
        for key in ROBUST_METHODS:
            sel = [m for m in rows if m["perturbation"] == pert and m["method"] == key]
            ext = {n: float(np.ptp(d.x, axis=0).max()) for n, (d, _) in demos.items()}
            rate = sum(m["success"] for m in sel) / len(sel)
            ttg_t = [
                m["time_to_goal"] / demos[m["demo"]][0].duration for m in sel if m["time_to_goal"] is not None
            ]
            rates[(pert, key)] = rate
            summ.add(
                perturbation=pert,
                method=METHODS[key].label,
                success_rate=rate,
                n=len(sel),
                final_error_pct=float(np.median([m["final_error_pct"] for m in sel])),
                final_error_pct_max=float(np.max([m["final_error_pct"] for m in sel])),
                frechet_pct=float(np.median([100 * m["frechet"] / ext[m["demo"]] for m in sel])),
                time_to_goal_T=float(np.median(ttg_t)) if ttg_t else None,
            )
    for key in ROBUST_METHODS:
        sel = [m for m in rows if m["method"] == key and m["perturbation"] != "none"]
        res.headline[f"success_{key}"] = Headline(
            f"{METHODS[key].label} success under perturbation",
            sum(m["success"] for m in sel) / len(sel),
            "",
            f"{sum(m['success'] for m in sel)}/{len(sel)} perturbed runs within {100 * TOLERANCE:g} % of E "
            f"by {TIME_LIMIT:g} T",
        )
    psm_all = [m for m in rows if m["method"] == "psm"]
    res.verdict(
        "psm_reaches_all",
        all(m["success"] for m in psm_all),
        f"PSM within {100 * TOLERANCE:g} % of E of the goal by {TIME_LIMIT:g} T in every trial",
        f"{sum(m['success'] for m in psm_all)}/{len(psm_all)}",
    )
    worse = [p for p in PERTURBATIONS if any(rates[(p, "psm")] < rates[(p, k)] for k in ROBUST_METHODS[1:])]
    res.verdict(
        "psm_not_worse",
        not worse,
        "PSM's success rate at least each DMP's for every perturbation",
        "lower for: " + (", ".join(worse) if worse else "none"),
    )

    # ---- figures and recording
    figs = _plot_examples(out_dir, demos, examples)
    res.figures += figs
    write_tracks_mcap(
        out_dir / "robustness_rollouts.mcap",
        tracks,
        {"experiment": "robustness", "seed": str(seed), "lasa_scale": "mm written as m/1000"},
    )
    res.recordings.append("robustness_rollouts.mcap")
    return res


def _plot_examples(out_dir: Path, demos: dict[str, tuple[Demo, str]], examples: dict) -> list[Figure]:
    """One figure per demonstration: a panel per perturbation, each method's first trial against the
    demonstration, in the plane of its two largest ranges."""
    import matplotlib.pyplot as plt

    figs = []
    for name, (demo, unit) in demos.items():
        dims = np.argsort(np.ptp(demo.x, axis=0))[::-1][:2]
        fig, axes = plt.subplots(2, 4, figsize=(15, 7))
        for ax, pert in zip(axes.ravel(), PERTURBATIONS, strict=False):
            ax.plot(demo.x[:, dims[0]], demo.x[:, dims[1]], color="black", lw=1.6, label="demonstration")
            for key in ROBUST_METHODS:
                r, trial = examples[(name, pert, key)]
                ax.plot(
                    r.x[:, dims[0]],
                    r.x[:, dims[1]],
                    color=METHODS[key].color,
                    lw=1.0,
                    label=METHODS[key].label,
                )
            ax.plot(*trial.true_goal[dims], marker="*", color="gold", mec="k", ms=12, ls="", label="goal")
            ax.plot(*trial.x0[dims], marker="o", color="k", ms=5, ls="", label="start")
            ax.set_title(pert, fontsize=9)
            ax.set_xlabel(f"{'xyz'[dims[0]]} [{unit}]")
            ax.set_ylabel(f"{'xyz'[dims[1]]} [{unit}]")
            ax.grid(alpha=0.3)
        axes.ravel()[-1].axis("off")
        axes.ravel()[0].legend(fontsize=7)
        fig.suptitle(f"{name}: one perturbed rollout per method")
        fig.tight_layout()
        fname = "robustness_" + "".join(c if c.isalnum() else "_" for c in name) + ".png"
        fig.savefig(out_dir / fname, dpi=120)
        plt.close(fig)
        figs.append(Figure(fname, f"{name}: PSM, DMP-10 and DMP-50 under each perturbation (first trial)"))
    return figs


EXPERIMENT = Experiment(
    name="robustness",
    title="Robustness: PSM and DMP under the same perturbations",
    run=run,
    description=(
        "PSM, DMP-10 and DMP-50 learn feeding demonstrations and LASA shapes and are rolled out "
        "(Cartesian point mass) under pushes against the motion, goal jumps, far starts, goal noise "
        "and a hold; success within 2 % of the extent by twice the demonstration's duration."
    ),
)
