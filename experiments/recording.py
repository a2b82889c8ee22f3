"""``psm report RUN.mcap``: a recording of a stack run (``psm up --record RUN.mcap``) as a result.

From the recording (:func:`recording_result`):

* the task's steps from the planner's events (``<prefix>/task/events``: each step's ``STARTED``
  and ``STEP_COMPLETED`` or ``ABORTED``; a step still running when the recording ends is
  *incomplete*), the arm's states (``<prefix>/arm/state``: end-effector position, velocity,
  ``dt_s``), the planner's commands (``<prefix>/arm/command``: the commanded acceleration), its
  status (``<prefix>/planner/status``: each dimension's time to go ``t_e`` at 20 Hz), the goal in
  use (``<prefix>/planner/goal``) and the obstacle monitor's predictions (``<prefix>/collision``);
* the models the planner ran: learned from the demonstrations of the task file (default
  ``configs/feeding.toml``, :func:`services.planner.models.load_task_models`, cached as the
  planner caches them), and the demonstrations' end-effector trajectories.

Per step it writes three plots and one table row:

* the executed trajectory against the demonstration, per dimension over time and as a 3-D/top
  view (``step<i>_<name>_trajectory.png``, ``..._path.png``);
* the phase space relative to the goal (position minus the goal in use): position--velocity and
  position--acceleration (the planner's commanded acceleration) of the run and of the smoothed
  demonstration, with the PSTF line of every segment of the model (``..._phase.png``);
* the time synchronisation (``..._sync.png``): ``t_e`` of each dimension at every tick,
  reconstructed by stepping the step's controller (the model, the step's controller options,
  the goal in use, the collision stops the planner applied) on the recorded states, with the
  values the planner reported in its status as markers; the table gives the largest
  difference between the two;
* duration (first to last tick of the step, s), final error (distance from the goal in use at the
  step's last tick, mm), peak speed (largest ``|v|`` over the step, m/s) and its ratio to the
  demonstration's, the peak commanded acceleration (m/s²).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from experiments import plots
from experiments.result import Column, ExperimentResult, Figure, Headline

__all__ = ["StepWindow", "read_recording", "recording_result"]

#: The streams the report reads (the camera images, the bulk of a recording, are not decoded).
_TOPICS = ("**/arm/state", "**/arm/command", "**/planner/status", "**/planner/goal", "**/task/events",
           "**/collision")


@dataclass
class StepWindow:
    """One step of the task as recorded: its ticks ``start_tick .. end_tick`` (inclusive), the
    outcome and, when completed, the planner's figures (``summary``)."""

    name: str
    index: int
    start_tick: int
    end_tick: int = -1
    outcome: str = "incomplete"
    summary: dict[str, Any] = field(default_factory=dict)
    #: The first tick the step's controller was stepped on: a step that starts when the one
    #: before it completes is started after that state was answered, so from the next one.
    control_tick: int = 0


@dataclass
class Recording:
    """What the report needs from a recording (arrays sorted by tick).

    ``ticks (N,)``; ``stamp_ns (N,)``; ``x, v (N, 3)`` [m, m/s] end-effector position and
    velocity; ``dt (N,)`` [s]; ``a_cmd (N, 3)`` [m/s²] the commanded acceleration (NaN where
    no command was recorded); ``status``: ``(state_tick, step, t_e (3,))`` of every planner
    status; ``goals``: ``(stamp_ns, (6,))`` of the planner's goal in use: position [m] and the
    goal's velocity [m/s] its motion was relative to (zero for a static goal);
    ``predictions``: ``(state_tick, collision, stop (3,), protective_stop)``."""

    path: Path
    prefix: str
    ticks: NDArray[np.int64]
    stamp_ns: NDArray[np.int64]
    x: NDArray[np.float64]
    v: NDArray[np.float64]
    dt: NDArray[np.float64]
    a_cmd: NDArray[np.float64]
    steps: list[StepWindow]
    status: list[tuple[int, str, NDArray[np.float64]]]
    goals: list[tuple[int, NDArray[np.float64]]]  # (stamp_ns, position + velocity (6,))
    predictions: list[tuple[int, bool, NDArray[np.float64], bool]]
    task_name: str = ""
    counts: dict[str, int] = field(default_factory=dict)

    def index_of(self, tick: int) -> int:
        """The row of ``tick`` (the last row at or before it)."""
        return max(0, int(np.searchsorted(self.ticks, tick, side="right")) - 1)


