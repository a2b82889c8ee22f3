"""``psm learn``, ``psm rollout`` and ``psm demo``: the PSM core from the command line.

Demonstration files:

* CSV: an optional header row, then one row per sample; the column ``t`` (or the first column)
  is time [s], the other columns (or those named with ``--columns``) are the positions. A file
  whose first row is all numbers has no header: every row is a sample, the dimensions are named
  ``x0, x1, ...``;
* NPZ: arrays ``t (T,)`` and ``X (T, D)``;
* MCAP: a recording of the arm (``psm teach`` or any run): the end-effector trajectory is taken from
  the arm-state messages on ``--topic`` (default ``<prefix>/arm/state``); a truncated or corrupt
  recording is refused (one line saying how much was readable).

A demonstration that does not move (every sample within :data:`MIN_DISPLACEMENT` of the first)
is refused with one line, e.g. ``demonstration does not move: max displacement 0.0 m over
2.0 s``.
"""

from __future__ import annotations

import argparse
import csv
import inspect
import json
from pathlib import Path

import numpy as np

from psm import PhaseSpaceModel, Rollout
from psm.controller import SYNC_MODES
from psm.errors import DemonstrationError
from psm.fitting import K_FIT_MODES, smooth, validate_demonstration


def check_recording(path: Path) -> None:
    """Raise ``LogReadError`` unless ``path`` is a complete MCAP file: never learn from the first
    part of a motion (a truncated or corrupt recording)."""
    from services.bus.log import LogReadError, scan_log

    scan = scan_log(path)  # LogReadError if it is not MCAP at all
    if not scan.complete:
        raise LogReadError(f"{path}: {scan.problem}")


