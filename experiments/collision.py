"""Experiment 2 of the paper (§IV-C, Fig. 8): collision avoidance on the way to the person.

The feeding task of ``configs/feeding.toml`` with a wall between the scoop and the person
(``configs/obstacles/paper_wall.toml``: a box 0.40 × 0.03 × 0.23 m centred at (0.50, 0.465,
0.115) m), known to the obstacle monitor in advance, against the same task without it. The
step the paper uses is reach_person: its lateral component (y) has to brake in front of the wall
while the vertical one (z) rises, and resumes once z has cleared the wall's top.

Variations (:func:`walls`): the wall's position along the path (its centre y ∈ {0.465, 0.490,
0.515} m: the face the end effector stops at moves towards the person) × its height (0.17, 0.20,
0.23 m; standing on the table, so the top the end effector must clear rises); the paper's wall
is (0.465 m, 0.23 m). A quick run has the paper's wall only.

Every run is the stack's control loop in process (:func:`experiments.harness.run_in_process`,
settings of ``configs/stack.toml``: the segment test inflates the wall by ``margin_m +
tool_radius_m`` = 0.18 m, the whole-arm clearance checks every ``clearance_every`` ticks), which
is a lockstep stack run bit for bit (docs/experiments.md, "In-process harness"). The person's
goal: the true mouth position, still, at 30 Hz.

Metrics per run:

* ``EE clearance`` [m]: the smallest distance from the end-effector point to the wall over the
  whole task; ``safety volume`` [m]: the same to the volume inflated by 0.18 m (≥ 0: never
  entered; the stop lands on its face);
* ``arm clearance`` [m]: the smallest distance between the arm's links (convex hulls of the
  robot as the arm service loads it, :class:`services.robot.clearance.ArmClearance`, no margin)
  and the wall, every 5th tick of the whole task;
* ``peak lateral speed`` [m/s]: the largest ``v_y`` in reach_person; ``held``: the largest ``v_y``
  while the end effector is below the top of the inflated wall and the monitor predicts the
  collision (the planner's stop on y is set, eq. 15), and ``below the top``: the same without
  the second condition, so it includes the moments after the release, when the straight path
  to the via-point already clears the volume's upper edge and y sets off while z climbs the
  rest; each ratio is with / without the wall (the free run's largest ``v_y`` below the top);
  ``release`` [m]: the height of the end effector above the top of the inflated wall when the
  stop is released (negative: below it);
* ``collision stops``: predicted collisions the planner acted on (eq. 15); ``protective stops``:
  the monitor's whole-arm stops;
* ``success``: the task completed (the person reached within 1 cm) with the arm clear of the
  wall and the end effector outside its safety volume;
* ``duration`` [s]: reach_person's and the task's, and the extra time the wall costs.

Recordings: ``collision_<run>.mcap`` per run as a stack recording under the prefix ``psm``,
with the obstacle set (``psm/obstacles``, ``psm/viz/scene``).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from experiments.registry import Experiment, Progress
from experiments.result import Column, ExperimentResult, Figure, Headline

WALL_CENTRE_Y_M = (0.465, 0.490, 0.515)
WALL_HEIGHT_M = (0.17, 0.20, 0.23)
WALL_X_M, WALL_LENGTH_M, WALL_THICKNESS_M = 0.50, 0.40, 0.03
PAPER = (0.465, 0.23)
STEP = "reach_person"
LATERAL = 1  # y
CLEARANCE_EVERY = 5  # ticks between the exact whole-arm clearances of the metric
#: Targets: the lateral speed while the collision stop is set and the end effector is below the
#: wall's top at most this share of the free run's peak below the top; the end effector's stop on
#: the safety volume's face within this [m] (the braking law's last tick).
SLOWDOWN_TARGET = 0.5
FACE_TOL_M = 1e-4


def wall(centre_y: float, height: float, oid: str = "wall") -> Any:
    """A wall like the paper's: 0.40 m along x, 0.03 m thick, ``height`` [m] standing on the
    table, centred at ``y = centre_y`` [m]."""
    from psm.obstacles import Obstacle

    return Obstacle(oid, "box", np.array([WALL_X_M, centre_y, 0.5 * height]),
                    size=np.array([WALL_LENGTH_M, WALL_THICKNESS_M, height]))


def walls(quick: bool) -> list[tuple[str, float, float]]:
    """The runs' walls as ``(name, centre y [m], height [m])``; the paper's first."""
    cells = [(y, h) for y in WALL_CENTRE_Y_M for h in WALL_HEIGHT_M]
    cells.sort(key=lambda c: c != PAPER)
    if quick:
        cells = cells[:1]
    return [(f"y{1e3 * y:.0f}_h{1e3 * h:.0f}", y, h) for y, h in cells]


def box_distance(x: np.ndarray, ob: Any, inflate_m: float = 0.0) -> np.ndarray:
    """Signed distance [m] of the points ``x (N, 3)`` to the box ``ob`` grown by ``inflate_m``
    (negative inside: minus the depth)."""
    rot = Rotation.from_quat(ob.orientation)
    local = rot.inv().apply(np.asarray(x, dtype=float) - ob.position)
    half = 0.5 * np.asarray(ob.size) + inflate_m
    q = np.abs(local) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


def arm_clearance(q: np.ndarray, ob: Any, robot: Any) -> tuple[float, str]:
    """The smallest link–wall distance [m] over the joint states ``q (N, n)`` (every
    :data:`CLEARANCE_EVERY`-th) and the closest link."""
    from services.robot.clearance import ArmClearance

    check = ArmClearance(robot, margin_m=0.0, cutoff_m=2.0)
    check.set_obstacles([ob])
    best, link = np.inf, ""
    for qi in q[::CLEARANCE_EVERY]:
        r = check.check(qi)
        if r.min_distance_m < best:
            best, link = float(r.min_distance_m), r.link
    return best, link


def step_mask(res: Any, name: str = STEP) -> np.ndarray:
    """Rows of the trace in step ``name``."""
    idx = next(i for i, r in enumerate(res.runner.reports) if r.name == name)
    return res.trace["step"] == idx


def lateral(res: Any, top_m: float) -> dict[str, float]:
    """reach_person's peak lateral speed [m/s]: overall (``peak_vy``), while below ``top_m`` [m]
    (``peak_vy_below``) and while below it with a collision predicted, the planner's collision
    stop set (``peak_vy_held``; 0 when there never is one; for these walls the stop is on y, the
    end effector's path entering the safety volume through the face towards the scoop);
    ``release_m`` [m]: the end effector's height above ``top_m`` at the first state after the
    step's last collision prediction (NaN: no prediction, or none released in the step)."""
    m = step_mask(res)
    v, x = res.trace["v"][m], res.trace["x"][m]
    collision = res.trace["collision"][m]
    below = x[:, 2] < top_m
    held = below & collision
    predicted = np.flatnonzero(collision)
    release = predicted[-1] + 1 if predicted.size else x.shape[0]
    return {"peak_vy": float(v[:, LATERAL].max()),
            "peak_vy_below": float(v[below, LATERAL].max()) if below.any() else 0.0,
            "peak_vy_held": float(v[held, LATERAL].max()) if held.any() else 0.0,
            "release_m": float(x[release, 2] - top_m) if release < x.shape[0] else math.nan}


def _height_words(dz_m: float) -> str:
    """``dz_m`` [m] above (positive) or below a height, in words."""
    if math.isnan(dz_m):
        return "never released, at"
    return f"{abs(1e3 * dz_m):.1f} mm {'above' if dz_m >= 0.0 else 'below'}"


def step_duration(res: Any, name: str = STEP) -> float:
    """The step's duration [s] (NaN if it did not end)."""
    s = next(s for s in res.summary["steps"] if s["step"] == name)
    return float(s["duration_s"]) if s["duration_s"] is not None else float("nan")


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------


def _rect(ax: Any, lo: tuple[float, float], hi: tuple[float, float], **kw: Any) -> None:
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle(lo, hi[0] - lo[0], hi[1] - lo[1], fill=False, **kw))