def read_recording(path: Path) -> Recording:
    """Read the arm, planner and monitor streams of a stack recording. ValueError when it has no
    arm state or no task events (it is not a recording of a stack run)."""
    from services.bus.log import read_log
    from services.bus.messages import (
        ArmCommand,
        ArmState,
        CollisionPrediction,
        Goal,
        PlannerStatus,
        TaskEvent,
    )

    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    states: dict[int, tuple[int, list[float], list[float], float]] = {}
    commands: dict[int, list[float]] = {}
    status: list[tuple[int, str, NDArray[np.float64]]] = []
    goals: list[tuple[int, NDArray[np.float64]]] = []
    predictions: list[tuple[int, bool, NDArray[np.float64], bool]] = []
    events: list[Any] = []
    counts: dict[str, int] = {}
    prefix = ""
    for key, msg, _stamp in read_log(path, list(_TOPICS)):
        suffix = key.split("/", 1)[1] if "/" in key else key
        if isinstance(msg, ArmState):
            if not prefix:
                prefix = key.rsplit("/arm/state", 1)[0]
            elif not key.startswith(prefix + "/"):
                continue  # one stack per report: the first prefix that has an arm
            if msg.tick not in states:
                p, vel = msg.ee_position, msg.ee_linear_velocity
                states[int(msg.tick)] = (
                    int(msg.stamp_ns), [p.x, p.y, p.z], [vel.x, vel.y, vel.z], float(msg.dt_s)
                )
        elif prefix and not key.startswith(prefix + "/"):
            continue
        elif isinstance(msg, ArmCommand):
            a = msg.linear_acceleration
            commands[int(msg.tick)] = [a.x, a.y, a.z]
        elif isinstance(msg, PlannerStatus):
            if msg.step and len(msg.time_to_go_s) == 3:
                status.append((int(msg.state_tick), msg.step, np.array(msg.time_to_go_s, dtype=float)))
        elif isinstance(msg, Goal):
            p, gv = msg.position, msg.velocity
            goals.append((int(msg.stamp_ns), np.array([p.x, p.y, p.z, gv.x, gv.y, gv.z])))
        elif isinstance(msg, TaskEvent):
            events.append(msg)
        elif isinstance(msg, CollisionPrediction):
            stop = np.full(3, np.nan)
            if len(msg.stop_position) == 3:
                stop = np.array(msg.stop_position, dtype=float)
            predictions.append((int(msg.state_tick), bool(msg.collision), stop, bool(msg.protective_stop)))
        counts[suffix] = counts.get(suffix, 0) + 1
    if not states:
        raise ValueError(f"{path}: no arm state (<prefix>/arm/state) in the recording")
    if not events:
        raise ValueError(f"{path}: no task events (<prefix>/task/events): not a recording of a stack run")
    order = sorted(states)
    ticks = np.array(order, dtype=np.int64)
    a_cmd = np.array([commands.get(k, [math.nan] * 3) for k in order], dtype=float)
    steps, task_name = _step_windows(events, int(ticks[-1]))
    if not steps:
        raise ValueError(f"{path}: the task events start no step")
    predictions.sort(key=lambda p: p[0])
    return Recording(
        path=path,
        prefix=prefix,
        ticks=ticks,
        stamp_ns=np.array([states[k][0] for k in order], dtype=np.int64),
        x=np.array([states[k][1] for k in order], dtype=float),
        v=np.array([states[k][2] for k in order], dtype=float),
        dt=np.array([states[k][3] for k in order], dtype=float),
        a_cmd=a_cmd,
        steps=steps,
        status=status,
        goals=sorted(goals, key=lambda g: g[0]),
        predictions=predictions,
        task_name=task_name,
        counts=counts,
    )


def _step_windows(events: list[Any], last_tick: int) -> tuple[list[StepWindow], str]:
    """The steps' tick windows from the task events, in order (a step started again, after the
    arm's state stream restarted, keeps its last start)."""
    from services.bus.messages import TaskEvent

    steps: list[StepWindow] = []
    current: StepWindow | None = None
    task = ""
    for ev in events:
        kind = TaskEvent.Kind.Name(ev.kind)
        task = task or ev.task
        if kind == "STARTED" and ev.step and ev.detail.startswith("step "):
            if current is not None and current.index == ev.step_index:
                steps.remove(current)  # the step restarted: its earlier part is not the step's run
            tick = int(ev.state_tick)
            follows = bool(steps) and steps[-1].end_tick == tick and steps[-1].outcome != "aborted"
            current = StepWindow(ev.step, int(ev.step_index), tick,
                                 control_tick=tick + 1 if follows else tick)
            steps.append(current)
        elif kind in ("STEP_COMPLETED", "ABORTED") and current is not None:
            current.end_tick = int(ev.state_tick)
            summary = json.loads(ev.summary_json) if ev.summary_json else {}
            if kind == "ABORTED":
                current.outcome = "aborted"
                mine = [s for s in summary.get("steps", []) if s.get("step") == current.name]
                current.summary = mine[-1] if mine else {}
            else:
                current.summary = summary
                current.outcome = str(summary.get("outcome", "reached"))
            current = None
    if current is not None:
        current.end_tick = last_tick
    return steps, task


