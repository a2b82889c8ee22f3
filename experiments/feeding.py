"""Experiment 1 of the paper (§IV-B, Fig. 7): the feeding task's goal adaptation on 3×3 grids.

The feeding task of ``configs/feeding.toml`` (grasp_spoon → back_to_neutral → reach_bowl → scoop →
reach_person) is run once per point of a 3×3 grid; each run moves the spoon, the bowl and the
person at once, so its five sub-tasks adapt to their moved goals: 9 runs × 5 sub-tasks = the
paper's 45 trajectory adaptations. The paper gives no spacing; the grid is
:func:`benchmarks.feeding.grid` with ``h = 5 cm``: point ``(a, b)``, ``a, b ∈ {−h, 0, +h}``, puts
the spoon and the bowl at ``(x + a, y + b)`` on the table and the person's mouth at
``(y + a, z + b)`` in the plane facing the robot (:func:`benchmarks.feeding.moved_scene`).
back_to_neutral always ends at the neutral position; scoop ends at the bowl + its offset.

Every run is the stack's control loop in process (:func:`experiments.harness.run_in_process`:
the planner's ``TaskRunner``, the arm simulation and the obstacle monitor as configured in
``configs/stack.toml``), which is a lockstep stack run bit for bit (docs/experiments.md,
"In-process harness"). The person's goal is live as in the stack: the true mouth position plus
Gaussian noise of the goal tracker's measured spread (:data:`PERSON_JITTER_M`, base frame, one
draw per 30 Hz camera frame, from the run's seed).

Metrics per adaptation (the planner's step report, and the trace at the step's last tick):
``success`` (reached within the step's tolerances, 1 cm and 30 mm/s, after its dwell);
``error`` [mm]: the runner's distance to the goal in use when it judged the step done;
``final error`` [mm]: ``|x_end − goal|`` at the step's last tick against the true goal (the
person's true mouth, not the noisy estimate); ``final speed error`` [mm/s]: ``|v_end|`` (every goal
is still); ``duration`` [s]; ``peak speed`` [m/s] and its ratio to the demonstration's peak;
``peak acceleration`` [m/s²]: the largest norm of the arm's measured end-effector acceleration.

Recordings: ``feeding_p<i>.mcap`` per grid point, laid out as a stack recording under the prefix
``psm`` (``psm/arm/state``, ``psm/arm/command``, ``psm/planner/goal``, ``psm/task/events``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from experiments.registry import Experiment, Progress
from experiments.result import Column, ExperimentResult, Figure, Headline

SPACING_M = 0.05
#: The goal tracker's estimate of a still mouth: standard deviation per base axis [m] (a lockstep
#: stack run of the shipped stack with the synthetic face still, docs/experiments.md).
PERSON_JITTER_M = (0.0004, 0.0017, 0.00035)
CAMERA_RATE_HZ = 30.0
#: The grid points of a quick run: (+h, +h), the corner farthest from the demonstrations.
QUICK_POINTS = (8,)
#: Targets: peak speed / the demonstration's; the Panda's Cartesian acceleration limit [m/s²];
#: the steps' position tolerance [m].
PEAK_SPEED_RATIO_TARGET = 1.5
CARTESIAN_ACCEL_LIMIT_MPS2 = 13.0
GRIDS = {  # sub-task -> (scene position moved, plane axes)
    "grasp_spoon": ("spoon", (0, 1)),
    "reach_bowl": ("bowl", (0, 1)),
    "scoop": ("bowl", (0, 1)),
    "reach_person": ("person", (1, 2)),
}


def person_goals(person: Sequence[float], jitter_m: Sequence[float], rng: np.random.Generator
                 ) -> Callable[[float], dict[str, tuple[np.ndarray, bool]]]:
    """The person's live goal: ``person (3,)`` [m] plus a fresh Gaussian draw of standard deviation
    ``jitter_m (3,)`` [m] per call (one camera frame)."""
    p = np.asarray(person, dtype=float)
    s = np.asarray(jitter_m, dtype=float)

    def goals(_t: float) -> dict[str, tuple[np.ndarray, bool]]:
        return {"person": (p + s * rng.standard_normal(3), True)}

    return goals


def true_goals(cfg: Any) -> dict[str, np.ndarray]:
    """Each step's true goal [m]: its scene position plus its offset."""
    scene = cfg.scene.positions()
    return {s.name: np.asarray(scene[s.goal], dtype=float) + np.asarray(s.offset_m, dtype=float)
            for s in cfg.task.steps}


