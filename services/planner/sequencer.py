"""The task sequencer: one PSM per step, goals, holding, completion — bus-free.

:class:`TaskRunner` is the planner's brain, used unchanged by the planner service (on every arm
state) and by the in-process simulation (:mod:`services.planner.simulate`)::

    runner = TaskRunner(task, scene, models, profiles)
    runner.update_goal("person", position, stamp_ns=t, valid=True)   # live goals, any time
    out = runner.step(t_ns, x, v, quat, dt)     # every arm state: the command
    out.acceleration, out.orientation, out.angular_velocity
    runner.drain_events()                       # transitions since the last call

Per step (``services.planner.task.StepSpec``):

* **start** from the arm's current state: the step's PSM controller towards its goal (scene
  position or live goal, plus the step's offset), an orientation tracker from the arm's current
  orientation (:class:`~services.planner.orientation.OrientationTracker`);
* **run**: the PSM's acceleration per dimension (synchronised, velocity continuous when the
  goal moves: :meth:`psm.PSMController.set_goal`); the orientation reference follows the
  reference dimension's ``t_e``;
* **hold** while the goal is unavailable (a live goal lost, invalid, stale, or outside the
  workspace): ``on_goal_lost = "hold"`` stops the arm with a critically damped approach to its
  stopping point and resumes the same PSM from wherever it stopped once the goal is back;
  ``"neutral"`` drives the neutral model to the neutral position meanwhile and starts the step
  afresh from there once the goal is back;
* **obstacles** (when a :class:`CollisionPolicy` is given): the latest collision prediction
  (:meth:`TaskRunner.set_collision`, from the obstacle monitor) is applied at every step. A
  predicted collision of the segment from the end effector to the goal sets the stop coordinates
  of the affected axes (eq. 15: they brake to rest at the obstacle's face while the other axes go
  on) and clears them once the segment is free, so the braked axes resume their PSTF from where
  they are; a protective stop (whole-arm clearance too small), a prediction older than
  ``max_age_s`` on the stack's clock, no prediction at all, or the monitor gone brakes every axis
  to rest (the path is treated as blocked: the arm never moves blind). At rest in front of an
  obstacle the step reports HOLDING with the obstacle's id;
* **done** once within ``position_tolerance_m`` of the goal and ``velocity_tolerance_mps`` of the
  goal's own velocity, then ``dwell_s`` (and ``follow_s`` for a live goal) with the PSM holding
  the goal, then the gripper action, then the next step. A step that takes longer than its
  timeout aborts the task (the arm holds where it is).

Units: positions m, velocities m/s, accelerations m/s², times ns (stamps) or s (durations),
quaternions ``(x, y, z, w)`` with ``w ≥ 0``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from psm import PhaseSpaceModel, PSMController
from psm.controller import MODE_STOP, MODE_TERMINAL
from services.planner.feasibility import JointAccelerationScaling, Joints
from services.planner.orientation import OrientationProfile, OrientationTracker
from services.planner.task import StepSpec, TaskSpec

__all__ = [
    "CollisionInfo",
    "CollisionPolicy",
    "CompletedStep",
    "DemoFigures",
    "GoalBook",
    "PlannerOutput",
    "StepReport",
    "TaskEventRecord",
    "TaskRunner",
]

# Runner states (the names of PlannerStatus.State).
IDLE, RUNNING, HOLDING, DONE, FAULT = "IDLE", "RUNNING", "HOLDING", "DONE", "FAULT"


def _read_only(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """``a``, made read-only (an array shared between ticks that no caller may change)."""
    a.flags.writeable = False
    return a


#: The velocity of a static goal (0, 0, 0) [m/s], shared and read-only.
ZERO3 = _read_only(np.zeros(3))

# The control step runs once per arm state on a loop whose caches are cold at every tick (the
# arm's process runs between two states): there each numpy call on a 3-vector costs ~10 µs,
# several times its cost in a warm loop, so the per-tick path works on plain floats
# (``ndarray.tolist`` once per input) and builds arrays only for its outputs.


@dataclass(frozen=True)
class DemoFigures:
    """What a step's demonstration did, for the generalisation criteria: ``peak_speed`` [m/s],
    ``away_m (3,)`` the most each axis moved farther from its goal than it started [m]."""

    peak_speed: float
    away_m: tuple[float, float, float]

    @classmethod
    def of(cls, t: NDArray[np.float64], X: NDArray[np.float64]) -> DemoFigures:
        """From a demonstration ``t (T,)`` [s], ``X (T, 3)`` [m] (velocity by central differences
        of the positions smoothed over 20 ms, as the fit sees them)."""
        from psm.fitting import smooth

        sm = smooth(t, X, 0.02)
        speed = float(np.max(np.linalg.norm(sm.v, axis=1)))
        goal = X[-1]
        dist = np.abs(X - goal)
        away = np.maximum(0.0, dist.max(axis=0) - dist[0])
        return cls(speed, (float(away[0]), float(away[1]), float(away[2])))


def _sign(value: float) -> float:
    """+1.0, −1.0 or 0.0 as ``value`` is positive, negative or zero."""
    return 1.0 if value > 0.0 else -1.0 if value < 0.0 else 0.0


@dataclass(frozen=True)
class CollisionPolicy:
    """How the planner uses the obstacle monitor's predictions: a prediction older than
    ``max_age_s`` [s] of the stack's clock counts as none (the path is treated as blocked)."""

    max_age_s: float