def _goal_track(rec: Recording, rows: slice, static_goal: NDArray[np.float64] | None,
                next_start_stamp: int | None) -> NDArray[np.float64]:
    """The goal in use at each row of the step ``(n, 6)``: position [m] and velocity [m/s] (NaN
    before the first one known): the static goal (at rest), or the planner's latest published
    goal of this step."""
    stamps = rec.stamp_ns[rows]
    n = len(stamps)
    if static_goal is not None:
        return np.broadcast_to(np.r_[static_goal, np.zeros(3)], (n, 6)).copy()
    out = np.full((n, 6), np.nan)
    lo = int(stamps[0])
    hi = next_start_stamp if next_start_stamp is not None else None
    mine = [(s, g) for s, g in rec.goals if s >= lo and (hi is None or s < hi)]
    j, current = 0, None
    for i, s in enumerate(stamps):
        while j < len(mine) and mine[j][0] <= s:
            current = mine[j][1]
            j += 1
        if current is not None:
            out[i] = current
    return out


def _time_to_go(rec: Recording, rows: slice, model: Any, goal: NDArray[np.float64],
                options: dict[str, Any], first_tick: int) -> NDArray[np.float64]:
    """``t_e (n, 3)`` [s] of the step's controller stepped on the recorded states from
    ``first_tick`` on (NaN before it), as the planner steps it: towards ``goal[:, :3]`` with the
    velocity relative to the goal's ``goal[:, 3:]``, with the
    collision stops the planner applied (the latest prediction at or before each tick) and not
    stepped during a protective stop (the planner brakes every axis then)."""
    ticks = rec.ticks[rows]
    X, V, dts = rec.x[rows], rec.v[rows], rec.dt[rows]
    goal, gvel = goal[:, :3], goal[:, 3:]
    preds = rec.predictions
    pred_ticks = np.array([p[0] for p in preds], dtype=np.int64)
    out = np.full((len(ticks), 3), np.nan)
    ctrl, current, stops_set = None, None, False
    for i, tick in enumerate(ticks):
        if tick < first_tick or not np.all(np.isfinite(goal[i])):
            continue
        if ctrl is None:
            ctrl = model.controller(goal[i], **options)
            current = goal[i]
        elif not np.array_equal(goal[i], current):
            ctrl.set_goal(goal[i])
            current = goal[i]
        if len(preds):
            j = int(np.searchsorted(pred_ticks, tick, side="right")) - 1
            if j >= 0:
                _t, collision, stop, protective = preds[j]
                if protective:
                    out[i] = ctrl.time_to_go
                    continue
                if collision and np.isfinite(stop).any():
                    ctrl.set_stops(stop)
                    stops_set = True
                elif stops_set:
                    ctrl.clear_stops()
                    stops_set = False
        ctrl.step(X[i], V[i], float(dts[i]), gvel[i])
        out[i] = ctrl.time_to_go
    return out