def adaptations(res: Any, cfg: Any, point: int) -> list[dict[str, Any]]:
    """One row per sub-task of an in-process run (see the module docstring for the metrics)."""
    tr = res.trace
    t_ns = np.round(tr["t"] * 1e9).astype(np.int64)
    goals = true_goals(cfg)
    steps = {s["step"]: s for s in res.summary["steps"]}
    rows = []
    for rep in res.runner.reports:
        s = steps[rep.name]
        end = int(np.searchsorted(t_ns, rep.end_ns)) if rep.end_ns else len(t_ns) - 1
        end = min(end, len(t_ns) - 1)
        x, v = tr["x"][end], tr["v"][end]
        ratio = s.get("peak_speed_ratio")
        rows.append({
            "point": point, "step": rep.name, "success": bool(s["success"]),
            "error_mm": 1e3 * float(s["position_error_m"]),
            "final_error_mm": 1e3 * float(np.linalg.norm(x - goals[rep.name])),
            "final_speed_mm_s": 1e3 * float(np.linalg.norm(v)),
            "duration_s": s["duration_s"], "peak_speed_mps": float(s["peak_speed_mps"]),
            "peak_speed_ratio": None if ratio is None else float(ratio),
            "peak_accel_mps2": float(s["peak_accel_mps2"]),
            "goal": goals[rep.name].tolist(), "final": x.tolist(),
        })
    return rows