@dataclass
class CollisionInfo:
    """One collision prediction as the planner uses it (from ``CollisionPrediction``).

    ``stamp_ns`` is the stamp of the arm state it was computed for; ``stop_position (3,)`` [m] the
    stop coordinate per axis (NaN: the axis goes on); ``protective_stop``: stop every axis;
    ``inside``: the end effector is inside the inflated obstacle, and the stopped axes stop where
    they are."""

    stamp_ns: int
    tick: int
    collision: bool = False
    obstacle_id: str = ""
    stop_position: NDArray[np.float64] = field(default_factory=lambda: np.full(3, np.nan))
    protective_stop: bool = False
    min_clearance_m: float = math.inf
    closest_link: str = ""
    detail: str = ""
    inside: bool = False  #: the end effector is inside the inflated obstacle (stops where it is)


@dataclass
class TaskEventRecord:
    """A transition: ``kind`` (a TaskEvent.Kind name), the step, the tick and a detail line."""

    kind: str
    step: str
    step_index: int
    tick: int
    stamp_ns: int
    detail: str = ""
    summary: dict[str, Any] | None = None


@dataclass
class PlannerOutput:
    """The command for one arm state: ``acceleration (3,)`` [m/s²], ``orientation (4,)`` xyzw,
    ``angular_velocity (3,)`` [rad/s]."""

    acceleration: NDArray[np.float64]
    orientation: NDArray[np.float64]
    angular_velocity: NDArray[np.float64]


@dataclass
class StepReport:
    """Figures of one step as it ran (``summary()`` is the JSON of TaskEvent / ``psm up``).

    The position and velocity errors are taken when the step is done (a static goal: after the
    dwell) or, for a live goal, when it was reached; ``hold_rms_m`` / ``hold_max_m`` are the
    distance to the goal from then on (dwell and following)."""

    name: str
    index: int
    goal_name: str
    start_ns: int
    start: NDArray[np.float64]
    demo: DemoFigures | None = None
    end_ns: int = 0
    success: bool = False
    outcome: str = "running"
    position_error_m: float = math.nan
    velocity_error_mps: float = math.nan
    reached_ns: int = 0
    peak_speed_mps: float = 0.0
    peak_accel_mps2: float = 0.0
    peak_command_accel_mps2: float = 0.0
    hold_s: float = 0.0
    max_orientation_error_deg: float = 0.0
    start_dist: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    #: Largest distance to the goal per axis so far [m] (plain floats: updated every tick).
    max_dist: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    goal: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    has_goal: bool = False
    follow_sq: float = 0.0  #: sum of squared distances to the goal once reached (dwell, follow)
    follow_n: int = 0
    follow_max_m: float = 0.0
    scaled_ticks: int = 0  #: commands scaled into the joint acceleration limits
    min_accel_scale: float = 1.0  #: the smallest of those factors

    def set_goal(self, goal: NDArray[np.float64], x: NDArray[np.float64]) -> None:
        """The step's goal became known with the arm at ``x (3,)`` [m] (distances start here)."""
        self.goal = np.array(goal, dtype=float)
        self.start_dist = np.abs(np.asarray(x, dtype=float) - self.goal)
        self.max_dist = self.start_dist.tolist()
        self.has_goal = True

    def summary(self) -> dict[str, Any]:
        """JSON-able figures (durations in s, distances in m)."""
        away = np.maximum(0.0, self.max_dist - self.start_dist)
        out: dict[str, Any] = {
            "step": self.name,
            "index": self.index,
            "goal": self.goal_name,
            "goal_position_m": [round(float(c), 5) for c in self.goal],
            "outcome": self.outcome,
            "success": self.success,
            "duration_s": (self.end_ns - self.start_ns) * 1e-9 if self.end_ns else None,
            "time_to_reach_s": (self.reached_ns - self.start_ns) * 1e-9 if self.reached_ns else None,
            "position_error_m": self.position_error_m,
            "velocity_error_mps": self.velocity_error_mps,
            "peak_speed_mps": self.peak_speed_mps,
            "peak_accel_mps2": self.peak_accel_mps2,
            "peak_command_accel_mps2": self.peak_command_accel_mps2,
            "hold_s": self.hold_s,
            "max_orientation_error_deg": self.max_orientation_error_deg,
            "away_m": [float(a) for a in away],
            "hold_rms_m": math.sqrt(self.follow_sq / self.follow_n) if self.follow_n else None,
            "hold_max_m": self.follow_max_m if self.follow_n else None,
            "accel_scaled_ticks": self.scaled_ticks,
            "min_accel_scale": self.min_accel_scale,
        }
        if self.demo is not None:
            out["demo_peak_speed_mps"] = self.demo.peak_speed
            out["peak_speed_ratio"] = (
                self.peak_speed_mps / self.demo.peak_speed if self.demo.peak_speed else None
            )
            out["demo_away_m"] = list(self.demo.away_m)
            out["extra_away_m"] = [
                max(0.0, float(a) - d) for a, d in zip(away, self.demo.away_m, strict=True)
            ]
        return out


@dataclass
class CompletedStep:
    """A step completed by an earlier planner process (from its progress file): its times [ns,
    stack clock] and figures (:meth:`StepReport.summary`), reported unchanged."""

    start_ns: int
    end_ns: int
    figures: dict[str, Any]

    @property
    def success(self) -> bool:
        """Whether the step succeeded."""
        return bool(self.figures.get("success"))

    def summary(self) -> dict[str, Any]:
        """The figures as they were reported."""
        return dict(self.figures)


@dataclass
class _LiveGoal:
    position: NDArray[np.float64]
    stamp_ns: int
    valid: bool
    reason: str
    velocity: NDArray[np.float64]


