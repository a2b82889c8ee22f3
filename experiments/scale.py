"""Experiment ``scale``: what the PSM costs as a problem grows, and two cells on one router.

1. **Cost vs size.** ``PhaseSpaceModel.fit`` and one ``controller.step`` timed on synthetic
   demonstrations (minimum-jerk reaches through random via-points, drawn from the seed) as the
   dimension grows from 1 to 7 (the default ``segments="auto"``, a movement_primitives DMP with
   50 weights per dimension fitted and stepped side by side in the same interleaved run) and as
   the number of segments grows from 2 to 50 (forced with ``segments=N``, 3 dimensions). The
   timing loops are those of the learner benchmark (:mod:`benchmarks.learner`): calls of all
   contenders alternate, warm-up calls are untimed, garbage collection is off while stepping.
   Linear scaling laws are fitted to the medians.
2. **Two cells on one router.** Two whole feeding stacks (``configs/stack.toml`` without its
   router process, prefixes ``cell_a`` and ``cell_b``) run the feeding task at once in lockstep
   through ONE ``psm serve router`` on loopback, and one cell alone through the same kind of
   router for reference. Measured: both complete, each cell's arm trajectory against the cell
   alone (tick by tick), cross-talk (any key of the other prefix in a cell's recording), the
   wall time and the lockstep rate of each. The cells run every process of the stack, the
   person's goal live from the synthetic camera and the goal tracker, with the planner's
   ``live_goal_sync`` on: each state is answered once the goal of every camera frame due at
   its time is in, so a cell's trajectory is a function of its configuration alone (without it
   the tracker's wall-time pace made two runs of one cell alone differ) and any difference is
   cross-talk.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from experiments.registry import Experiment, Progress
from experiments.result import Column, ExperimentResult, Figure, Headline

FloatArray = NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[1]
STACK_FILE = ROOT / "configs" / "stack.toml"
TASK_FILE = ROOT / "configs" / "feeding.toml"

#: The synthetic demonstrations: 2 s at 500 Hz (the stack's control rate), 0.1 mm noise.
DEMO_SAMPLES = 1001
DEMO_DURATION_S = 2.0
DEMO_NOISE_M = 1e-4
#: Via-points between start and goal, each displaced from the straight line by N(0, 3 cm).
N_VIA = 2
VIA_SIGMA_M = 0.03
DMP_WEIGHTS = 50
DIMENSIONS = (1, 2, 3, 4, 5, 6, 7)
QUICK_DIMENSIONS = (1, 3, 7)
SEGMENTS = (2, 3, 4, 6, 8, 12, 16, 24, 32, 40, 50)
QUICK_SEGMENTS = (2, 12, 50)
SEGMENT_SWEEP_DIM = 3
#: The learner benchmark's target: a PSM step at most half a DMP step (D = 1 and 3 there).
STEP_TARGET_RATIO = 0.5

#: The two cells' prefixes (one router, multicast off, loopback).
CELL_PREFIXES = ("cell_a", "cell_b")
ALONE_PREFIX = "cell_a"
#: Processes the quick run leaves out (only the last feeding step uses the person's goal).
QUICK_WITHOUT = ("camera", "goal_tracker")
#: Wall-clock bound of one ``psm up`` run [s] (it is stopped, by PID, after that).
CELL_TIMEOUT_S = 300.0


@dataclass(frozen=True)
class Timing:
    """Per contender: how many timed calls, warm-up calls and rounds."""

    fit_repeats: int
    step_calls: int
    step_warmup: int
    rounds: int


FULL_TIMING = Timing(fit_repeats=31, step_calls=20_000, step_warmup=1_000, rounds=3)
QUICK_TIMING = Timing(fit_repeats=3, step_calls=600, step_warmup=60, rounds=1)


# ---------------------------------------------------------------------------- demonstrations


def via_point_reach(
    rng: np.random.Generator,
    dim: int,
    n_via: int = N_VIA,
    n_samples: int = DEMO_SAMPLES,
    duration: float = DEMO_DURATION_S,
    noise: float = DEMO_NOISE_M,
) -> Any:
    """A reach from rest to rest through ``n_via`` via-points, on a minimum-jerk time profile.

    The start is uniform in [-0.25, 0.25] m per dimension, the goal 0.15–0.4 m away along each
    axis (random sign); the via-points sit at equal phase steps on the straight line, displaced
    by N(0, :data:`VIA_SIGMA_M`) per axis. The path is the natural cubic spline through start,
    via-points and goal in the phase ``s = 10τ³ − 15τ⁴ + 6τ⁵`` (``τ = t/duration``), so it starts
    and ends at rest; Gaussian noise of ``noise`` [m] is added.

    Returns:
        :class:`benchmarks.learner.Demo` with ``t (n_samples,)`` [s], ``x (n_samples, dim)`` [m].
    """
    from scipy.interpolate import CubicSpline

    from benchmarks.learner import Demo

    t = np.linspace(0.0, duration, n_samples)
    tau = t / duration
    s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    start = rng.uniform(-0.25, 0.25, dim)
    goal = start + rng.uniform(0.15, 0.4, dim) * rng.choice([-1.0, 1.0], dim)
    phase = np.linspace(0.0, 1.0, n_via + 2)
    knots = start + phase[:, None] * (goal - start)
    knots[1:-1] += rng.normal(0.0, VIA_SIGMA_M, (n_via, dim))
    x = CubicSpline(phase, knots, bc_type="natural", axis=0)(s)
    return Demo(t=t, x=x + rng.normal(0.0, noise, x.shape))


def slice_demo(demo: Any, dim: int) -> Any:
    """The first ``dim`` coordinates of ``demo``."""
    from benchmarks.learner import Demo

    return Demo(t=demo.t, x=np.ascontiguousarray(demo.x[:, :dim]))


# ---------------------------------------------------------------------------- cost vs size


def _fit_stats(times_s: Sequence[float]) -> dict[str, float]:
    a = np.asarray(times_s, float) * 1e3
    return {
        "median_ms": float(np.median(a)),
        "p10_ms": float(np.percentile(a, 10)),
        "p90_ms": float(np.percentile(a, 90)),
        "calls": len(a),
    }


def _merge_rounds(rounds: list[dict[str, float]]) -> dict[str, float]:
    """Per-call statistics over rounds: the median of each statistic, and the rounds' range of
    the median."""
    keys = [k for k in rounds[0] if k != "calls"]
    med = [r["median_us"] if "median_us" in r else r["median_ms"] for r in rounds]
    out = {k: float(statistics.median(r[k] for r in rounds)) for k in keys}
    out.update(calls=int(sum(r["calls"] for r in rounds)), round_min=min(med), round_max=max(med))
    return out


def time_fits(fitters: dict[str, Callable[[], Any]], timing: Timing) -> dict[str, dict[str, Any]]:
    """Fit times of every contender, calls interleaved (:func:`benchmarks.learner.interleaved_times`),
    ``timing.rounds`` rounds; per contender the pooled median / p10 / p90 [ms] and each round's
    median [ms] (``rounds``)."""
    from benchmarks.learner import interleaved_times

    samples: dict[str, list[float]] = {k: [] for k in fitters}
    per_round: dict[str, list[float]] = {k: [] for k in fitters}
    for _ in range(timing.rounds):
        times = interleaved_times(fitters, timing.fit_repeats)
        for k, v in times.items():
            samples[k].extend(v)
            per_round[k].append(float(np.median(v)) * 1e3)
    return {k: {**_fit_stats(samples[k]), "rounds": per_round[k]} for k in fitters}


def time_steps(steppers: dict[str, Any], timing: Timing) -> dict[str, dict[str, Any]]:
    """Control-step times of every contender in interleaved blocks
    (:func:`benchmarks.learner.time_interleaved`), ``timing.rounds`` rounds; per contender the
    median over rounds of the median / p10 / p90 [µs] and each round's median [µs]."""
    from benchmarks.learner import time_interleaved

    rounds: list[dict[str, dict[str, float]]] = []
    for _ in range(timing.rounds):
        calls = dict.fromkeys(steppers, timing.step_calls)
        rounds.append(time_interleaved(steppers, calls, timing.step_warmup))
    return {
        k: {**_merge_rounds([r[k] for r in rounds]), "rounds": [r[k]["median_us"] for r in rounds]}
        for k in steppers
    }