def recording_result(
    path: Path,
    out_dir: Path,
    *,
    task_file: Path | None = None,
    cache_dir: Path | None = Path("out/models"),
) -> ExperimentResult:
    """The report of a stack recording as an :class:`ExperimentResult`, its PNGs written into
    ``out_dir`` (see the module docstring). ``task_file``: the task the planner ran (default the
    shipped ``configs/feeding.toml``); ``cache_dir``: the planner's model cache (None: learn anew)."""
    from psm.fitting import smooth
    from services.planner.models import ModelCache, demo_path, load_task_models
    from services.robot.recordings import ee_trajectory
    from services.tasks.feeding import DEFAULT_FEEDING_CONFIG, load_feeding

    rec = read_recording(path)
    task_path = Path(task_file) if task_file is not None else DEFAULT_FEEDING_CONFIG
    cfg = load_feeding(task_path)
    task = cfg.task
    scene = {k: np.asarray(v, dtype=float) for k, v in cfg.scene.positions().items()}
    unknown = [s.name for s in rec.steps if s.name not in task.sequence]
    if unknown:
        raise ValueError(f"{path}: step {unknown[0]!r} is not a step of the task in {task_path}")
    models = load_task_models(task, ModelCache(cache_dir) if cache_dir is not None else None).models
    out_dir.mkdir(parents=True, exist_ok=True)

    res = ExperimentResult(
        name=_slug(path.stem),
        title=f"Recording {path.name}",
        seed=0,
        description=(
            f"The stack run recorded in `{path.name}`: task `{rec.task_name or task.name}`, "
            f"{len(rec.steps)} step(s) recorded. Each step's executed end-effector trajectory is "
            "compared with its demonstration; the phase-space plots are relative to the goal in use "
            "and show the PSTF line of every segment of the step's model; the time to go of each "
            "dimension is reconstructed by stepping the step's controller on the recorded states "
            "(markers: the values the planner reported)."
        ),
    )
    dt0 = float(np.median(rec.dt))
    res.config = {
        "recording": str(path),
        "task_file": str(task_path),
        "prefix": rec.prefix,
        "arm_dt_s": dt0,
        "ticks": [int(rec.ticks[0]), int(rec.ticks[-1])],
        "messages_read": rec.counts,
    }
    tab = res.table("Per step", [
        Column("step", "step"),
        Column("outcome", "outcome"),
        Column("duration", "duration", "s", 2),
        Column("final_error", "final error", "mm", 2),
        Column("peak_speed", "peak speed", "m/s", 3),
        Column("demo_peak_speed", "demo peak speed", "m/s", 3),
        Column("speed_ratio", "peak speed / demo's", "", 2),
        Column("peak_accel", "peak commanded acceleration", "m/s²", 2),
        Column("demo_duration", "demo duration", "s", 2),
        Column("te_diff", "t_e vs planner, max |Δ|", "ms", 3),
    ], note="Duration: first to last tick of the step. Final error: distance of the end effector from "
            "the goal in use at the step's last tick. Peak speed: the largest end-effector speed over "
            "the step. t_e: the reconstructed time to go against the planner's status reports.")

    completed = 0
    worst_error = 0.0
    for n, step in enumerate(rec.steps):
        spec = task.step(step.name)
        model = models[step.name]
        i0, i1 = rec.index_of(step.start_tick), rec.index_of(step.end_tick)
        rows = slice(i0, i1 + 1)
        t = (rec.stamp_ns[rows] - rec.stamp_ns[i0]) * 1e-9
        X, V, A = rec.x[rows], rec.v[rows], rec.a_cmd[rows]
        static = None if spec.live else scene[spec.goal] + np.asarray(spec.offset_m, dtype=float)
        nxt = rec.steps[n + 1] if n + 1 < len(rec.steps) else None
        next_stamp = int(rec.stamp_ns[rec.index_of(nxt.start_tick)]) if nxt is not None else None
        goal_state = _goal_track(rec, rows, static, next_stamp)
        te = _time_to_go(rec, rows, model, goal_state, dict(spec.controller), step.control_tick)
        goal = goal_state[:, :3]

        demo_t = demo_X = None
        dpath = demo_path(spec.demo_name)
        if not spec.model_file and dpath.suffix.lower() == ".mcap" and dpath.is_file():
            demo_t, demo_X = ee_trajectory(dpath)
        base = f"step{step.index}_{step.name}"
        curves = [plots.Curve("executed", t, X, {"color": "C0", "lw": 1.6})]
        if demo_X is not None:
            curves.append(plots.Curve("demonstration", demo_t, demo_X, {"color": "k", "lw": 1.0, "ls": "--"}))
        final_goal = goal[-1] if np.all(np.isfinite(goal[-1])) else None
        reached_s = step.summary.get("time_to_reach_s")
        marks = {"goal reached": float(reached_s)} if isinstance(reached_s, int | float) else {}
        plots.plot_trajectories(out_dir / f"{base}_trajectory.png", curves, unit="m", goal=final_goal,
                                marks=marks, title=f"{step.name}: end-effector position")
        points = {"goal": final_goal} if final_goal is not None else {}
        plots.plot_path(out_dir / f"{base}_path.png", curves, unit="m", points=points,
                        title=f"{step.name}: path")
        phase = [plots.PhaseCurve("executed (commanded a)", X - goal, V, A, {"color": "C0", "lw": 1.4})]
        demo_speed = demo_duration = None
        if demo_X is not None:
            sm = smooth(demo_t, demo_X, model.parameters.smoothing)
            phase.insert(0, plots.PhaseCurve("demonstration (smoothed)", sm.x - demo_X[-1], sm.v, sm.a,
                                             {"color": "k", "lw": 1.0}))
            demo_speed = float(np.max(np.linalg.norm(sm.v, axis=1)))
            demo_duration = float(demo_t[-1] - demo_t[0])
        lines = plots.pstf_lines(model, goal=np.zeros(model.dim))
        plots.plot_phase_space(out_dir / f"{base}_phase.png", phase, lines, unit="m",
                               dims=("x − goal", "y − goal", "z − goal"),
                               title=f"{step.name}: phase space relative to the goal, with the PSTF lines")
        reported = [(tk, vals) for tk, name, vals in rec.status
                    if name == step.name and step.start_tick <= tk <= step.end_tick]
        te_diff = None
        recorded = None
        if reported:
            ts = np.array([(rec.stamp_ns[rec.index_of(tk)] - rec.stamp_ns[i0]) * 1e-9 for tk, _ in reported])
            tes = np.array([vals for _, vals in reported])
            recorded = (ts, tes)
            idx = np.array([rec.index_of(tk) - i0 for tk, _ in reported])
            diffs = np.abs(te[idx] - tes)
            finite = diffs[np.isfinite(diffs)]
            te_diff = float(np.max(finite)) * 1e3 if finite.size else None
        plots.plot_time_to_go(out_dir / f"{base}_sync.png", t, te, recorded=recorded, marks=marks,
                              title=f"{step.name}: time synchronisation of the dimensions")
        res.figures += [
            Figure(f"{base}_trajectory.png",
                   f"{step.name}: executed end-effector position per dimension against the demonstration "
                   "(dashed); dotted: the goal at the step's end."),
            Figure(f"{base}_path.png",
                   f"{step.name}: the executed path and the demonstration's, 3-D and top view."),
            Figure(f"{base}_phase.png",
                   f"{step.name}: position–velocity (top) and position–acceleration (bottom) relative "
                   "to the goal, executed and demonstrated, with the PSTF line a = c0 + k (x − m) of each "
                   "segment of the model and its via-points."),
            Figure(f"{base}_sync.png",
                   f"{step.name}: each dimension's time to go t_e (top) and its lag behind the slowest "
                   "dimension (bottom), reconstructed from the recorded states; circles: the planner's "
                   "status reports."),
        ]
        speed = np.linalg.norm(V, axis=1)
        err = float(np.linalg.norm(X[-1] - goal[-1])) if final_goal is not None else None
        peak = float(np.max(speed))
        acc_norm = np.linalg.norm(A, axis=1)
        acc_norm = acc_norm[np.isfinite(acc_norm)]
        if step.outcome == "reached":
            completed += 1
        if err is not None:
            worst_error = max(worst_error, err)
        tab.add(
            step=step.name,
            outcome=step.outcome,
            duration=float((rec.stamp_ns[i1] - rec.stamp_ns[i0]) * 1e-9),
            final_error=None if err is None else err * 1e3,
            peak_speed=peak,
            demo_peak_speed=demo_speed,
            speed_ratio=peak / demo_speed if demo_speed else None,
            peak_accel=float(np.max(acc_norm)) if acc_norm.size else None,
            demo_duration=demo_duration,
            te_diff=te_diff,
        )

    total = len(task.steps)
    first, last = rec.index_of(rec.steps[0].start_tick), rec.index_of(rec.steps[-1].end_tick)
    t_task = float((rec.stamp_ns[last] - rec.stamp_ns[first]) * 1e-9)
    res.headline["steps"] = Headline("steps reached", completed, "", f"of {total} in the task")
    res.headline["duration"] = Headline("task time", t_task, "s", "first step's start to last step's end")
    res.headline["worst_error"] = Headline("worst final error", worst_error * 1e3, "mm",
                                           "over the recorded steps")
    res.verdict("task completed", completed == total, f"{total}/{total} steps reached",
                f"{completed}/{total} reached")
    keys = res.table("Recorded streams", [Column("key", "key"), Column("messages", "messages")],
                     note="The streams read for this report (others in the file are not read).")
    for key, count in sorted(rec.counts.items()):
        keys.add(key=key, messages=count)
    return res


def _slug(text: str) -> str:
    out = "".join(c if c.isalnum() or c in "-_" else "-" for c in text).strip("-")
    return out or "recording"