def plot_paths(free: Any, runs: list[tuple[str, Any, Any]], inflate_m: float, person: Any,
               path: Path) -> None:
    """reach_person's end-effector paths, top view (x-y) and side view (y-z), around the walls."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, side) = plt.subplots(1, 2, figsize=(12.0, 5.5), dpi=120)
    mf = step_mask(free)
    xf = free.trace["x"][mf]
    colours = plt.cm.plasma(np.linspace(0.0, 0.85, max(1, len(runs))))
    for (name, ob, res), c in zip(runs, colours, strict=True):
        x = res.trace["x"][step_mask(res)]
        paper = name == walls(True)[0][0]
        lw = 2.0 if paper else 0.9
        top.plot(x[:, 0], x[:, 1], color=c, lw=lw, label=f"wall {name}" + (" (paper)" if paper else ""))
        side.plot(x[:, 1], x[:, 2], color=c, lw=lw)
        lo, hi = ob.position - 0.5 * ob.size, ob.position + 0.5 * ob.size
        if paper:
            _rect(top, (lo[0], lo[1]), (hi[0], hi[1]), color=c, lw=1.5)
            _rect(top, (lo[0] - inflate_m, lo[1] - inflate_m), (hi[0] + inflate_m, hi[1] + inflate_m),
                  color=c, lw=0.8, ls="--")
            _rect(side, (lo[1] - inflate_m, lo[2] - inflate_m), (hi[1] + inflate_m, hi[2] + inflate_m),
                  color=c, lw=0.8, ls="--")
        _rect(side, (lo[1], lo[2]), (hi[1], hi[2]), color=c, lw=1.5 if paper else 0.7)
    for ax, (i, j) in ((top, (0, 1)), (side, (1, 2))):
        ax.plot(xf[:, i], xf[:, j], "k--", lw=1.5, label="no wall" if ax is top else None)
        ax.plot(person[i], person[j], "k*", ms=12, label="person" if ax is top else None)
    top.plot([], [], "k--", lw=0.8, label=f"safety volume (+{inflate_m:.2f} m), paper's wall")
    top.set(title="reach_person, top view", xlabel="x [m]", ylabel="y [m]")
    side.set(title="reach_person, side view (walls solid)", xlabel="y [m]", ylabel="z [m]")
    for ax in (top, side):
        ax.set_aspect("equal", adjustable="datalim")
    top.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_lateral(free: Any, runs: list[tuple[str, Any, Any]], inflate_m: float, path: Path) -> None:
    """v_y (top) and z (bottom) over the time in reach_person, with and without the walls."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (av, az) = plt.subplots(2, 1, figsize=(9.0, 7.0), dpi=120, sharex=True)
    colours = plt.cm.plasma(np.linspace(0.0, 0.85, max(1, len(runs))))
    for (name, ob, res), c in zip(runs, colours, strict=True):
        m = step_mask(res)
        t = res.trace["t"][m] - res.trace["t"][m][0]
        paper = name == walls(True)[0][0]
        lw = 2.0 if paper else 0.8
        label = f"wall {name}" + (" (paper)" if paper else "")
        av.plot(t, res.trace["v"][m][:, LATERAL], color=c, lw=lw, label=label)
        az.plot(t, res.trace["x"][m][:, 2], color=c, lw=lw)
        if paper:
            az.axhline(ob.position[2] + 0.5 * ob.size[2] + inflate_m, color=c, ls=":", lw=1,
                       label="top of the paper wall's safety volume")
    m = step_mask(free)
    t = free.trace["t"][m] - free.trace["t"][m][0]
    av.plot(t, free.trace["v"][m][:, LATERAL], "k--", lw=1.5, label="no wall")
    az.plot(t, free.trace["x"][m][:, 2], "k--", lw=1.5)
    av.set(title="reach_person: lateral velocity with and without the wall", ylabel="v_y [m/s]")
    az.set(xlabel="time in reach_person [s]", ylabel="z [m]")
    av.legend(fontsize=7)
    az.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# The experiment