def linear_law(x: Sequence[float], y: Sequence[float]) -> dict[str, float]:
    """Least-squares ``y = intercept + slope x`` with its R² and the log–log slope (exponent of
    a power law ``y ∝ x^p`` through the same points)."""
    xa, ya = np.asarray(x, float), np.asarray(y, float)
    slope, intercept = np.polyfit(xa, ya, 1)
    resid = ya - (intercept + slope * xa)
    ss = float(np.sum((ya - ya.mean()) ** 2))
    r2 = 1.0 - float(np.sum(resid**2)) / ss if ss > 0 else 1.0
    exponent = (
        float(np.polyfit(np.log(xa), np.log(ya), 1)[0]) if np.all(xa > 0) and np.all(ya > 0) else math.nan
    )
    return {"intercept": float(intercept), "slope": float(slope), "r2": r2, "exponent": exponent}


def dimension_sweep(
    seed: int, dims: Sequence[int], timing: Timing, log: Callable[[str], None]
) -> dict[str, Any]:
    """Fit and step costs of the PSM and DMP-50 for each dimension in ``dims`` (one 7-D reach,
    its first D coordinates)."""
    from benchmarks.learner import DMPStepper, PSMStepper, fit_dmp, fit_psm

    demo = via_point_reach(np.random.default_rng([seed, 1]), max(dims))
    demos = {d: slice_demo(demo, d) for d in dims}
    fitters: dict[str, Callable[[], Any]] = {}
    for d in dims:
        fitters[f"psm_D{d}"] = lambda dd=demos[d]: fit_psm(dd)
        fitters[f"dmp_D{d}"] = lambda dd=demos[d]: fit_dmp(dd, DMP_WEIGHTS)
    fits = time_fits(fitters, timing)
    log("dimension sweep: fits timed")
    models = {d: fit_psm(demos[d]) for d in dims}
    steppers: dict[str, Any] = {}
    for d in dims:
        steppers[f"psm_D{d}"] = PSMStepper(models[d], demos[d])
        steppers[f"dmp_D{d}"] = DMPStepper(fit_dmp(demos[d], DMP_WEIGHTS), demos[d], "rk4-cython")
    steps = time_steps(steppers, timing)
    log("dimension sweep: steps timed")
    rows = []
    for d in dims:
        pf, df = fits[f"psm_D{d}"], fits[f"dmp_D{d}"]
        ps, ds = steps[f"psm_D{d}"], steps[f"dmp_D{d}"]
        fit_ratios = [p / q for p, q in zip(pf["rounds"], df["rounds"], strict=True)]
        step_ratios = [p / q for p, q in zip(ps["rounds"], ds["rounds"], strict=True)]
        rows.append(
            {
                "dim": d,
                "segments": float(np.mean([len(k) for k in models[d].k])),
                "psm_fit": pf,
                "dmp_fit": df,
                "psm_step": ps,
                "dmp_step": ds,
                "fit_ratio": pf["median_ms"] / df["median_ms"],
                "fit_ratio_rounds": [min(fit_ratios), max(fit_ratios)],
                "step_ratio": ps["median_us"] / ds["median_us"],
                "step_ratio_rounds": [min(step_ratios), max(step_ratios)],
            }
        )
    laws = {
        "psm_fit_ms": linear_law(dims, [r["psm_fit"]["median_ms"] for r in rows]),
        "dmp_fit_ms": linear_law(dims, [r["dmp_fit"]["median_ms"] for r in rows]),
        "psm_step_us": linear_law(dims, [r["psm_step"]["median_us"] for r in rows]),
        "dmp_step_us": linear_law(dims, [r["dmp_step"]["median_us"] for r in rows]),
    }
    return {"rows": rows, "laws": laws}