def load_demonstration(
    path: Path, columns: list[str] | None = None, topic: str | None = None
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read a demonstration file: returns ``t (T,) [s]``, ``X (T, D)`` and the dimension names."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        with np.load(path) as data:
            if "t" not in data or "X" not in data:
                found = ", ".join(f"'{k}'" for k in data.files) or "none"
                raise DemonstrationError(
                    f"{path}: an NPZ demonstration needs arrays 't' and 'X' (found {found})"
                )
            t, X = np.asarray(data["t"], float), np.asarray(data["X"], float)
        X = X[:, None] if X.ndim == 1 else X
        return t, X, [f"x{d}" for d in range(X.shape[1])]
    if suffix == ".csv":
        return _load_csv(path, columns)
    if suffix == ".mcap":
        from services.robot.recordings import ee_trajectory

        check_recording(path)
        t, X = ee_trajectory(path, topic=topic)
        return t, X, ["x", "y", "z"]
    raise DemonstrationError(f"{path}: unknown demonstration format '{suffix}' (use .csv, .npz or .mcap)")


#: A demonstration whose samples all lie within this distance of the first one does not move
#: (Euclidean, in the demonstration's units: m for arm recordings).
MIN_DISPLACEMENT = 1e-6


def check_motion(t: np.ndarray, X: np.ndarray) -> None:
    """Raise :class:`DemonstrationError` if the demonstration ``t (T,) [s]``, ``X (T, D)`` does
    not move: its largest distance from the first sample is below :data:`MIN_DISPLACEMENT`."""
    if len(t) == 0 or X.size == 0:
        return  # too few samples: the core's validation says so
    reach = float(np.max(np.linalg.norm(X - X[0], axis=1)))
    if not np.isfinite(reach):
        return  # NaN/inf: the core's validation names the sample
    if reach < MIN_DISPLACEMENT:
        duration = float(t[-1] - t[0])
        raise DemonstrationError(
            f"demonstration does not move: max displacement {reach:.3g} m over {duration:.3g} s"
        )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _load_csv(path: Path, columns: list[str] | None) -> tuple[np.ndarray, np.ndarray, list[str]]:
    with path.open(newline="") as fh:
        rows = [r for r in csv.reader(fh) if r]
    if rows and all(_is_number(c) for c in rows[0]):  # no header: every row is a sample
        if columns:
            raise DemonstrationError(
                f"{path}: --columns needs a header row naming the columns (the first row is "
                "numbers)"
            )
        rows = [["t", *(f"x{d}" for d in range(len(rows[0]) - 1))], *rows]
    if len(rows) < 2:
        raise DemonstrationError(f"{path}: a CSV demonstration needs samples (after a header row)")
    header = [h.strip() for h in rows[0]]
    time_col = header.index("t") if "t" in header else 0
    names = columns or [h for i, h in enumerate(header) if i != time_col]
    missing = [n for n in names if n not in header]
    if missing:
        raise DemonstrationError(f"{path}: no column named {missing[0]!r} (columns: {', '.join(header)})")
    idx = [header.index(n) for n in names]
    try:
        data = np.array([[float(r[time_col])] + [float(r[i]) for i in idx] for r in rows[1:]])
    except (ValueError, IndexError) as exc:
        raise DemonstrationError(f"{path}: not numeric ({exc})") from None
    return data[:, 0], data[:, 1:], names


def _parse_vector(text: str | None, name: str) -> np.ndarray | None:
    if text is None:
        return None
    try:
        return np.array([float(v) for v in text.replace(",", " ").split()])
    except ValueError:
        raise DemonstrationError(f"--{name}: expected numbers separated by commas, got {text!r}") from None


def plot_rollout(
    path: Path, rollout: Rollout, model: PhaseSpaceModel, names: list[str],
    demo: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Write position-vs-time and phase-space (velocity vs position) plots of a rollout to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    D = rollout.x.shape[1]
    if demo is not None:
        smoothed = smooth(*validate_demonstration(*demo), model.parameters.smoothing)
        demo_x, demo_v = smoothed.x, smoothed.v
    fig, axes = plt.subplots(2, D, figsize=(4.2 * D, 7), squeeze=False)
    for d in range(D):
        ax_t, ax_p = axes[0, d], axes[1, d]
        if demo is not None:
            t_demo, X_demo = demo
            ax_t.plot(t_demo - t_demo[0], X_demo[:, d], "k-", lw=1.0, label="demonstration")
            ax_p.plot(demo_x[:, d], demo_v[:, d], "k-", lw=1.0, label="demonstration (smoothed)")
        ax_t.plot(rollout.t, rollout.x[:, d], "C0--", lw=1.5, label="PSM")
        ax_t.plot(rollout.t, rollout.goal[:, d], "C3:", lw=1.0, label="goal")
        ax_p.plot(rollout.x[:, d], rollout.v[:, d], "C0--", lw=1.5, label="PSM")
        vp = model.via_points[d]
        ax_p.plot(rollout.goal[-1, d] + vp.position, vp.velocity, "C1o", ms=4, label="via-points")
        ax_t.set_title(f"{names[d]}: position")
        ax_t.set_xlabel("t [s]")
        ax_p.set_title(f"{names[d]}: phase space")
        ax_p.set_xlabel("position")
        ax_p.set_ylabel("velocity")
        ax_t.grid(alpha=0.3)
        ax_p.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    axes[1, 0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _segments_arg(text: str) -> str | int | list[float]:
    if text == "auto":
        return "auto"
    if "," in text:
        return [float(v) for v in text.split(",")]
    return int(text)


def _times_arg(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def cmd_learn(args: argparse.Namespace) -> int:
    """``psm learn DEMO -o MODEL``."""
    t, X, names = load_demonstration(Path(args.demo), args.columns, args.topic)
    check_motion(t, X)
    options = {  # only what was given: the model's own defaults stay the single source
        name: value
        for name, value in (
            ("segments", args.segments),
            ("smoothing", args.smoothing),
            ("k_fit", args.k_fit),
            ("auto_tolerance", args.auto_tolerance),
            ("sync_mode", args.sync),
            ("start_shift", args.start_shift or None),
            ("velocity_extrema", args.velocity_extrema),
            ("via_point_times", args.via_points),
        )
        if value is not None
    }
    model = PhaseSpaceModel.fit(t, X, **options)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    model.save(out)
    print(
        f"learned {model!r} from {len(t)} samples x {X.shape[1]} dims "
        f"({', '.join(names)}); segments per dim: {[len(k) for k in model.k]} -> {out}"
    )
    if args.plot:
        r = model.rollout(model.start, dt=float(np.median(np.diff(t))))
        plot_rollout(Path(args.plot), r, model, names, (t, X))
        print(f"plot -> {args.plot}")
    return 0


def cmd_rollout(args: argparse.Namespace) -> int:
    """``psm rollout MODEL [--start ...] [--goal ...] [--plot out.png] [--csv out.csv]``."""
    model = PhaseSpaceModel.load(Path(args.model))
    goal = _parse_vector(args.goal, "goal")
    start = _parse_vector(args.start, "start")
    r = model.rollout(start, goal=goal, dt=args.dt, max_duration=args.max_duration)
    names = [f"x{d}" for d in range(model.dim)]
    print(
        json.dumps(
            {
                "done": r.done,
                "duration_s": float(r.t[-1]),
                "final_position": r.x[-1].tolist(),
                "goal": r.goal[-1].tolist(),
                "max_abs_acceleration": np.max(np.abs(r.a), axis=0).tolist(),
            }
        )
    )
    if args.csv:
        header = ["t"] + [f"{n}{s}" for s in ("", "_v", "_a") for n in names]
        data = np.column_stack([r.t, r.x, r.v, r.a])
        np.savetxt(args.csv, data, delimiter=",", header=",".join(header), comments="")
    if args.plot:
        plot_rollout(Path(args.plot), r, model, names)
    return 0


#: The committed kinesthetic demonstration the demo learns from (repository checkout).
DEMO_RECORDING = Path(__file__).resolve().parents[1] / "data" / "demos" / "reach_person.mcap"


def _synthetic_reach() -> tuple[np.ndarray, np.ndarray]:
    """A 2 s, 3-D minimum-jerk reach at 500 Hz with 50 µm noise: ``t (T,)`` [s], ``X (T, 3)`` [m]."""
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    s = np.clip(t / 2.0, 0, 1)
    s = 10 * s**3 - 15 * s**4 + 6 * s**5
    X = np.stack([0.4 * s, 0.2 * np.sin(np.pi * s), 0.1 * np.sin(2 * np.pi * s)], axis=1)
    return t, X + np.random.default_rng(0).normal(0.0, 5e-5, X.shape)


def cmd_demo(args: argparse.Namespace) -> int:
    """``psm demo``: learn the feeding task's last sub-task (reach the person) from its committed
    kinesthetic recording, then show goal adaptation, a goal that moves mid-motion and a push."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if DEMO_RECORDING.exists():
        t, X, names = load_demonstration(DEMO_RECORDING)
        source = f"{DEMO_RECORDING.name} (joint states -> forward kinematics)"
    else:  # installed without the repository's data folder
        (t, X), names = _synthetic_reach(), ["x", "y", "z"]
        source = "a synthetic minimum-jerk reach"
    model = PhaseSpaceModel.fit(t, X)
    model.save(out / "model.json")
    dt = float(np.median(np.diff(t)))
    plot_rollout(out / "reproduction.png", model.rollout(dt=dt), model, names, (t, X))
    # The person sits 10 cm further left and 5 cm lower than in the demonstration.
    moved = model.goal + np.array([0.0, 0.10, -0.05])
    plot_rollout(out / "goal_adapted.png", model.rollout(dt=dt, goal=moved), model, names, (t, X))
    # The person moves while the arm is on its way (at 40 % of the motion).
    t_move = 0.4 * model.duration
    g0 = model.goal
    moving = model.rollout(dt=dt, goal_fn=lambda s: g0 if s < t_move else moved)
    plot_rollout(out / "goal_moved.png", moving, model, names, (t, X))
    push_step = round(0.3 * model.duration / dt)

    def push(s: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if round(s / dt) == push_step:  # one shove against the motion along y
            v = v.copy()
            v[1] -= 0.3
        return x, v

    pushed = model.rollout(dt=dt, disturbance=push)
    plot_rollout(out / "pushed.png", pushed, model, names, (t, X))
    print(f"learned {model!r} from {source}")
    for label, r in (("goal moved", moving), ("pushed", pushed)):
        print(f"  {label}: reached the goal: {r.done}, in {r.t[-1]:.2f} s, "
              f"final error {np.linalg.norm(r.x[-1] - r.goal[-1]) * 1e3:.2f} mm")
    print(f"plots and model written to {out}/")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``learn``, ``rollout`` and ``demo`` to the ``psm`` command line."""
    p = subparsers.add_parser("learn", help="learn a PSM from one demonstration (CSV, NPZ, MCAP)")
    p.add_argument("demo", help="demonstration file (.csv, .npz or .mcap)")
    p.add_argument("-o", "--output", default="model.json", help="model file to write (JSON)")
    default = {name: par.default for name, par in inspect.signature(PhaseSpaceModel.fit).parameters.items()}
    p.add_argument("--segments", type=_segments_arg,
                   help="'auto', a number of segments, or comma-separated cut times [s] "
                   f"(default {default['segments']})")
    p.add_argument("--smoothing", type=float,
                   help=f"Gaussian smoothing sigma [s] (default {default['smoothing']})")
    p.add_argument("--k-fit", choices=K_FIT_MODES,
                   help=f"how each segment's k is chosen (default {default['k_fit']})")
    p.add_argument("--auto-tolerance", type=float,
                   help="'auto' segmentation: position budget per segment, share of the range "
                   f"(default {default['auto_tolerance']})")
    p.add_argument("--sync", choices=SYNC_MODES,
                   help="synchronisation of the dimensions: 'scale' (time scaling) or 'brake' "
                   f"(the paper's eq. 14) (default {default['sync_mode']})")
    p.add_argument("--start-shift", action="store_true",
                   help="spread a start offset over the motion (fading to 0 at the goal)")
    p.add_argument("--via-points", type=_times_arg, metavar="T1,T2,..",
                   help="demonstration times [s] of via-points to keep with the demonstrated velocity")
    p.add_argument("--velocity-extrema", action=argparse.BooleanOptionalAction, default=None,
                   help="keep the demonstration's speed peaks and dips as via-points "
                        "(default: on; --no-velocity-extrema: the segmentation alone)")
    p.add_argument("--columns", nargs="+", help="CSV columns to learn (default: all but t)")
    p.add_argument("--topic", help="MCAP: arm-state topic (default <prefix>/arm/state)")
    p.add_argument("--plot", help="also write a reproduction plot (PNG)")
    p.set_defaults(func=cmd_learn)

    p = subparsers.add_parser("rollout", help="generate a motion from a learned model")
    p.add_argument("model", help="model file (JSON) written by 'psm learn'")
    p.add_argument("--goal", help="goal, comma-separated (default: the demonstration's)")
    p.add_argument("--start", help="start position, comma-separated (default: the demonstration's)")
    p.add_argument("--dt", type=float, default=0.002, help="control period [s]")
    p.add_argument("--max-duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--plot", help="write position and phase-space plots (PNG)")
    p.add_argument("--csv", help="write the rollout (t, x, v, a) as CSV")
    p.set_defaults(func=cmd_rollout)

    p = subparsers.add_parser("demo", help="learn a committed demonstration, adapt it, write plots")
    p.add_argument("--out", default="out/demo", help="output folder")
    p.set_defaults(func=cmd_demo)