class GoalBook:
    """The goals the task may use: static scene positions and live goals from the bus.

    A live goal is unavailable while it is marked invalid, when its last update is older than
    ``goal_timeout_s`` on the stack's clock, or when it lies outside the workspace (such an
    update is rejected and counted, and never used). Its velocity is estimated from successive
    updates (a first-order filter of the finite differences, 0.1 s time constant)."""

    def __init__(self, task: TaskSpec, scene: Mapping[str, Any]) -> None:
        self.task = task
        self.static = {k: np.asarray(v, dtype=float) for k, v in scene.items()}
        self.live: dict[str, _LiveGoal] = {}
        self.rejected = 0
        self.last_rejection = ""
        self.last_rejection_kind = ""  #: the reason of the last rejection: non_finite, workspace, stamp
        self._timeout_ns = int(task.goal_timeout_s * 1e9)
        # resolve() runs every tick: the goal arrays it returns are built once per static goal
        # and offset, and once per live update, and are read-only (shared between ticks).
        self._static_goals: dict[tuple[str, tuple[float, ...]], NDArray[np.float64]] = {}
        self._live_goals: dict[str, tuple[_LiveGoal, tuple[float, ...], NDArray[np.float64]]] = {}

    def update(
        self, name: str, position: Any, stamp_ns: int, valid: bool = True, reason: str = "",
        now_ns: int | None = None,
    ) -> str:
        """Offer a live goal; returns ``""`` if accepted, else why it was rejected (counted).
        ``now_ns`` [ns]: the stack's clock (the latest arm state), when known: a goal stamped more
        than ``goal_timeout_s`` ahead of it is rejected (it would hide every real update)."""
        p = np.asarray(position, dtype=float)
        problem, kind = "", ""
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            problem, kind = "position is not 3 finite numbers", "non_finite"
        elif valid and not self.task.workspace.contains(p):
            where = [round(float(c), 3) for c in p]
            problem, kind = f"position {where} is outside the workspace", "workspace"
        prev = self.live.get(name)
        if not problem and prev is not None and stamp_ns < prev.stamp_ns:
            problem, kind = "stamp older than the last update", "stamp"
        if not problem and now_ns is not None and stamp_ns - now_ns > self._timeout_ns:
            problem, kind = f"stamp {(stamp_ns - now_ns) * 1e-9:.3g} s ahead of the stack's clock", "stamp"
        if problem:
            self.rejected += 1
            self.last_rejection = f"goal {name}: {problem}"
            self.last_rejection_kind = kind
            if prev is not None and valid:
                # A goal that left the workspace (or turned non-finite) is not used any more.
                prev.valid, prev.reason = False, problem
            return problem
        vel = np.zeros(3)
        if prev is not None and prev.valid and valid and stamp_ns > prev.stamp_ns:
            dt = (stamp_ns - prev.stamp_ns) * 1e-9
            w = min(1.0, dt / 0.1)
            vel = (1.0 - w) * prev.velocity + w * (p - prev.position) / dt
        self.live[name] = _LiveGoal(
            p, int(stamp_ns), bool(valid), reason or ("" if valid else "invalid"), vel
        )
        return ""

    def resolve(
        self, step: StepSpec, now_ns: int
    ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64], str]:
        """``(goal (3,) or None, goal velocity (3,), why unavailable)`` for ``step`` at ``now_ns``."""
        offset = tuple(step.offset_m)
        if not step.live:
            key = (step.goal, offset)
            goal = self._static_goals.get(key)
            if goal is None:
                goal = _read_only(self.static[step.goal] + np.asarray(offset, dtype=float))
                self._static_goals[key] = goal
            return goal, ZERO3, ""
        g = self.live.get(step.goal)
        if g is None:
            return None, ZERO3, f"waiting for goal {step.goal}"
        if not g.valid:
            return None, ZERO3, f"goal {step.goal} lost: {g.reason}"
        if now_ns - g.stamp_ns > self._timeout_ns:
            return None, ZERO3, f"goal {step.goal} stale ({(now_ns - g.stamp_ns) * 1e-9:.2f} s old)"
        cached = self._live_goals.get(step.goal)
        if cached is not None and cached[0] is g and cached[1] == offset:
            return cached[2], g.velocity, ""
        goal = _read_only(g.position + np.asarray(offset, dtype=float))
        self._live_goals[step.goal] = (g, offset, goal)
        return goal, g.velocity, ""