def segment_sweep(
    seed: int, segments: Sequence[int], timing: Timing, log: Callable[[str], None]
) -> dict[str, Any]:
    """Fit and step costs of the PSM with ``segments=N`` for each N (one 3-D reach)."""
    from benchmarks.learner import PSMStepper, fit_psm

    demo = via_point_reach(np.random.default_rng([seed, 2]), SEGMENT_SWEEP_DIM)
    fitters = {f"N{n}": (lambda nn=n: fit_psm(demo, segments=nn)) for n in segments}
    fits = time_fits(fitters, timing)
    log("segment sweep: fits timed")
    models = {n: fit_psm(demo, segments=n) for n in segments}
    steps = time_steps({f"N{n}": PSMStepper(models[n], demo) for n in segments}, timing)
    log("segment sweep: steps timed")
    rows = []
    for n in segments:
        m = models[n]
        r = m.rollout(demo.x[0], dt=demo.dt, max_duration=2 * demo.duration)
        rows.append(
            {
                "requested": n,
                "segments": float(np.mean([len(k) for k in m.k])),
                "fit": fits[f"N{n}"],
                "step": steps[f"N{n}"],
                "done": bool(r.done),
                "rmse_mm": 1e3
                * float(
                    np.sqrt(
                        np.mean(
                            np.sum(
                                (
                                    np.stack(
                                        [np.interp(demo.t, r.t, r.x[:, j]) for j in range(demo.x.shape[1])], 1
                                    )
                                    - demo.x
                                )
                                ** 2,
                                axis=1,
                            )
                        )
                    )
                ),
            }
        )
    x = [r["segments"] for r in rows]
    laws = {
        "fit_ms": linear_law(x, [r["fit"]["median_ms"] for r in rows]),
        "step_us": linear_law(x, [r["step"]["median_us"] for r in rows]),
    }
    return {"rows": rows, "laws": laws, "dim": SEGMENT_SWEEP_DIM}


# ---------------------------------------------------------------------------- plots


def _plain_log_labels(ax: Any) -> None:
    """Tick labels of log axes as plain numbers (2, 5, 10 instead of 2×10⁰)."""
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    for axis, scale in ((ax.xaxis, ax.get_xscale()), (ax.yaxis, ax.get_yscale())):
        if scale == "log":
            axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(ScalarFormatter())
            axis.set_minor_formatter(NullFormatter())