# --------------------------------------------------------------------------------------------


def run(out_dir: Path, *, seed: int, quick: bool, progress: Progress) -> ExperimentResult:
    """The run without a wall and one per wall of :func:`walls` into ``out_dir``."""
    from experiments.harness import TraceWriter, feeding_models, robot_model, run_in_process, stack_settings
    from services.tasks.feeding import load_feeding

    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = load_feeding()
    models = feeding_models(cfg.task)
    settings = stack_settings()
    robot = robot_model(settings)
    joint_names = list(robot.joint_names)
    inflate = settings.monitor["margin_m"] + settings.monitor["tool_radius_m"]
    person = np.asarray(cfg.scene.person, dtype=float)

    def goals(_t: float) -> dict[str, tuple[np.ndarray, bool]]:
        return {"person": (person, True)}

    cells = walls(quick)
    total = 1 + len(cells)
    recordings: list[str] = []

    def record(name: str, res: Any, obstacles: list[Any], meta: dict[str, str]) -> None:
        fname = f"collision_{name}.mcap"
        with TraceWriter(out_dir / fname) as w:
            w.metadata("psm.experiment", {"experiment": "collision", "run": name, **meta})
            w.write_obstacles("psm", obstacles, inflate)
            w.write_run("psm", res, joint_names)
        recordings.append(fname)

    t0 = time.perf_counter()
    free = run_in_process(cfg, models, settings, goals=goals)
    free_wall = time.perf_counter() - t0
    record("no_wall", free, [], {})
    progress(1, total, "no wall")
    runs: list[tuple[str, Any, Any]] = []
    rows: list[dict[str, Any]] = []
    for done, (name, y, h) in enumerate(cells, start=2):
        ob = wall(y, h)
        t0 = time.perf_counter()
        res = run_in_process(cfg, models, settings, obstacles=[ob], goals=goals)
        wall_s = time.perf_counter() - t0
        runs.append((name, ob, res))
        record(name, res, [ob], {"centre_y_m": f"{y:.3f}", "height_m": f"{h:.3f}"})
        tr = res.trace
        top = float(ob.position[2] + 0.5 * ob.size[2] + inflate)
        with_lat, free_lat = lateral(res, top), lateral(free, top)
        ee = box_distance(tr["x"], ob)
        arm, link = arm_clearance(tr["q"], ob, robot)
        safety = float(box_distance(tr["x"], ob, inflate).min())
        # The free run against the same wall: how close it would have come.
        free_arm, _ = arm_clearance(free.trace["q"], ob, robot)
        success = bool(res.summary["success"]) and arm > 0.0 and safety > -FACE_TOL_M
        d_with, d_free = step_duration(res), step_duration(free)
        rows.append({
            "run": name, "paper": (y, h) == PAPER, "centre_y_m": y, "height_m": h, "success": success,
            "task_success": bool(res.summary["success"]),
            "ee_clearance_m": float(ee.min()), "safety_volume_m": safety, "arm_clearance_m": arm,
            "closest_link": link, "free_arm_clearance_m": free_arm,
            "free_ee_clearance_m": float(box_distance(free.trace["x"], ob).min()),
            "peak_vy_mps": with_lat["peak_vy"], "free_peak_vy_mps": free_lat["peak_vy"],
            "peak_vy_ratio": with_lat["peak_vy"] / free_lat["peak_vy"],
            "peak_vy_below_mps": with_lat["peak_vy_below"],
            "free_peak_vy_below_mps": free_lat["peak_vy_below"],
            "slowdown_ratio": with_lat["peak_vy_below"] / free_lat["peak_vy_below"],
            "peak_vy_held_mps": with_lat["peak_vy_held"],
            "held_ratio": with_lat["peak_vy_held"] / free_lat["peak_vy_below"],
            "release_m": with_lat["release_m"],
            "collision_stops": int(res.runner.collision_stops),
            "protective_stops": int(res.monitor.protective_stops),
            "step_duration_s": d_with, "extra_s": d_with - d_free,
            "task_duration_s": res.summary["duration_s"], "wall_s": wall_s,
        })
        progress(done, total, f"wall {name}")

    out = ExperimentResult(
        name="collision", title=EXPERIMENT.title, seed=seed, description=EXPERIMENT.description,
        config={"walls": [{"run": n, "centre_y_m": y, "height_m": h} for n, y, h in cells],
                "wall_x_m": WALL_X_M, "wall_length_m": WALL_LENGTH_M, "wall_thickness_m": WALL_THICKNESS_M,
                "segment_inflation_m": inflate, "monitor": settings.monitor, "step": STEP, "quick": quick,
                "stack_file": "configs/stack.toml", "arm_clearance_every_ticks": CLEARANCE_EVERY,
                "seed_note": "deterministic: no random input"},
        recordings=recordings,
    )
    tab = out.table("Per wall", [
        Column("run", "wall"), Column("centre_y_m", "centre y", "m", 3), Column("height_m", "height", "m", 2),
        Column("success", "success"), Column("ee_clearance_m", "EE clearance", "m", 3),
        Column("safety_volume_m", "EE to safety volume", "m", 4),
        Column("arm_clearance_m", "arm clearance", "m", 3), Column("closest_link", "closest link"),
        Column("peak_vy_held_mps", "peak v_y held (stop set, below the top)", "m/s", 3),
        Column("held_ratio", "held / no wall", "", 3),
        Column("release_m", "released at, above the top", "m", 4),
        Column("peak_vy_below_mps", "peak v_y below the top", "m/s", 3),
        Column("free_peak_vy_below_mps", "same, no wall", "m/s", 3),
        Column("slowdown_ratio", "below the top / no wall", "", 3),
        Column("peak_vy_mps", "peak v_y", "m/s", 3), Column("peak_vy_ratio", "peak v_y / no wall", "", 2),
        Column("collision_stops", "collision stops", digits=0),
        Column("protective_stops", "protective stops", digits=0),
        Column("step_duration_s", f"{STEP} duration", "s", 2), Column("extra_s", "extra time", "s", 2),
        Column("task_duration_s", "task duration", "s", 2), Column("wall_s", "wall time", "s", 1),
    ], note="EE to safety volume: the end effector's distance to the wall inflated by the segment test's "
            f"{inflate:.2f} m (0 = on its face)")
    for r in rows:
        tab.add(**{c.key: r[c.key] for c in tab.columns})
    ref = out.table("Without the wall", [
        Column("run", "wall it is measured against"), Column("free_ee_clearance_m", "EE clearance", "m", 3),
        Column("free_arm_clearance_m", "arm clearance", "m", 3),
    ], note=f"the same task without any obstacle (task {free.summary['duration_s']:.2f} s, "
            f"{STEP} {step_duration(free):.2f} s, wall time {free_wall:.1f} s): it would pass through "
            "the wall")
    for r in rows:
        ref.add(run=r["run"], free_ee_clearance_m=r["free_ee_clearance_m"],
                free_arm_clearance_m=r["free_arm_clearance_m"])

    plot_paths(free, runs, inflate, person, out_dir / "paths.png")
    out.figures.append(Figure("paths.png", "reach_person's end-effector paths around the walls: top view "
                              "and side view, without the wall dashed, the paper's wall bold"))
    plot_lateral(free, runs, inflate, out_dir / "lateral_velocity.png")
    out.figures.append(Figure("lateral_velocity.png", "reach_person's lateral velocity v_y and height z over "
                              "time with and without the walls"))

    paper = next(r for r in rows if r["paper"])
    n_ok = sum(r["success"] for r in rows)
    out.headline["success"] = Headline("runs succeeded", n_ok, "", f"of {len(rows)} walls")
    out.headline["min_arm_clearance"] = Headline(
        "min arm clearance", min(r["arm_clearance_m"] for r in rows), "m", "over every wall")
    out.headline["min_ee_clearance"] = Headline(
        "min EE clearance", min(r["ee_clearance_m"] for r in rows), "m", "over every wall")
    out.headline["paper_slowdown"] = Headline(
        "lateral speed below the wall's top, paper's wall / no wall", paper["slowdown_ratio"], "",
        f"{paper['peak_vy_below_mps']:.3f} vs {paper['free_peak_vy_below_mps']:.3f} m/s")
    held_worst = max(rows, key=lambda r: r["held_ratio"])
    out.headline["held_slowdown"] = Headline(
        "lateral speed while the stop holds y, worst wall / no wall", held_worst["held_ratio"], "",
        f"wall {held_worst['run']}: {held_worst['peak_vy_held_mps']:.3f} vs "
        f"{held_worst['free_peak_vy_below_mps']:.3f} m/s")
    out.headline["paper_extra_time"] = Headline(f"{STEP}: extra time, paper's wall", paper["extra_s"], "s")
    out.verdict("avoids_the_wall", all(r["success"] for r in rows),
                "the person is reached with the arm clear of the wall (paper: the spoon is brought to the "
                "user around the obstacle)", f"{n_ok}/{len(rows)}; min arm clearance "
                f"{min(r['arm_clearance_m'] for r in rows):.3f} m, EE never inside the safety volume: "
                f"{all(r['safety_volume_m'] > -FACE_TOL_M for r in rows)}")
    worst_held = max(r["held_ratio"] for r in rows)
    worst = max(rows, key=lambda r: r["slowdown_ratio"])
    # (A wall that never stopped y has no held phase: its ratio 0 proves nothing, so it fails.)
    held_everywhere = all(r["peak_vy_held_mps"] > 0.0 for r in rows)
    out.verdict("lateral_slows_down", held_everywhere and worst_held <= SLOWDOWN_TARGET,
                "y slows down while the wall blocks its path (paper: the y component decreased its "
                "velocity until z had cleared the obstacle): peak v_y while the stop is set and the end "
                f"effector below the top ≤ {SLOWDOWN_TARGET}× the free run's peak below the top",
                f"worst ratio {worst_held:.3f}, paper's wall {paper['held_ratio']:.3f}"
                f"{'' if held_everywhere else ' (a wall without a held phase)'}; below the top "
                f"including after the release: worst {worst['slowdown_ratio']:.3f} (wall {worst['run']}: "
                f"the stop released {_height_words(worst['release_m'])} the top, where the straight path "
                "to the via-point already clears the safety volume)")
    resumed = all(r["peak_vy_ratio"] >= 0.5 for r in rows)
    out.verdict("lateral_resumes", resumed,
                "y resumes once z has cleared the wall (paper: y resumed its normal trajectory): peak v_y "
                "≥ 0.5× the free run's", f"min peak v_y ratio {min(r['peak_vy_ratio'] for r in rows):.2f}")
    return out


EXPERIMENT = Experiment(
    name="collision",
    title="Collision avoidance",
    run=run,
    description="The paper's experiment 2: a wall between the scoop and the person (configs/obstacles/"
    "paper_wall.toml) and 3 positions × 3 heights of it, against the task without it, in process "
    "(lockstep-equivalent).",
)