class TaskRunner:
    """Runs a :class:`~services.planner.task.TaskSpec` (see the module docstring).

    Args:
        task: the steps and goal handling.
        scene: named static positions ``(3,)`` [m].
        models: one :class:`PhaseSpaceModel` per step name.
        profiles: the orientation profile per step name (a step without one, or with
            ``orientation = "hold"``, keeps its start orientation).
        demos: the demonstration figures per step name (for the step reports).
        collision: use the obstacle monitor's predictions (None: no obstacle handling).
        feasibility: scale the motion's commands into the arm's joint acceleration limits
            (:mod:`services.planner.feasibility`; needs the joints in :meth:`step`).
    """

    def __init__(
        self,
        task: TaskSpec,
        scene: Mapping[str, Any],
        models: Mapping[str, PhaseSpaceModel],
        profiles: Mapping[str, OrientationProfile] | None = None,
        demos: Mapping[str, DemoFigures] | None = None,
        collision: CollisionPolicy | None = None,
        feasibility: JointAccelerationScaling | None = None,
    ) -> None:
        missing = [s.name for s in task.steps if s.name not in models]
        if missing:
            raise ValueError(f"no model for step {missing[0]!r}")
        if task.on_goal_lost == "neutral" and task.neutral_model not in models:
            raise ValueError(f"on_goal_lost = neutral needs a model for step {task.neutral_model!r}")
        self.task = task
        self.goals = GoalBook(task, scene)
        # The neutral detour runs the neutral model's step with that step's controller options.
        self._neutral_opts = (
            dict(task.step(task.neutral_model).controller) if task.neutral_model in task.sequence else {}
        )
        self.models = dict(models)
        self.profiles = dict(profiles or {})
        self.demos = dict(demos or {})
        self.state = IDLE
        self.detail = ""
        self.index = -1
        self.reports: list[StepReport | CompletedStep] = []
        #: Resumes of this task by a restarted planner: ``{"at_step": i, "tick": k}`` each.
        self.resumes: list[dict[str, Any]] = []
        self._resume_at: int | None = None
        self._events: list[TaskEventRecord] = []
        self._ctrl: PSMController | None = None
        self._orient: OrientationTracker | None = None
        self._goal: NDArray[np.float64] | None = None
        self._goal_l: list[float] = []  # self._goal as floats (the per-tick path)
        self._xl: list[float] = []  # the state of the current step() as floats
        self._vl: list[float] = []
        self._goal_velocity = ZERO3
        self._event_goal: NDArray[np.float64] | None = None
        self._segments: tuple[int, ...] = ()
        self._phase = "idle"  # run | dwell | hold | neutral | done | fault
        self._phase_since_ns = 0
        self._hold_target: NDArray[np.float64] | None = None
        self._hold_quat: NDArray[np.float64] | None = None
        self._last_quat = np.array([0.0, 0.0, 0.0, 1.0])
        self._last_omega = np.zeros(3)
        self._tick = 0
        self._now_ns = 0
        self._neutral_ctrl: PSMController | None = None
        self._orient_dim = task.orientation_dim
        self._restart = False
        self.distance = math.nan
        self.speed = 0.0
        self.collision_policy = collision
        self.feasibility = feasibility
        self._collision: CollisionInfo | None = None
        self._monitor_alive = True
        self._guard = ""  # why every axis is braked for the obstacles ("" = not)
        self._guard_target: NDArray[np.float64] | None = None
        self._blocked_by = ""  # obstacle at whose face the arm rests ("" = none)
        self._stops_set = False
        # The stops applied last (per axis, NaN: none) and the obstacle they were for.
        self._applied_stops = [math.nan] * 3
        self._stop_sides = [0.0] * 3  # the obstacle's side of each (+1, -1; 0: none)
        self._stop_obstacle = ""
        self.collision_stops = 0  # predicted collisions acted on (transitions into a stop)
        w = task.hold_omega
        self._kp, self._kd = w * w, 2.0 * w

    # ------------------------------------------------------------------ inputs
    def update_goal(
        self, name: str, position: Any, stamp_ns: int, valid: bool = True, reason: str = "",
        now_ns: int | None = None,
    ) -> str:
        """A live goal update (see :meth:`GoalBook.update`); ``""`` if accepted."""
        return self.goals.update(name, position, stamp_ns, valid, reason, now_ns)

    def set_collision(self, info: CollisionInfo) -> None:
        """The obstacle monitor's latest prediction (applied from the next :meth:`step`)."""
        self._collision = info

    def set_monitor_alive(self, alive: bool) -> None:
        """The obstacle monitor's liveliness (gone: the path is treated as blocked)."""
        self._monitor_alive = alive

    @property
    def monitor_alive(self) -> bool:
        """The obstacle monitor's liveliness as last reported."""
        return self._monitor_alive

    @property
    def collision(self) -> CollisionInfo | None:
        """The latest collision prediction, or None."""
        return self._collision

    @property
    def step_spec(self) -> StepSpec | None:
        """The active step, or None before the start and after the end."""
        return self.task.steps[self.index] if 0 <= self.index < len(self.task.steps) else None

    @property
    def controller(self) -> PSMController | None:
        """The active step's PSM controller."""
        return self._ctrl

    @property
    def goal_velocity(self) -> NDArray[np.float64]:
        """The estimated velocity of the goal in use [m/s] (zero for a static goal)."""
        return self._goal_velocity

    @property
    def orientation_reference(self) -> NDArray[np.float64]:
        """The last orientation reference sent, xyzw."""
        return self._last_quat

    @property
    def goal(self) -> NDArray[np.float64] | None:
        """The goal in use (with the step's offset) [m], or None."""
        return self._goal

    def resume(
        self, next_index: int, completed: list[dict[str, Any]], resumes: list[dict[str, Any]] | None = None
    ) -> None:
        """Before the first :meth:`step`: continue a task an earlier planner process ran
        (:mod:`services.planner.progress`). Steps ``0 .. next_index - 1`` are done (their
        ``completed`` records, ``start_ns``/``end_ns``/``summary``, are reported as they were);
        the first state starts step ``next_index`` from the arm's state, like any step start
        (``next_index == len(steps)``: the task is done, the arm is held)."""
        if self.state != IDLE:
            raise RuntimeError("resume() must come before the first step()")
        if not 0 <= next_index <= len(self.task.steps) or len(completed) != next_index:
            raise ValueError(f"cannot resume at step {next_index} with {len(completed)} completed")
        self.reports = [
            CompletedStep(int(c["start_ns"]), int(c["end_ns"]), dict(c["summary"])) for c in completed
        ]
        self.resumes = list(resumes or [])
        self._resume_at = next_index

    def completed_steps(self, upto: int) -> list[dict[str, Any]]:
        """The records of steps ``0 .. upto - 1`` (done) for a progress file: ``start_ns``,
        ``end_ns`` and ``summary``."""
        return [
            {"start_ns": int(r.start_ns), "end_ns": int(r.end_ns), "summary": r.summary()}
            for r in self.reports[:upto]
        ]

    def restart_step(self) -> None:
        """Start the active step afresh from the next state (the arm's state stream restarted);
        its report so far is discarded."""
        if self._phase not in ("done", "fault", "idle") and self.reports:
            self._restart = True

    def drain_events(self) -> list[TaskEventRecord]:
        """The transitions since the last call, oldest first."""
        ev, self._events = self._events, []
        return ev

    def _event(self, kind: str, detail: str = "", summary: dict[str, Any] | None = None) -> None:
        spec = self.step_spec
        self._events.append(
            TaskEventRecord(
                kind, spec.name if spec else "", max(self.index, 0), self._tick, self._now_ns, detail, summary
            )
        )

    # ------------------------------------------------------------------ the control step
    def step(
        self,
        now_ns: int,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
        quat: NDArray[np.float64],
        dt: float,
        *,
        tick: int = 0,
        measured_accel: NDArray[np.float64] | None = None,
        joints: Joints | None = None,
    ) -> PlannerOutput:
        """The command for the arm state at ``now_ns`` [ns]: EE position ``x (3,)`` [m], velocity
        ``v (3,)`` [m/s], orientation ``quat (4,)`` xyzw; ``dt`` [s] the control period;
        ``measured_accel (3,)`` [m/s²] (for the step report); ``joints``: a function giving the
        state's ``(q, dq)`` ``(n,)`` [rad, rad/s] (or None), for the joint acceleration scaling
        (called only on the ticks that need them)."""
        self._tick, self._now_ns = tick, now_ns
        if self.state == IDLE:
            self._last_quat = np.asarray(quat, dtype=float).copy()  # held until a step sets one
            if self._resume_at is None:
                self._event("STARTED", f"task {self.task.name}: {len(self.task.steps)} steps")
                self._start_step(0, now_ns, x, quat)
            else:
                self._start_resumed(self._resume_at, now_ns, x, quat)
        elif self._restart:
            self._restart = False
            self.reports.pop()
            self._start_step(self.index, now_ns, x, quat)
        xl, vl = _floats(x), _floats(v)
        self._xl, self._vl = xl, vl
        speed = math.sqrt(vl[0] * vl[0] + vl[1] * vl[1] + vl[2] * vl[2])
        self.speed = speed
        rep = self.reports[-1] if self.reports else None
        if self._phase in ("done", "fault"):
            return self._hold(x, v, quat)
        spec = self.step_spec
        assert spec is not None and rep is not None
        goal, goal_vel, why = self.goals.resolve(spec, now_ns)
        if self.collision_policy is not None and self._obstacle_guard(now_ns, rep, dt):
            out = self._guard_stop(x, v, quat)  # no usable prediction or a protective stop
        elif goal is None:
            out = self._unavailable(why, now_ns, x, v, quat, dt)
        else:
            if self.collision_policy is not None:
                self._apply_stops(self._ctrl, x)
            out = self._available(spec, rep, goal, goal_vel, now_ns, x, v, quat, dt)
            if self.collision_policy is not None and self._phase == "run":
                self._check_blocked(rep, dt)
        if self.feasibility is not None and joints is not None:
            self._scale_into_limits(out, rep, joints)
        if rep.outcome == "running":
            if speed > rep.peak_speed_mps:
                rep.peak_speed_mps = speed
            if measured_accel is not None:
                m0, m1, m2 = _floats(measured_accel)
                rep.peak_accel_mps2 = max(rep.peak_accel_mps2, math.sqrt(m0 * m0 + m1 * m1 + m2 * m2))
            a0, a1, a2 = _floats(out.acceleration)
            a_cmd = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            rep.peak_command_accel_mps2 = max(rep.peak_command_accel_mps2, a_cmd)
            if self._goal is not None:
                gl, md = self._goal_l, rep.max_dist
                for i in range(3):
                    d = abs(xl[i] - gl[i])
                    if d > md[i]:
                        md[i] = d
            err = _angle_deg(quat, out.orientation)
            if self._phase == "run" and err > rep.max_orientation_error_deg:
                rep.max_orientation_error_deg = err
        self._last_quat, self._last_omega = out.orientation, out.angular_velocity
        return out

    def _available(
        self,
        spec: StepSpec,
        rep: StepReport,
        goal: NDArray[np.float64],
        goal_vel: NDArray[np.float64],
        now_ns: int,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
        quat: NDArray[np.float64],
        dt: float,
    ) -> PlannerOutput:
        if self._phase in ("hold", "neutral"):
            self._resume(spec, now_ns, x, quat)
        ctrl = self._ctrl
        assert ctrl is not None
        if goal is not self._goal:  # (resolve returns the same array while the goal is unchanged)
            if self._goal is None or not (goal == self._goal).all():
                ctrl.set_goal(goal)
                if (
                    self._event_goal is None
                    or float(np.linalg.norm(goal - self._event_goal)) >= self.task.goal_event_m
                ):
                    self._event_goal = goal.copy()
                    self._event("GOAL_CHANGED", f"{spec.goal} at {np.round(goal, 3).tolist()}")
            self._set_goal(goal)
        self._goal_velocity = goal_vel
        # The via-points are relative to the goal, so the phase-space state is too: the controller
        # runs its law on the velocity relative to a moving goal's (zero for a static goal). With
        # the absolute velocity a via-point at rest, carried along by a goal moving steadily, is
        # never reached at rest: the dimension trails it and the motion stalls there. Its
        # collision stops, fixed in the world, brake the measured velocity.
        static_goal = goal_vel is ZERO3
        acc = ctrl.step(self._xl, self._vl, dt, None if static_goal else goal_vel)
        seg = ctrl.segment_tuple
        if seg != self._segments:
            changed = [
                f"{'xyz'[d]}:{a}->{b}"
                for d, (a, b) in enumerate(zip(self._segments, seg, strict=False))
                if a != b
            ]
            if self._segments:
                self._event("SEGMENT_CHANGED", " ".join(changed))
            self._segments = seg
        q, omega = self._orientation(ctrl)
        xl, vl, gl = self._xl, self._vl, self._goal_l
        e0, e1, e2 = gl[0] - xl[0], gl[1] - xl[1], gl[2] - xl[2]
        self.distance = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if static_goal:
            rel_speed = self.speed
        else:
            gv = _floats(goal_vel)
            u0, u1, u2 = vl[0] - gv[0], vl[1] - gv[1], vl[2] - gv[2]
            rel_speed = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        reached = self.distance <= spec.position_tolerance_m and rel_speed <= spec.velocity_tolerance_mps
        if self._phase == "run" and reached:
            self._phase, self._phase_since_ns = "dwell", now_ns
            rep.reached_ns = now_ns
            rep.position_error_m, rep.velocity_error_mps = self.distance, rel_speed
        if self._phase == "dwell":
            if spec.live:
                # Following a live goal once reached: a critically damped tracker with the
                # goal's velocity as feed-forward (no lag behind a goal moving steadily).
                acc = self._tracking(goal, goal_vel, x, v)
            rep.follow_sq += self.distance * self.distance
            rep.follow_n += 1
            rep.follow_max_m = max(rep.follow_max_m, self.distance)
            wait = spec.dwell_s + (spec.follow_s if spec.live else 0.0)
            if (now_ns - self._phase_since_ns) * 1e-9 >= wait - 1e-9:
                if not spec.live:  # a static goal: the error after the dwell
                    rep.position_error_m, rep.velocity_error_mps = self.distance, rel_speed
                self._finish_step(now_ns, x, quat, success=True, outcome="reached")
        elif self._timed_out(spec, rep, now_ns):
            rep.position_error_m, rep.velocity_error_mps = self.distance, rel_speed
            self._fail(
                f"step {spec.name} timed out after {(now_ns - rep.start_ns) * 1e-9:.1f} s "
                f"({self.distance:.3f} m from the goal)"
            )
            return self._hold(x, v, quat)
        return PlannerOutput(acc, q, omega)

    def _set_goal(self, goal: NDArray[np.float64] | None) -> None:
        """The goal in use (None: not known yet), also as floats for the per-tick path."""
        self._goal = goal
        self._goal_l = [] if goal is None else goal.tolist()

    def _scale_into_limits(self, out: PlannerOutput, rep: StepReport, joints: Joints) -> None:
        """Scale the motion's command ``out`` into the joint acceleration limits (see
        :mod:`services.planner.feasibility`): a PSM motion (the step, its dwell or following, the
        neutral detour), never a brake (collision stop, guard, hold)."""
        if self._phase in ("run", "dwell"):
            ctrl = self._ctrl
        elif self._phase == "neutral":
            ctrl = self._neutral_ctrl
        else:
            return
        # (a dimension can only be in MODE_STOP while stops are set: ``modes`` copies a list)
        if ctrl is None or self._guard or (self._stops_set and MODE_STOP in ctrl.modes):
            return
        assert self.feasibility is not None
        s = self.feasibility.scale(out.acceleration, self._tick, joints)
        if s < 1.0:
            out.acceleration = out.acceleration * s
            rep.scaled_ticks += 1
            rep.min_accel_scale = min(rep.min_accel_scale, s)

    def _unavailable(
        self,
        why: str,
        now_ns: int,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
        quat: NDArray[np.float64],
        dt: float,
    ) -> PlannerOutput:
        rep = self.reports[-1]
        if self._phase in ("run", "dwell"):
            mode = self.task.on_goal_lost
            self._phase, self._phase_since_ns = ("neutral" if mode == "neutral" else "hold"), now_ns
            self._hold_target = None
            self._neutral_ctrl = None
            if not why.startswith("waiting"):
                self._event("GOAL_LOST", why)
            self._event("PAUSED", f"{why}: {'going to neutral' if mode == 'neutral' else 'holding'}")
        self.state, self.detail = HOLDING, why
        rep.hold_s += dt
        if self._phase == "neutral":
            if self._neutral_ctrl is None:
                model = self.models[self.task.neutral_model]
                self._neutral_ctrl = model.controller(
                    self.goals.static[self.task.neutral], **self._neutral_opts
                )
                self._stops_set = False  # a fresh controller: the stops are applied to it anew
            if self.collision_policy is not None:
                self._apply_stops(self._neutral_ctrl, x)  # the detour is guarded as the step is
            acc = self._neutral_ctrl.step(x, v, dt)
            return PlannerOutput(np.asarray(acc, dtype=float), self._last_quat, np.zeros(3))
        return self._hold(x, v, quat)

    # ------------------------------------------------------------------ obstacles
    def _obstacle_guard(self, now_ns: int, rep: StepReport, dt: float) -> bool:
        """Apply the latest prediction to the active controller; True when every axis must brake
        (protective stop, or no usable prediction)."""
        assert self.collision_policy is not None
        info = self._collision
        reason = ""
        if not self._monitor_alive:
            reason = "obstacle monitor not alive"
        elif info is None:
            reason = "no collision prediction yet"
        elif (now_ns - info.stamp_ns) * 1e-9 > self.collision_policy.max_age_s:
            reason = f"collision prediction stale ({(now_ns - info.stamp_ns) * 1e-6:.0f} ms old)"
        elif info.protective_stop:
            reason = "protective stop: " + (
                info.detail
                or f"clearance {info.min_clearance_m:.3f} m ({info.closest_link}, {info.obstacle_id})"
            )
        if reason:
            if not self._guard:
                self._guard_target = None
                self._event("PAUSED", f"{reason}: braking every axis")
            self._guard = reason
            self._blocked_by = ""
            self.state, self.detail = HOLDING, reason
            rep.hold_s += dt
            return True
        if self._guard:
            self._guard = ""
            self._guard_target = None
            self.state, self.detail = RUNNING, ""
            self._event("RESUMED", "collision prediction available")
        return False

    def _apply_stops(self, ctrl: PSMController | None, x: NDArray[np.float64]) -> None:
        """Eq. 15 on ``ctrl`` (the controller about to run, the end effector at ``x (3,)`` [m]):
        the latest prediction's stop coordinates, with the obstacle's side of each, while it
        predicts a collision; none once the path is clear."""
        info = self._collision
        assert info is not None and ctrl is not None
        if info.collision and info.stop_position.shape == (3,) and np.isfinite(info.stop_position).any():
            if not self._stops_set:
                self.collision_stops += 1
                self._event(
                    "COLLISION_PREDICTED",
                    f"collision predicted with {info.obstacle_id}: stop at "
                    + " ".join(
                        f"{'xyz'[d]}={info.stop_position[d]:.3f}"
                        for d in range(3)
                        if math.isfinite(info.stop_position[d])
                    ),
                )
            # Per axis on Python floats (three of them, every tick while a stop is set).
            stop = info.stop_position.tolist()
            xs, goal = x.tolist(), ctrl.goal.tolist()
            same = self._stops_set and info.obstacle_id == self._stop_obstacle
            side = [0.0, 0.0, 0.0]
            for d in range(3):
                s_d = stop[d]
                if s_d != s_d:  # NaN: no stop
                    continue
                prev = self._applied_stops[d]
                if same and prev == prev:
                    # The same obstacle as the last prediction: an axis that keeps its stop keeps
                    # the side it had (an axis pushed through its stop would otherwise see the
                    # side turn round), and inside, where a stop is set where the axis is at each
                    # prediction and would follow any drift of the arm deeper into the volume,
                    # the stop itself (the controller's holding spring brings the axis back).
                    side[d] = self._stop_sides[d]
                    if info.inside:
                        stop[d] = prev
                else:
                    # The obstacle's side: the stop lies between the end effector and the
                    # obstacle, or, where it is the end effector's own coordinate (inside), the
                    # goal's side (the axes moving towards the goal would go deeper).
                    side[d] = _sign(s_d - xs[d]) or _sign(goal[d] - xs[d])
            ctrl.set_stops(stop, side)
            self._applied_stops, self._stop_sides = stop, side
            self._stop_obstacle = info.obstacle_id
            self._stops_set = True
        elif self._stops_set:
            ctrl.clear_stops()
            self._stops_set = False
            self._event("PATH_CLEAR", "path clear of obstacles: braked axes resume")

    def _check_blocked(self, rep: StepReport, dt: float) -> None:
        """HOLDING with the obstacle's id while the arm rests at a collision stop it cannot pass."""
        ctrl, info = self._ctrl, self._collision
        assert ctrl is not None
        stopped = self._stops_set and info is not None and MODE_STOP in ctrl.modes
        at_rest = stopped and self.speed <= self.step_spec.velocity_tolerance_mps  # type: ignore[union-attr]
        if at_rest and all(m in (MODE_STOP, MODE_TERMINAL) for m in ctrl.modes):
            assert info is not None
            if self._blocked_by != info.obstacle_id:
                self._blocked_by = info.obstacle_id
                self._event("PAUSED", f"obstacle {info.obstacle_id} blocks the path to the goal")
            self.state, self.detail = HOLDING, f"obstacle {info.obstacle_id} blocks the path to the goal"
            rep.hold_s += dt
        elif self._blocked_by:
            self._blocked_by = ""
            self.state, self.detail = RUNNING, ""
            self._event("RESUMED", "path clear of obstacles")

    def _guard_stop(
        self, x: NDArray[np.float64], v: NDArray[np.float64], quat: NDArray[np.float64]
    ) -> PlannerOutput:
        """Brake every axis to rest (the hold law towards the stopping point ``x + v/ω``)."""
        if self._guard_target is None:
            x_arr, v_arr = np.asarray(x, dtype=float), np.asarray(v, dtype=float)
            self._guard_target = x_arr + v_arr / self.task.hold_omega
        a = self._tracking(self._guard_target, None, x, v)
        return PlannerOutput(a, self._last_quat, np.zeros(3))

    # ------------------------------------------------------------------ transitions
    def _start_resumed(
        self, index: int, now_ns: int, x: NDArray[np.float64], quat: NDArray[np.float64]
    ) -> None:
        """The first state of a resumed task: step ``index`` starts from it (or, the task being
        done, the arm is held where it is)."""
        n = len(self.task.steps)
        self.resumes.append({"at_step": index, "tick": self._tick})
        if index >= n:
            self.index = n - 1
            self._phase, self.state, self.detail = "done", DONE, ""
            self._hold_target = np.asarray(x, dtype=float).copy()
            self._hold_quat = self._last_quat
            self._event("STARTED", f"task {self.task.name} resumed: all {n} steps were completed")
            return
        self._event(
            "STARTED",
            f"task {self.task.name} resumed at step {index + 1}/{n} ({self.task.steps[index].name}) "
            f"from the arm's state, {index} completed before",
        )
        self._start_step(index, now_ns, x, quat)

    def _start_step(self, index: int, now_ns: int, x: NDArray[np.float64], quat: NDArray[np.float64]) -> None:
        self.index = index
        spec = self.task.steps[index]
        model = self.models[spec.name]
        goal, _vel, _why = self.goals.resolve(spec, now_ns)
        self._ctrl = model.controller(goal if goal is not None else model.goal, **spec.controller)
        self._stops_set, self._blocked_by = False, ""
        self._set_goal(goal)
        self._event_goal = None if goal is None else goal.copy()
        self._segments = ()
        profile = self.profiles.get(spec.name)
        if spec.orientation == "hold" or profile is None:
            profile = OrientationProfile.constant(quat)
        self._orient = OrientationTracker(profile, quat)
        # The reference dimension's t_e drives the orientation; if it does not move in this
        # step (a hold dimension), the slowest dimension's t_e does.
        d = self.task.orientation_dim
        self._orient_dim = -1 if d in model.hold_dimensions else d
        self._phase, self._phase_since_ns = "run", now_ns
        self._hold_target = None
        self.state, self.detail = RUNNING, ""
        x = np.asarray(x, dtype=float)
        rep = StepReport(spec.name, index, spec.goal, now_ns, x.copy(), self.demos.get(spec.name))
        if goal is not None:
            rep.set_goal(goal, x)
        self.reports.append(rep)
        self._event(
            "STARTED",
            f"step {spec.name} towards {spec.goal}"
            + (f" at {np.round(goal, 3).tolist()}" if goal is not None else " (waiting for it)"),
        )

    def _resume(self, spec: StepSpec, now_ns: int, x: NDArray[np.float64], quat: NDArray[np.float64]) -> None:
        """The goal is back: after a hold the same PSM resumes from the current state; after a
        detour to neutral the step starts afresh from there."""
        rep = self.reports[-1]
        if self._phase == "neutral":
            model = self.models[spec.name]
            goal, _v, _w = self.goals.resolve(spec, now_ns)
            self._ctrl = model.controller(goal, **spec.controller)
            self._stops_set, self._blocked_by = False, ""
            self._orient = OrientationTracker(
                self._orient.profile if self._orient else OrientationProfile.constant(quat), quat
            )
            self._segments = ()
        if not rep.has_goal:
            goal, _v, _w = self.goals.resolve(spec, now_ns)
            if goal is not None:
                rep.set_goal(goal, x)
        self._phase, self._phase_since_ns = "run", now_ns
        self._hold_target = None
        self.state, self.detail = RUNNING, ""
        self._event("RESUMED", f"goal {spec.goal} available")

    def _finish_step(
        self, now_ns: int, x: NDArray[np.float64], quat: NDArray[np.float64], *, success: bool, outcome: str
    ) -> None:
        spec = self.step_spec
        assert spec is not None
        rep = self.reports[-1]
        rep.end_ns, rep.success, rep.outcome = now_ns, success, outcome
        if self._goal is not None:
            rep.goal = self._goal.copy()
        if spec.gripper:
            self._event("GRIPPER", spec.gripper)
        self._event("STEP_COMPLETED", f"step {spec.name} {outcome}", rep.summary())
        if self.index + 1 < len(self.task.steps):
            self._start_step(self.index + 1, now_ns, x, quat)
        else:
            self._phase, self.state, self.detail = "done", DONE, ""
            self._hold_target = np.asarray(x, dtype=float).copy()
            self._hold_quat = self._last_quat
            self._event("COMPLETED", f"task {self.task.name} completed", self.summary())

    def _fail(self, why: str) -> None:
        rep = self.reports[-1]
        rep.end_ns, rep.success, rep.outcome = self._now_ns, False, "timeout"
        self._phase, self.state, self.detail = "fault", FAULT, why
        self._hold_target = None
        self._event("ABORTED", why, self.summary())

    def _timed_out(self, spec: StepSpec, rep: StepReport, now_ns: int) -> bool:
        limit = spec.timeout_s or (3.0 * self.models[spec.name].demo_duration + 5.0)
        return (now_ns - rep.start_ns) * 1e-9 - rep.hold_s > limit

    # ------------------------------------------------------------------ laws
    def _orientation(self, ctrl: PSMController) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        assert self._orient is not None
        te = ctrl.time_to_go_tuple
        return self._orient.update(max(te) if self._orient_dim < 0 else te[self._orient_dim])

    def _tracking(
        self,
        target: NDArray[np.float64],
        target_velocity: NDArray[np.float64] | None,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """Critically damped tracking of ``target (3,)`` [m] moving at ``target_velocity (3,)``
        [m/s] (None: still), natural frequency ``hold_omega``, limited to ``hold_max_accel``."""
        dv = -v if target_velocity is None else target_velocity - v
        a = self._kp * (target - x) + self._kd * dv
        n = math.sqrt(float(a @ a))
        return a * (self.task.hold_max_accel / n) if n > self.task.hold_max_accel else a

    def _hold(
        self, x: NDArray[np.float64], v: NDArray[np.float64], quat: NDArray[np.float64]
    ) -> PlannerOutput:
        """Critically damped stop at the stopping point ``x + v/ω`` (no reversal), limited to
        ``hold_max_accel``; the orientation reference is kept."""
        if self._hold_target is None:
            self._hold_target = np.asarray(x, dtype=float) + np.asarray(v, dtype=float) / self.task.hold_omega
            self._hold_quat = self._last_quat
        a = self._tracking(self._hold_target, None, x, v)
        q = self._hold_quat if self._hold_quat is not None else np.asarray(quat, dtype=float)
        return PlannerOutput(a, q, np.zeros(3))

    # ------------------------------------------------------------------ reporting
    def summary(self) -> dict[str, Any]:
        """The task's figures: per step (:meth:`StepReport.summary`) and overall."""
        steps = [r.summary() for r in self.reports]
        done = [r for r in self.reports if r.end_ns]
        return {
            "task": self.task.name,
            "state": self.state,
            "detail": self.detail,
            "steps_total": len(self.task.steps),
            "steps_succeeded": sum(1 for r in self.reports if r.success),
            "success": self.state == DONE and all(r.success for r in self.reports),
            "duration_s": (done[-1].end_ns - self.reports[0].start_ns) * 1e-9 if done else None,
            "steps": steps,
            "resumes": list(self.resumes),
        }

    def summary_json(self) -> str:
        """:meth:`summary` as compact JSON."""
        return json.dumps(self.summary(), separators=(",", ":"), default=float)


def _floats(a: NDArray[np.float64] | Any) -> list[float]:
    """The elements of a 1-D array (or sequence) as plain floats."""
    return a.tolist() if isinstance(a, np.ndarray) else [float(e) for e in a]


def _angle_deg(q1: NDArray[np.float64], q2: NDArray[np.float64]) -> float:
    """Angle between two unit quaternions, degrees."""
    a, b = _floats(q1), _floats(q2)
    d = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
    return math.degrees(2.0 * math.acos(min(1.0, d)))