def plot_dimensions(sweep: dict[str, Any], path: Path) -> None:
    """Fit [ms] and step [µs] vs dimension, PSM and DMP-50 (median, p10–p90 bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sweep["rows"]
    d = [r["dim"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (kind, unit) in zip(axes, (("fit", "ms"), ("step", "us")), strict=True):
        for who, label, colour in (("psm", "PSM", "C0"), ("dmp", f"DMP-{DMP_WEIGHTS}", "C1")):
            st = [r[f"{who}_{kind}"] for r in rows]
            med = np.array([s[f"median_{unit}"] for s in st])
            lo = med - np.array([s[f"p10_{unit}"] for s in st])
            hi = np.array([s[f"p90_{unit}"] for s in st]) - med
            ax.errorbar(
                d, med, yerr=[lo, hi], marker="o", capsize=3, color=colour, label=f"{label} (median, p10–p90)"
            )
        law = sweep["laws"][f"psm_{kind}_{unit}"]
        xs = np.linspace(min(d), max(d), 50)
        ax.plot(
            xs,
            law["intercept"] + law["slope"] * xs,
            "--",
            color="C0",
            alpha=0.6,
            label=f"PSM linear law (R² {law['r2']:.2f})",
        )
        ax.set_yscale("log")
        ax.set_xlabel("dimension D")
        ax.set_ylabel("fit time [ms]" if kind == "fit" else "controller step [µs]")
        ax.set_title("PhaseSpaceModel.fit vs DMP.imitate" if kind == "fit" else "controller.step vs DMP.step")
        _plain_log_labels(ax)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_segments(sweep: dict[str, Any], path: Path) -> None:
    """Fit [ms] and step [µs] vs segments per dimension (log–log), with the linear law."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sweep["rows"]
    n = np.array([r["segments"] for r in rows])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (kind, key, unit, ylabel) in zip(
        axes,
        (("fit", "fit_ms", "ms", "fit time [ms]"), ("step", "step_us", "us", "controller step [µs]")),
        strict=True,
    ):
        med = np.array([r[kind][f"median_{unit}"] for r in rows])
        lo = med - np.array([r[kind][f"p10_{unit}"] for r in rows])
        hi = np.array([r[kind][f"p90_{unit}"] for r in rows]) - med
        ax.errorbar(n, med, yerr=[lo, hi], marker="o", capsize=3, label="PSM (median, p10–p90)")
        law = sweep["laws"][key]
        xs = np.geomspace(n.min(), n.max(), 50)
        ax.plot(
            xs,
            law["intercept"] + law["slope"] * xs,
            "--",
            label=f"{law['intercept']:.3g} + {law['slope']:.3g}·N {unit} (R² {law['r2']:.2f})",
        )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"segments per dimension N (D = {sweep['dim']})")
        ax.set_ylabel(ylabel)
        _plain_log_labels(ax)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("PSM cost vs number of segments (segments=N)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------- two cells


def toml_value(value: Any) -> str:
    """``value`` (str, bool, int, float, list, dict of these) as an inline TOML value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def cell_processes(without: Sequence[str] = (), stack_file: Path = STACK_FILE) -> list[dict[str, Any]]:
    """The stack file's processes with its router and those named in ``without`` disabled
    (``enabled = false``: their tables stay owned): a cell that joins a router someone else runs."""
    import tomllib

    procs = tomllib.loads(stack_file.read_text())["stack"]["processes"]
    unknown = set(without) - {p["name"] for p in procs}
    if unknown:
        raise ValueError(f"no process {sorted(unknown)} in {stack_file}")
    return [
        {**p, "enabled": False}
        if list(p["command"][:2]) == ["serve", "router"] or p["name"] in without
        else p
        for p in procs
    ]


def quick_task_file(path: Path, steps: int = 1) -> Path:
    """``configs/feeding.toml`` with only its first ``steps`` sub-tasks, written to ``path``."""
    text = TASK_FILE.read_text()
    head, *step_tables = text.split("[[task.steps]]")
    if len(step_tables) < steps:
        raise ValueError(f"{TASK_FILE} has {len(step_tables)} steps, fewer than {steps}")
    path.write_text(head + "".join("[[task.steps]]" + s for s in step_tables[:steps]))
    return path


@dataclass
class CellRun:
    """One ``psm up`` of a cell: where it writes and what came out."""

    prefix: str
    run_dir: Path
    recording: Path
    proc: Any = None
    started: float = 0.0
    wall_s: float | None = None
    exit_code: int | None = None

    def args(self, port: int, task_file: Path, cache_dir: Path, without: Sequence[str] = ()) -> list[str]:
        """``psm up`` arguments: the shipped stack without its router (and ``without``), on
        ``prefix``, connected to the router at 127.0.0.1:``port``, lockstep with the planner's
        ``live_goal_sync`` (and the arm waiting up to 5 s for an answer), everything under
        ``run_dir``."""
        values = [
            'clock="lockstep"',
            f'prefix="{self.prefix}"',
            f"stack.processes={toml_value(cell_processes(without))}",
            f'zenoh.connect=["tcp/127.0.0.1:{port}"]',
            f'stack.run_dir="{self.run_dir}"',
            f'recorder.output="{self.recording}"',
            f'planner.task_file="{task_file}"',
            f'planner.summary_file="{self.run_dir / "task.json"}"',
            f'planner.progress_file="{self.run_dir / "progress.json"}"',
            f'arm.stats_file="{self.run_dir / "arm.json"}"',
            f'planner.cache_dir="{cache_dir}"',
            "planner.live_goal_sync=true",
            # The arm waits up to 5 s for each answer (0.5 s shipped): with two cells on two cores
            # the camera and the tracker can take longer than 0.5 s for a frame, and an arm that
            # steps on without an answer makes the run differ by design.
            "arm.lockstep_timeout_s=5.0",
        ]
        return ["up", str(STACK_FILE), "--no-live", *(a for v in values for a in ("--set", v))]


def start_router(log_dir: Path) -> tuple[Any, int]:
    """``psm serve router`` on a free loopback port (its status on prefix ``scale_router``);
    returns the process and the port once it listens."""
    from services.supervisor import ManagedProcess, free_port, psm_argv, wait_port

    port = free_port()
    argv = psm_argv(
        [
            "serve",
            "router",
            "--config",
            str(STACK_FILE),
            "--prefix",
            "scale_router",
            "--set",
            f'router.listen=["tcp/127.0.0.1:{port}"]',
        ]
    )
    proc = ManagedProcess("router", argv, log_dir / "router.log", cwd=ROOT)
    try:
        wait_port(port, 30.0, proc)
    except RuntimeError:
        proc.stop()
        raise
    return proc, port


def run_cells(
    cells: list[CellRun],
    port: int,
    task_file: Path,
    cache_dir: Path,
    *,
    without: Sequence[str] = (),
    timeout_s: float = CELL_TIMEOUT_S,
) -> None:
    """Start every cell's ``psm up`` at once, wait (at most ``timeout_s`` in all) for each to
    end, stop any still running by its PID; fills ``wall_s`` and ``exit_code``."""
    from services.supervisor import ManagedProcess, psm_argv

    for c in cells:
        c.run_dir.mkdir(parents=True, exist_ok=True)
        c.proc = ManagedProcess(
            f"up_{c.prefix}",
            psm_argv(c.args(port, task_file, cache_dir, without)),
            c.run_dir / "up.log",
            cwd=ROOT,
        )
        c.started = time.monotonic()
    deadline = time.monotonic() + timeout_s
    try:
        for c in cells:
            rc = c.proc.wait(max(0.0, deadline - time.monotonic()))
            if rc is not None:
                c.exit_code = rc
                c.wall_s = (c.proc.ended or time.monotonic()) - c.started
    finally:
        for c in cells:
            rc = c.proc.stop()
            if c.exit_code is None:
                c.exit_code = None if rc is None else -1000 - abs(rc)  # stopped at the deadline


def read_recording(path: Path) -> dict[str, Any]:
    """What a cell's recording holds: every topic with its message count, the arm states by
    tick (``q (7,)`` [rad] and end-effector position (3,) [m]), the log times [ns] of the arm
    commands and the last tick a command answered."""
    from mcap.reader import make_reader

    from services.bus.messages import ArmCommand, ArmState

    topics: dict[str, int] = {}
    states: dict[int, tuple[list[float], list[float]]] = {}
    command_log_ns: list[int] = []
    command_ticks: list[int] = []
    with path.open("rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            topic = channel.topic
            topics[topic] = topics.get(topic, 0) + 1
            if topic.endswith("/arm/state"):
                st = ArmState.FromString(message.data)
                p = st.ee_position
                states.setdefault(int(st.tick), (list(st.q), [p.x, p.y, p.z]))
            elif topic.endswith("/arm/command"):
                command_log_ns.append(int(message.log_time))
                command_ticks.append(int(ArmCommand.FromString(message.data).tick))
    return {
        "topics": topics,
        "states": states,
        "command_log_ns": sorted(command_log_ns),
        "last_command_tick": max(command_ticks, default=-1),
    }


def compare_states(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Tick-by-tick difference of two cells' arm states (``cell_outcome`` dicts) over the ticks
    both planners answered (tick 0 to the earlier last command: the task and the hold after it;
    afterwards the arm brakes on its watchdog for as long as the shutdown takes, which is wall
    time): the largest |Δq| [rad] and end-effector distance [m], and how many ticks differ."""
    last = min(a["last_command_tick"], b["last_command_tick"])
    common = [k for k in sorted(set(a["states"]) & set(b["states"])) if k <= last]
    if not common:
        return {"common_ticks": 0, "max_dq_rad": None, "max_dee_m": None, "ticks_differing": None}
    qa = np.array([a["states"][k][0] for k in common])
    qb = np.array([b["states"][k][0] for k in common])
    ea = np.array([a["states"][k][1] for k in common])
    eb = np.array([b["states"][k][1] for k in common])
    dq = np.abs(qa - qb).max(axis=1)
    de = np.linalg.norm(ea - eb, axis=1)
    return {
        "common_ticks": len(common),
        "last_tick": last,
        "max_dq_rad": float(dq.max()),
        "max_dee_m": float(de.max()),
        "ticks_differing": int(np.count_nonzero((dq > 0) | (de > 0))),
    }


def cell_outcome(cell: CellRun, others: Sequence[str]) -> dict[str, Any]:
    """A finished cell's figures: task success and steps, sim duration, wall times, lockstep
    rates, and the recording's keys outside its prefix or under another cell's."""
    task = (
        json.loads((cell.run_dir / "task.json").read_text()) if (cell.run_dir / "task.json").exists() else {}
    )
    arm = json.loads((cell.run_dir / "arm.json").read_text()) if (cell.run_dir / "arm.json").exists() else {}
    rec = (
        read_recording(cell.recording)
        if cell.recording.exists()
        else {"topics": {}, "states": {}, "command_log_ns": [], "last_command_tick": -1}
    )
    own = f"{cell.prefix}/"
    foreign = {t: n for t, n in rec["topics"].items() if not t.startswith(own)}
    other_prefix = {t: n for t, n in rec["topics"].items() if any(t.startswith(f"{o}/") for o in others)}
    cmd = rec["command_log_ns"]
    task_wall = (cmd[-1] - cmd[0]) * 1e-9 if len(cmd) > 1 else None
    steps = task.get("steps", [])
    return {
        "prefix": cell.prefix,
        "exit_code": cell.exit_code,
        "success": bool(task.get("success")),
        "steps_succeeded": int(task.get("steps_succeeded") or 0),
        "steps_total": int(task.get("steps_total") or 0),
        "task_sim_s": task.get("duration_s"),
        "steps": [
            {k: s.get(k) for k in ("step", "success", "duration_s", "position_error_m", "peak_speed_mps")}
            for s in steps
        ],
        "up_wall_s": cell.wall_s,
        "task_wall_s": task_wall,
        "commands": len(cmd),
        "command_rate_hz": (len(cmd) - 1) / task_wall if task_wall else None,
        "arm_ticks": arm.get("ticks"),
        "arm_ticks_per_s": arm.get("ticks_per_s"),
        "messages": int(sum(rec["topics"].values())),
        "topics": len(rec["topics"]),
        "foreign_messages": int(sum(foreign.values())),
        "other_cell_messages": int(sum(other_prefix.values())),
        "foreign_topics": sorted(foreign),
        "task_end_tick": (
            round(task["duration_s"] / arm["dt_s"]) if task.get("duration_s") and arm.get("dt_s") else None
        ),
        "last_command_tick": rec["last_command_tick"],
        "states": rec["states"],
    }


def cells_experiment(out_dir: Path, *, quick: bool, progress: Callable[[str], None]) -> dict[str, Any]:
    """One cell alone and two cells at once through one router, alternately, twice, on the
    feeding task with the live goal synchronised (see the module docstring). The quick run
    (tests) is one pair only, on a reduced task: the first feeding step, without the camera and
    the goal tracker (only the last step uses them); its cells are compared with each other."""
    work = out_dir / "cells"
    work.mkdir(parents=True, exist_ok=True)
    cache = work / "models"
    if quick:
        task_file = quick_task_file(work / "task_quick.toml")
        runs = ["pair"]
        without = QUICK_WITHOUT
    else:
        task_file, runs, without = TASK_FILE, ["alone", "pair", "alone", "pair"], ()
    alone: list[dict[str, Any]] = []
    pairs: list[list[dict[str, Any]]] = []
    recordings: list[str] = []
    for i, kind in enumerate(runs):
        name = f"{kind}{len(alone if kind == 'alone' else pairs) + 1}"
        router, port = start_router(work / name)
        try:
            prefixes = (ALONE_PREFIX,) if kind == "alone" else CELL_PREFIXES
            cells = [CellRun(p, work / name / p, out_dir / f"{name}_{p}.mcap") for p in prefixes]
            run_cells(cells, port, task_file, cache, without=without)
        finally:
            router.stop()
        outcomes = [cell_outcome(c, [p for p in CELL_PREFIXES if p != c.prefix]) for c in cells]
        if kind == "alone":
            alone.append(outcomes[0])
        else:
            pairs.append(outcomes)
        recordings += [c.recording.name for c in cells if c.recording.exists()]
        progress(f"cells: {name} ({i + 1}/{len(runs)})")
    reference = alone[0] if alone else pairs[0][0]
    for o in [*alone, *(o for p in pairs for o in p)]:
        o["vs_reference"] = compare_states(reference, o)
    return {
        "alone": alone,
        "pairs": pairs,
        "recordings": recordings,
        "task_file": str(task_file),
        "reference": "alone 1" if alone else f"pair 1 {reference['prefix']}",
        "without": list(without),
        "runs": runs,
    }


# ---------------------------------------------------------------------------- the experiment


def _us(v: float) -> float:
    return round(v, 2)


def run(out_dir: Path, *, seed: int, quick: bool, progress: Progress) -> ExperimentResult:
    """Run both parts into ``out_dir`` (plots, the cells' recordings) and return the result."""
    timing = QUICK_TIMING if quick else FULL_TIMING
    dims = QUICK_DIMENSIONS if quick else DIMENSIONS
    segs = QUICK_SEGMENTS if quick else SEGMENTS
    total = 6 + (1 if quick else 4)
    done = [0]

    def step(label: str) -> None:
        done[0] += 1
        progress(done[0], total, label)

    res = ExperimentResult(
        name="scale",
        title=EXPERIMENT.title,
        seed=seed,
        description=EXPERIMENT.description,
        config={
            "quick": quick,
            "dimensions": list(dims),
            "segments": list(segs),
            "segment_sweep_dim": SEGMENT_SWEEP_DIM,
            "demo_samples": DEMO_SAMPLES,
            "demo_duration_s": DEMO_DURATION_S,
            "demo_noise_m": DEMO_NOISE_M,
            "via_points": N_VIA,
            "via_sigma_m": VIA_SIGMA_M,
            "dmp_weights": DMP_WEIGHTS,
            "dmp_step_function": "rk4-cython",
            "timing": timing.__dict__,
            "cell_prefixes": list(CELL_PREFIXES),
            "cell_timeout_s": CELL_TIMEOUT_S,
            "stack_file": str(STACK_FILE.relative_to(ROOT)),
        },
    )
    dim = dimension_sweep(seed, dims, timing, step)
    seg = segment_sweep(seed, segs, timing, step)
    plot_dimensions(dim, out_dir / "cost_vs_dimension.png")
    plot_segments(seg, out_dir / "cost_vs_segments.png")
    step("plots")
    cells = cells_experiment(out_dir, quick=quick, progress=step)
    _report_costs(res, dim, seg, timing)
    _report_cells(res, cells)
    step("report")
    return res


def _report_costs(res: ExperimentResult, dim: dict[str, Any], seg: dict[str, Any], timing: Timing) -> None:
    note = (
        f"{DEMO_SAMPLES}-sample {DEMO_DURATION_S:g} s reach through {N_VIA} via-points, "
        f"{DEMO_NOISE_M * 1e3:g} mm noise; {timing.rounds} rounds of interleaved calls "
        f"({timing.fit_repeats} fits, {timing.step_calls} steps per contender and round); "
        "median and p10/p90 per call; ratio range = per-round ratios. The machine was shared "
        "(2 cores, other jobs running): absolute times drift, same-run ratios less so."
    )
    t = res.table(
        "Cost vs dimension: PSM and DMP-50 in the same run",
        [
            Column("dim", "D"),
            Column("segments", "PSM segments / dim", "", 1),
            Column("psm_fit", "PSM fit median", "ms", 3),
            Column("psm_fit_p90", "PSM fit p90", "ms", 3),
            Column("dmp_fit", "DMP-50 imitate median", "ms", 3),
            Column("fit_ratio", "fit ratio PSM/DMP", "", 3),
            Column("fit_ratio_range", "fit ratio range (rounds)"),
            Column("psm_step", "PSM step median", "µs", 2),
            Column("psm_step_p10", "PSM step p10", "µs", 2),
            Column("psm_step_p90", "PSM step p90", "µs", 2),
            Column("dmp_step", "DMP step median", "µs", 2),
            Column("step_ratio", "step ratio PSM/DMP", "", 3),
            Column("step_ratio_range", "step ratio range (rounds)"),
        ],
        note=note,
    )
    for r in dim["rows"]:
        t.add(
            dim=r["dim"],
            segments=r["segments"],
            psm_fit=r["psm_fit"]["median_ms"],
            psm_fit_p90=r["psm_fit"]["p90_ms"],
            dmp_fit=r["dmp_fit"]["median_ms"],
            fit_ratio=r["fit_ratio"],
            fit_ratio_range="{:.3f}–{:.3f}".format(*r["fit_ratio_rounds"]),
            psm_step=r["psm_step"]["median_us"],
            psm_step_p10=r["psm_step"]["p10_us"],
            psm_step_p90=r["psm_step"]["p90_us"],
            dmp_step=r["dmp_step"]["median_us"],
            step_ratio=r["step_ratio"],
            step_ratio_range="{:.3f}–{:.3f}".format(*r["step_ratio_rounds"]),
        )
    t = res.table(
        f"Cost vs segments: PSM, D = {seg['dim']}, segments=N",
        [
            Column("requested", "N requested"),
            Column("segments", "segments / dim", "", 1),
            Column("fit", "fit median", "ms", 3),
            Column("fit_p10", "fit p10", "ms", 3),
            Column("fit_p90", "fit p90", "ms", 3),
            Column("step", "step median", "µs", 2),
            Column("step_p10", "step p10", "µs", 2),
            Column("step_p90", "step p90", "µs", 2),
            Column("rmse", "rollout RMSE vs demo", "mm", 2),
            Column("done", "goal reached"),
        ],
        note="segments / dim: what the fit kept (cuts that leave a segment moving less than the "
        "hold tolerance are dropped near the rest ends). " + note,
    )
    for r in seg["rows"]:
        t.add(
            requested=r["requested"],
            segments=r["segments"],
            fit=r["fit"]["median_ms"],
            fit_p10=r["fit"]["p10_ms"],
            fit_p90=r["fit"]["p90_ms"],
            step=r["step"]["median_us"],
            step_p10=r["step"]["p10_us"],
            step_p90=r["step"]["p90_us"],
            rmse=r["rmse_mm"],
            done=r["done"],
        )
    t = res.table(
        "Scaling laws (least squares on the medians)",
        [
            Column("quantity", "quantity"),
            Column("law", "law"),
            Column("intercept", "intercept"),
            Column("slope", "slope"),
            Column("r2", "R²", "", 3),
            Column("exponent", "log–log exponent", "", 2),
        ],
    )
    laws = [
        ("PSM fit vs segments N", "fit_ms", seg["laws"]["fit_ms"], "ms", "N"),
        ("PSM step vs segments N", "step_us", seg["laws"]["step_us"], "µs", "N"),
        ("PSM fit vs dimension D", "", dim["laws"]["psm_fit_ms"], "ms", "D"),
        ("DMP-50 imitate vs dimension D", "", dim["laws"]["dmp_fit_ms"], "ms", "D"),
        ("PSM step vs dimension D", "", dim["laws"]["psm_step_us"], "µs", "D"),
        ("DMP-50 step vs dimension D", "", dim["laws"]["dmp_step_us"], "µs", "D"),
    ]
    for name, _key, law, unit, var in laws:
        t.add(
            quantity=name,
            law=f"{law['intercept']:.3g} {unit} + {law['slope']:.3g} {unit} × {var}",
            intercept=f"{law['intercept']:.4g} {unit}",
            slope=f"{law['slope']:.4g} {unit}/{var}",
            r2=law["r2"],
            exponent=law["exponent"],
        )
    res.figures += [
        Figure(
            "cost_vs_dimension.png",
            "Fit time [ms] and control step [µs] vs dimension, PSM and DMP-50, medians with p10–p90 (log y)",
        ),
        Figure(
            "cost_vs_segments.png",
            f"PSM fit [ms] and step [µs] vs segments per dimension (D = {seg['dim']}, "
            "log–log) with the fitted linear law",
        ),
    ]
    fl, sl = seg["laws"]["fit_ms"], seg["laws"]["step_us"]
    res.headline["fit_per_segment"] = Headline(
        "PSM fit cost per segment",
        round(fl["slope"] * 1e3, 1),
        "µs/segment",
        f"fit ≈ {fl['intercept']:.2f} ms + {fl['slope'] * 1e3:.1f} µs × N "
        f"(D = {seg['dim']}, R² {fl['r2']:.2f})",
    )
    first, last = seg["rows"][0], seg["rows"][-1]
    res.headline["step_vs_segments"] = Headline(
        "PSM step, fewest → most segments",
        f"{first['step']['median_us']:.1f} → {last['step']['median_us']:.1f}",
        "µs",
        f"N {first['segments']:.0f} → {last['segments']:.0f}; slope {sl['slope'] * 1e3:.1f} ns/segment",
    )
    lo, hi = dim["rows"][0], dim["rows"][-1]
    res.headline["step_ratio"] = Headline(
        f"PSM/DMP step ratio, D = {lo['dim']} → {hi['dim']}",
        f"{lo['step_ratio']:.2f} → {hi['step_ratio']:.2f}",
        "",
        f"PSM {lo['psm_step']['median_us']:.1f} → {hi['psm_step']['median_us']:.1f} µs, "
        f"DMP {lo['dmp_step']['median_us']:.1f} → {hi['dmp_step']['median_us']:.1f} µs",
    )
    res.headline["fit_ratio"] = Headline(
        f"PSM/DMP-50 fit ratio, D = {lo['dim']} → {hi['dim']}",
        f"{lo['fit_ratio']:.2f} → {hi['fit_ratio']:.2f}",
        "",
        f"PSM {lo['psm_fit']['median_ms']:.2f} → {hi['psm_fit']['median_ms']:.2f} ms, "
        f"DMP {lo['dmp_fit']['median_ms']:.2f} → {hi['dmp_fit']['median_ms']:.2f} ms",
    )
    pl = dim["laws"]["psm_step_us"]
    res.headline["step_per_dim"] = Headline(
        "PSM step cost per dimension",
        round(pl["slope"], 2),
        "µs/dimension",
        f"step ≈ {pl['intercept']:.2f} µs + {pl['slope']:.2f} µs × D (R² {pl['r2']:.2f})",
    )
    res.verdict(
        "fit_linear_in_segments",
        fl["r2"] >= 0.9 and fl["slope"] > 0,
        "fit time linear in segments (R² ≥ 0.9, slope > 0)",
        f"{fl['intercept']:.3f} ms + {fl['slope'] * 1e3:.2f} µs × N, R² {fl['r2']:.3f}",
    )
    span = last["segments"] - first["segments"]
    growth = sl["slope"] * span / max(first["step"]["median_us"], 1e-9)
    res.verdict(
        "step_independent_of_segments",
        abs(growth) <= 0.25,
        "step cost within 25 % from fewest to most segments (law's change / first median)",
        f"{growth * 100:+.1f} % over N {first['segments']:.0f} → {last['segments']:.0f}",
    )
    small = [r for r in dim["rows"] if r["dim"] <= 3]
    res.verdict(
        "step_ratio_small_dims",
        all(r["step_ratio"] <= STEP_TARGET_RATIO for r in small),
        f"PSM step ≤ {STEP_TARGET_RATIO}× DMP step for D ≤ 3 (the learner benchmark's target)",
        ", ".join(f"D{r['dim']} {r['step_ratio']:.2f}×" for r in small),
    )
    worst = max(dim["rows"], key=lambda r: r["step_ratio"])
    res.verdict(
        "step_ratio_all_dims",
        all(r["step_ratio"] <= STEP_TARGET_RATIO for r in dim["rows"]),
        f"PSM step ≤ {STEP_TARGET_RATIO}× DMP step at every D up to {dim['rows'][-1]['dim']}",
        f"worst D{worst['dim']} {worst['step_ratio']:.2f}×",
    )
    res.verdict(
        "fit_below_dmp",
        all(r["fit_ratio"] < 1 for r in dim["rows"]),
        "PSM fit faster than DMP-50 imitate at every D",
        ", ".join(f"D{r['dim']} {r['fit_ratio']:.2f}×" for r in dim["rows"]),
    )
    res.config["raw"] = {"dimension_sweep": dim, "segment_sweep": seg}


def _median(values: Sequence[float | None]) -> float | None:
    v = [x for x in values if x is not None]
    return float(statistics.median(v)) if v else None


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def _report_cells(res: ExperimentResult, cells: dict[str, Any]) -> None:
    alone, pair_cells = cells["alone"], [o for p in cells["pairs"] for o in p]
    t = res.table(
        "Two cells on one router vs one cell alone (lockstep feeding task)",
        [
            Column("run", "run"),
            Column("prefix", "prefix"),
            Column("success", "task succeeded"),
            Column("steps", "steps"),
            Column("task_sim", "task (sim)", "s", 3),
            Column("up_wall", "psm up wall", "s", 1),
            Column("task_wall", "task wall", "s", 2),
            Column("rate", "lockstep rate", "ticks/s", 0),
            Column("rate_ratio", "rate / alone", "", 2),
            Column("arm_rate", "arm ticks/s (stats)", "ticks/s", 0),
            Column("messages", "recorded messages"),
            Column("foreign", "other-prefix messages"),
            Column("compared", "ticks compared"),
            Column("differing", "ticks differing"),
            Column("dq", "max |Δq| vs reference", "rad", 3),
            Column("dee", "max Δ end effector vs reference", "mm", 4),
        ],
        note="task wall: first to last arm command in the cell's recording (recorder receive times); "
        "lockstep rate: arm commands (one per tick) per second over that span; psm up wall: start of "
        "`psm up` to its exit (start-up of every process, task, shutdown); arm ticks/s: the arm's own "
        "statistics over its whole life (start-up and shutdown ticks on its watchdog included). "
        f"Δ: tick by tick against {cells['reference']} over the ticks both planners answered (the "
        "task and the hold after it). "
        f"Task file: {Path(cells['task_file']).name}"
        + ("" if cells["without"] else " (the person's goal live from the synthetic camera and the "
           "goal tracker; the planner's live_goal_sync on)")
        + (f"; processes left out: {', '.join(cells['without'])}" if cells["without"] else "")
        + ". The machine was loaded (2 cores shared with other jobs).",
    )
    alone_rate = _median([o["command_rate_hz"] for o in alone])
    alone_wall = _median([o["task_wall_s"] for o in alone])
    rows = [(f"alone {i + 1}", o) for i, o in enumerate(alone)]
    rows += [(f"pair {i + 1}", o) for i, p in enumerate(cells["pairs"]) for o in p]
    for name, o in rows:
        v = o["vs_reference"]
        t.add(
            run=name,
            prefix=o["prefix"],
            success=o["success"],
            steps=f"{o['steps_succeeded']}/{o['steps_total']}",
            task_sim=o["task_sim_s"],
            up_wall=o["up_wall_s"],
            task_wall=o["task_wall_s"],
            rate=o["command_rate_hz"],
            rate_ratio=_ratio(o["command_rate_hz"], alone_rate),
            arm_rate=o["arm_ticks_per_s"],
            messages=o["messages"],
            foreign=o["foreign_messages"],
            compared=v["common_ticks"],
            differing=v["ticks_differing"],
            dq=v["max_dq_rad"],
            dee=None if v["max_dee_m"] is None else v["max_dee_m"] * 1e3,
        )
    all_ok = all(o["success"] and o["exit_code"] == 0 for o in pair_cells)
    res.verdict(
        "both_cells_complete",
        all_ok,
        "both cells complete the task (every pair run)",
        ", ".join(
            f"{o['prefix']}: {o['steps_succeeded']}/{o['steps_total']} steps, exit {o['exit_code']}"
            for o in pair_cells
        ),
    )
    foreign = sum(o["foreign_messages"] for o in pair_cells)
    res.verdict(
        "no_cross_talk",
        foreign == 0 and all(o["messages"] > 0 for o in pair_cells),
        "no message of another prefix in a cell's recording",
        f"{foreign} foreign messages in {sum(o['messages'] for o in pair_cells)} recorded",
    )
    compared = [o for o in [*alone, *pair_cells] if o is not (alone[0] if alone else pair_cells[0])]
    worst_dee = max((o["vs_reference"]["max_dee_m"] or 0.0) for o in compared)
    worst_dq = max((o["vs_reference"]["max_dq_rad"] or 0.0) for o in compared)
    ref_steps = [s["step"] for s in (alone or pair_cells)[0]["steps"]]
    covered = all(
        o["vs_reference"]["common_ticks"] > 0
        and o["task_end_tick"] is not None
        and o["vs_reference"]["last_tick"] >= o["task_end_tick"]
        for o in compared
    )
    same = (
        covered
        and worst_dq == 0.0
        and worst_dee == 0.0
        and all([s["step"] for s in o["steps"]] == ref_steps for o in compared)
    )
    res.verdict(
        "same_trajectory",
        same,
        f"every cell's arm trajectory equals {cells['reference']}'s, tick by tick, over the whole task",
        f"max |Δq| {worst_dq:.3g} rad, max Δ end effector {worst_dee * 1e3:.3g} mm; ticks compared "
        + ", ".join(str(o["vs_reference"]["common_ticks"]) for o in compared)
        + " (task ends at tick "
        + ", ".join(str(o["task_end_tick"]) for o in compared)
        + ")",
    )
    pair_rate = _median([o["command_rate_hz"] for o in pair_cells])
    pair_wall = _median([o["task_wall_s"] for o in pair_cells])
    if alone_rate is not None and pair_rate is not None:
        res.headline["cells_rate"] = Headline(
            "lockstep rate, each of two cells / one alone",
            round(pair_rate / alone_rate, 2),
            "",
            f"{pair_rate:.0f} vs {alone_rate:.0f} ticks/s; "
            f"the two cells together {2 * pair_rate:.0f} ticks/s",
        )
    if alone_wall is not None and pair_wall is not None:
        res.headline["cells_wall"] = Headline(
            "task wall time, two cells at once vs one alone",
            f"{pair_wall:.1f} vs {alone_wall:.1f}",
            "s",
            "first to last arm command, medians",
        )
    elif pair_wall is not None:
        res.headline["cells_wall"] = Headline(
            "task wall time of a cell of the pair", round(pair_wall, 2), "s", f"{pair_rate:.0f} ticks/s"
        )
    res.headline["cells_cross_talk"] = Headline(
        "messages of the other prefix in a cell's recording",
        foreign,
        "",
        f"{len(pair_cells)} cell recordings",
    )
    res.headline["cells_trajectory"] = Headline(
        f"largest end-effector difference vs {cells['reference']}",
        worst_dee * 1e3,
        "mm",
        f"max |Δq| {worst_dq:.3g} rad",
    )
    res.recordings += cells["recordings"]
    res.config["cells"] = {
        "runs": cells["runs"],
        "task_file": cells["task_file"],
        "without": cells["without"],
        "reference": cells["reference"],
        "alone": [{k: v for k, v in o.items() if k != "states"} for o in alone],
        "pairs": [[{k: v for k, v in o.items() if k != "states"} for o in p] for p in cells["pairs"]],
    }


EXPERIMENT = Experiment(
    name="scale",
    title="Scale: PSM cost vs dimension and segments; two cells on one router",
    run=run,
    description=(
        "Fit and control-step cost of the PSM as the dimension grows (1–7, DMP-50 side by side) "
        "and as the number of segments grows (2–50); two feeding stacks with different prefixes "
        "sharing one router in lockstep, against one alone."
    ),
)