def _aggregate(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    def mx(key: str) -> float:
        vals = [r[key] for r in rows if r[key] is not None]
        return max(vals) if vals else math.nan

    durs = [r["duration_s"] for r in rows if r["duration_s"] is not None]
    return {
        "n": len(rows), "ok": sum(r["success"] for r in rows),
        "success_rate": sum(r["success"] for r in rows) / len(rows) if rows else math.nan,
        "max_error_mm": mx("error_mm"), "max_final_error_mm": mx("final_error_mm"),
        "mean_final_error_mm": float(np.mean([r["final_error_mm"] for r in rows])),
        "max_final_speed_mm_s": mx("final_speed_mm_s"),
        "mean_duration_s": float(np.mean(durs)) if durs else math.nan,
        "max_duration_s": max(durs) if durs else math.nan,
        "max_peak_speed_mps": mx("peak_speed_mps"), "max_peak_speed_ratio": mx("peak_speed_ratio"),
        "max_peak_accel_mps2": mx("peak_accel_mps2"),
    }


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------


def plot_grids(rows: Sequence[dict[str, Any]], path: Path, tolerance_m: float,
               centres: dict[str, np.ndarray], spacing_m: float) -> None:
    """Final positions on each grid against the goals (top; the grid's 9 goals around its centre
    ``centres[step] (3,)`` [m], spacing ``spacing_m``) and final − goal [mm] (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(GRIDS)
    fig, axes = plt.subplots(2, len(names), figsize=(4.2 * len(names), 8.0), dpi=120)
    labels = "xyz"
    points = sorted({r["point"] for r in rows})
    colours = plt.cm.viridis(np.linspace(0.0, 0.9, max(1, len(points))))
    for j, step in enumerate(names):
        _scene, (i0, i1) = GRIDS[step]
        sub = [r for r in rows if r["step"] == step]
        top, bot = axes[0, j], axes[1, j]
        c0 = centres[step]
        for a in (-spacing_m, 0.0, spacing_m):
            for b in (-spacing_m, 0.0, spacing_m):
                top.plot(c0[i0] + a, c0[i1] + b, "+", color="0.7", ms=12)
        for r in sub:
            c = colours[points.index(r["point"])]
            g, f = np.asarray(r["goal"]), np.asarray(r["final"])
            top.plot(g[i0], g[i1], "kx", ms=9, mew=1.5)
            top.plot(f[i0], f[i1], "o", color=c, ms=5, mfc="none")
            d = 1e3 * (f - g)
            bot.plot(d[i0], d[i1], "o", color=c, label=f"point {r['point']}")
        top.plot([], [], "kx", label="goal")
        top.plot([], [], "o", color="grey", mfc="none", label="final position")
        top.set(title=f"{step}: 3×3 grid", xlabel=f"{labels[i0]} [m]", ylabel=f"{labels[i1]} [m]")
        pad = spacing_m + 0.03
        top.set(xlim=(c0[i0] - pad, c0[i0] + pad), ylim=(c0[i1] - pad, c0[i1] + pad))
        top.set_aspect("equal")
        top.plot([], [], "+", color="0.7", label="grid")
        top.legend(fontsize=7, loc="upper right")
        tol = 1e3 * tolerance_m
        a = np.linspace(0, 2 * np.pi, 100)
        bot.plot(tol * np.cos(a), tol * np.sin(a), "k--", lw=0.8, label=f"tolerance {tol:.0f} mm")
        bot.axhline(0, color="grey", lw=0.5)
        bot.axvline(0, color="grey", lw=0.5)
        bot.set(title=f"{step}: final − goal", xlabel=f"Δ{labels[i0]} [mm]", ylabel=f"Δ{labels[i1]} [mm]")
        bot.set_aspect("equal", adjustable="datalim")
        bot.legend(fontsize=6, loc="best", ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_trajectories(runs: Sequence[tuple[int, Any]], step: str, demo: tuple[np.ndarray, np.ndarray],
                      path: Path) -> None:
    """``step``'s trajectories of every grid point against its demonstration: the path in the
    grid's plane (left) and x, y, z over the time in the step (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _scene, (i0, i1) = GRIDS[step]
    fig, (ax, axt) = plt.subplots(1, 2, figsize=(12.0, 5.0), dpi=120)
    colours = plt.cm.viridis(np.linspace(0.0, 0.9, max(1, len(runs))))
    t_d, X_d = demo
    ax.plot(X_d[:, i0], X_d[:, i1], "k--", lw=2, label="demonstration")
    for c, (point, res) in zip(colours, runs, strict=True):
        idx = next(i for i, r in enumerate(res.runner.reports) if r.name == step)
        mask = res.trace["step"] == idx
        x, t = res.trace["x"][mask], res.trace["t"][mask]
        ax.plot(x[:, i0], x[:, i1], color=c, lw=1, label=f"point {point}")
        ax.plot(x[-1, i0], x[-1, i1], "o", color=c, ms=4)
        for d, ls in zip(range(3), ("-", "--", ":"), strict=True):
            axt.plot(t - t[0], x[:, d], ls, color=c, lw=0.8)
    for d, ls in zip(range(3), ("-", "--", ":"), strict=True):
        axt.plot(t_d - t_d[0], X_d[:, d], ls, color="k", lw=2, label=f"demonstration {'xyz'[d]}")
    ax.set(title=f"{step}: paths on the 3×3 grid vs the demonstration", xlabel=f"{'xyz'[i0]} [m]",
           ylabel=f"{'xyz'[i1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7)
    axt.set(title=f"{step}: x (solid), y (dashed), z (dotted) over time", xlabel="time in the step [s]",
            ylabel="position [m]")
    axt.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# The experiment
# --------------------------------------------------------------------------------------------


def run(out_dir: Path, *, seed: int, quick: bool, progress: Progress) -> ExperimentResult:
    """Run the grid (``quick``: :data:`QUICK_POINTS` only) into ``out_dir``."""
    from benchmarks.feeding import grid, moved_config
    from experiments.harness import TraceWriter, feeding_models, robot_model, run_in_process, stack_settings
    from services.learn_cli import load_demonstration
    from services.planner.models import demo_path
    from services.tasks.feeding import load_feeding

    out_dir.mkdir(parents=True, exist_ok=True)
    base = load_feeding()
    models = feeding_models(base.task)
    settings = stack_settings()
    rng = np.random.default_rng(seed)
    joint_names = list(robot_model(settings).joint_names)
    offsets = grid(SPACING_M)
    points = [(i, offsets[i]) for i in (QUICK_POINTS if quick else range(len(offsets)))]
    sequence = list(base.task.sequence)
    total = len(points)
    rows: list[dict[str, Any]] = []
    runs: list[tuple[int, Any]] = []
    recordings: list[str] = []
    per_point: list[dict[str, Any]] = []
    for done, (i, off) in enumerate(points, start=1):
        cfg = moved_config(off)
        t0 = time.perf_counter()
        res = run_in_process(cfg, models, settings,
                             goals=person_goals(cfg.scene.person, PERSON_JITTER_M, rng))
        wall = time.perf_counter() - t0
        rows += adaptations(res, cfg, i)
        runs.append((i, res))
        name = f"feeding_p{i}.mcap"
        with TraceWriter(out_dir / name) as w:
            w.metadata("psm.experiment", {"experiment": "feeding", "point": str(i),
                                          "offset_m": f"{off[0]:+.3f},{off[1]:+.3f}", "seed": str(seed)})
            w.write_run("psm", res, joint_names)
        recordings.append(name)
        s = res.summary
        per_point.append({"point": i, "a_cm": 100 * off[0], "b_cm": 100 * off[1],
                          "success": bool(s["success"]),
                          "steps_ok": s["steps_succeeded"], "duration_s": s["duration_s"], "wall_s": wall})
        progress(done, total, f"grid point {i} ({100 * off[0]:+.0f}, {100 * off[1]:+.0f}) cm")

    res_out = ExperimentResult(
        name="feeding", title=EXPERIMENT.title, seed=seed, description=EXPERIMENT.description,
        config={"spacing_m": SPACING_M, "points": [{"point": i, "offset_m": list(o)} for i, o in points],
                "sequence": sequence, "person_jitter_m": list(PERSON_JITTER_M),
                "camera_rate_hz": CAMERA_RATE_HZ, "quick": quick, "stack_file": "configs/stack.toml",
                "prediction_max_age_s": settings.prediction_max_age_s, "dt_s": settings.arm.dt_s},
        recordings=recordings,
    )
    cols = [
        Column("step", "sub-task"), Column("n", "adaptations", digits=0),
        Column("success_rate", "success rate", "", 3),
        Column("max_error_mm", "max error at completion", "mm", 2),
        Column("max_final_error_mm", "max final error", "mm", 2),
        Column("mean_final_error_mm", "mean final error", "mm", 2),
        Column("max_final_speed_mm_s", "max final speed error", "mm/s", 1),
        Column("mean_duration_s", "mean duration", "s", 2), Column("max_duration_s", "max duration", "s", 2),
        Column("max_peak_speed_mps", "max peak speed", "m/s", 3),
        Column("max_peak_speed_ratio", "max peak speed / demo", "", 2),
        Column("max_peak_accel_mps2", "max peak acceleration", "m/s²", 2),
    ]
    tab = res_out.table("Per sub-task", cols, note="final error: |x − goal| at the step's last tick, "
                        "against the true goal; error at completion: the planner's, to the goal in use")
    agg = {}
    for step in [*sequence, "overall"]:
        sub = rows if step == "overall" else [r for r in rows if r["step"] == step]
        agg[step] = a = _aggregate(sub)
        tab.add(step=step, **{k: a[k] for k in (c.key for c in cols[1:])})
    every = res_out.table("Every adaptation", [
        Column("point", "grid point", digits=0), Column("step", "sub-task"), Column("success", "success"),
        Column("error_mm", "error at completion", "mm", 2), Column("final_error_mm", "final error", "mm", 2),
        Column("final_speed_mm_s", "final speed error", "mm/s", 1), Column("duration_s", "duration", "s", 2),
        Column("peak_speed_mps", "peak speed", "m/s", 3),
        Column("peak_speed_ratio", "peak speed / demo", "", 2),
        Column("peak_accel_mps2", "peak acceleration", "m/s²", 2),
    ])
    for r in rows:
        every.add(**{k: r[k] for k in (c.key for c in every.columns)})
    pts = res_out.table("Per grid point", [
        Column("point", "grid point", digits=0), Column("a_cm", "a", "cm", 0), Column("b_cm", "b", "cm", 0),
        Column("success", "task succeeded"), Column("steps_ok", "sub-tasks succeeded", digits=0),
        Column("duration_s", "task duration", "s", 2), Column("wall_s", "wall time", "s", 1),
    ])
    for p in per_point:
        pts.add(**p)

    tol = min(s.position_tolerance_m for s in base.task.steps)
    plot_grids(rows, out_dir / "grids.png", tol, true_goals(base), SPACING_M)
    res_out.figures.append(Figure("grids.png", "Final positions on the 3×3 grids of the spoon, the bowl "
                                  "(reach_bowl, scoop) and the person against their goals (top), and "
                                  "final − goal in mm with the 1 cm tolerance (bottom)"))
    t_d, X_d, _ = load_demonstration(demo_path("reach_person"))
    plot_trajectories(runs, "reach_person", (t_d, X_d), out_dir / "reach_person_paths.png")
    res_out.figures.append(Figure("reach_person_paths.png", "reach_person on the person's 3×3 grid: paths "
                                  "in the y-z plane and x, y, z over time against the demonstration"))

    o = agg["overall"]
    res_out.headline["success_rate"] = Headline("overall success rate", o["success_rate"], "",
                                                f"{o['ok']}/{o['n']} adaptations")
    worst = max(rows, key=lambda r: r["final_error_mm"])
    res_out.headline["worst_final_error"] = Headline(
        "worst final error", o["max_final_error_mm"], "mm", f"{worst['step']} at grid point {worst['point']}")
    res_out.headline["max_peak_accel"] = Headline("max peak acceleration", o["max_peak_accel_mps2"], "m/s²")
    res_out.headline["max_peak_speed_ratio"] = Headline("max peak speed / demonstration",
                                                        o["max_peak_speed_ratio"], "")
    n_expected = len(points) * len(sequence)
    res_out.verdict("adapts_to_every_goal", o["ok"] == n_expected,
                    f"every adaptation reaches its moved goal (paper: {9 * len(sequence)} adaptations on the "
                    "3×3 grids)", f"{o['ok']}/{n_expected} within the steps' tolerances")
    res_out.verdict("final_error", o["max_final_error_mm"] <= 1e3 * tol, f"final error ≤ {1e3 * tol:.0f} mm",
                    f"worst {o['max_final_error_mm']:.2f} mm ({worst['step']}, point {worst['point']})")
    res_out.verdict("demonstration_speed_kept", o["max_peak_speed_ratio"] <= PEAK_SPEED_RATIO_TARGET,
                    f"peak speed ≤ {PEAK_SPEED_RATIO_TARGET}× the demonstration's (the motion keeps its "
                    "shape)",
                    f"max {o['max_peak_speed_ratio']:.2f}×")
    res_out.verdict("acceleration_limit", o["max_peak_accel_mps2"] <= CARTESIAN_ACCEL_LIMIT_MPS2,
                    f"peak acceleration ≤ {CARTESIAN_ACCEL_LIMIT_MPS2:.0f} m/s² (Panda Cartesian limit)",
                    f"max {o['max_peak_accel_mps2']:.2f} m/s²")
    return res_out


EXPERIMENT = Experiment(
    name="feeding",
    title="Feeding task goal adaptation",
    run=run,
    description="The paper's experiment 1: the feeding task with the spoon, the bowl and the person moved "
    "over 3×3 grids (h = 5 cm), 9 runs × 5 sub-tasks = 45 adaptations, in process (lockstep-equivalent).",
)
