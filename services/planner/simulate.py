"""A task run in process: the planner's :class:`~services.planner.sequencer.TaskRunner` driving
the simulated arm (:class:`~services.arm.sim.ArmSim`) tick by tick, without the bus.

The same control code as the planner service, with the arm's own integration, limits and
orientation controller, so option choices and generalisation checks (``benchmarks/feeding.py``,
the tests) run in seconds; the end-to-end tests and ``psm up`` run the same thing over Zenoh.

    result = simulate_task(load_feeding(), load_task_models(task, cache), goals=moving_person)
    result.summary["success"], result.trace["x"]
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.planner.models import TaskModels
from services.planner.sequencer import CollisionInfo, CollisionPolicy, TaskRunner
from services.threads import blas_threads

__all__ = [
    "CollisionFn",
    "GoalUpdate",
    "LiveGoalFn",
    "SimulationResult",
    "monitor_predictor",
    "segment_predictor",
    "simulate_task",
]

#: Live goals at sim time ``t`` [s]: ``{name: (position (3,) [m], valid)}``.
LiveGoalFn = Callable[[float], Mapping[str, tuple[Any, bool]]]

@dataclass(frozen=True)
class GoalUpdate:
    """A live goal update offered to the planner before it answers the state of ``tick``:
    ``position (3,)`` [m], the update's own ``stamp_ns`` [ns] and validity (a stack run's
    ``goals/<name>`` messages, at the ticks its planner received them)."""

    tick: int
    name: str
    position: tuple[float, float, float]
    stamp_ns: int
    valid: bool = True


#: The obstacle monitor in process: ``(stamp_ns, tick, x (3,), v (3,), goal (3,) or None, q (n,),
#: dq (n,), dt_s)`` → the prediction for that state (None: no prediction this tick).
CollisionFn = Callable[..., CollisionInfo | None]


def monitor_predictor(obstacles: Sequence[Any], robot: Any | None = None, **section: Any) -> CollisionFn:
    """The obstacle monitor's logic (:class:`~services.obstacle_monitor.monitor.ObstacleMonitor`:
    segment test, and the whole-arm clearance when ``robot`` is given) as a :data:`CollisionFn`.
    ``obstacles`` are added at the first state; ``section`` sets ``[obstacle_monitor]`` fields
    (``margin_m``, ``clearance_every``, ...; the start list must stay empty)."""
    from services.obstacle_monitor.config import ObstacleMonitorSection
    from services.obstacle_monitor.monitor import ObstacleMonitor

    mon = ObstacleMonitor(ObstacleMonitorSection(**section), robot)
    for ob in obstacles:
        problem = mon.add(ob)
        if problem:
            raise ValueError(f"obstacle {ob.id}: {problem}")

    def predict(
        stamp_ns: int, tick: int, x: Any, v: Any, goal: Any, q: Any, dq: Any, dt_s: float
    ) -> CollisionInfo:
        mon.set_goal(goal)
        p = mon.check(stamp_ns, tick, np.asarray(x), np.asarray(v), np.asarray(q), np.asarray(dq), dt_s)
        return CollisionInfo(
            stamp_ns, tick, p.collision, p.obstacle_id, p.stop_position, p.protective_stop,
            p.min_clearance_m, p.closest_link, p.detail, p.inside,
        )

    predict.monitor = mon  # type: ignore[attr-defined]
    return predict


def segment_predictor(obstacles: Sequence[Any], inflation_m: float, horizon_s: float = 0.0) -> CollisionFn:
    """The monitor's segment test alone (no whole-arm clearance), obstacles inflated by
    ``inflation_m`` [m], as a :data:`CollisionFn`."""
    return monitor_predictor(
        obstacles, None, margin_m=inflation_m, tool_radius_m=0.0, horizon_s=horizon_s, clearance=False
    )


@dataclass
class SimulationResult:
    """``summary``: :meth:`TaskRunner.summary`; ``trace``: per tick ``tick (N,)``, ``t (N,)`` [s],
    ``x, v (N, 3)`` [m, m/s], ``a (N, 3)`` the measured end-effector acceleration [m/s²],
    ``a_cmd (N, 3)`` the command [m/s²], ``omega_cmd (N, 3)`` [rad/s], ``quat, quat_ref (N, 4)``,
    ``goal (N, 3)`` (NaN while none), ``step (N,)``, ``state (N,)`` (the runner's state name),
    ``q, dq (N, n)`` joints [rad, rad/s]; with ``collision`` also ``collision (N,)`` (bool),
    ``protective_stop (N,)`` and ``min_clearance (N,)`` [m] of the prediction applied at each tick
    (NaN where none); ``events``: every transition."""

    summary: dict[str, Any]
    trace: dict[str, NDArray[Any]]
    events: list[Any]
    runner: TaskRunner


@blas_threads(1)
def simulate_task(
    config: Any,
    models: TaskModels,
    *,
    goals: LiveGoalFn | None = None,
    goal_rate_hz: float = 30.0,
    goal_updates: Sequence[GoalUpdate] = (),
    start_pose: str | list[float] = "ready",
    dt_s: float = 0.002,
    max_s: float = 120.0,
    arm: Mapping[str, Any] | None = None,
    collision: CollisionFn | None = None,
    prediction_max_age_s: float = 0.02,
    joint_accel_fraction: float | None = None,
) -> SimulationResult:
    """Run ``config`` (a :class:`~services.tasks.feeding.FeedingConfig`: scene + task) to its end
    (done or aborted) or ``max_s`` of sim time. Linear algebra runs on one BLAS thread, as in the
    services (:func:`services.threads.blas_threads`), so that the run rounds as the stack does.

    Args:
        models: from :func:`services.planner.models.load_task_models`.
        goals: live goal positions over sim time, sampled at ``goal_rate_hz`` (a camera's rate).
        goal_updates: live goal updates at given ticks (e.g. those a stack run's planner
            received, :func:`experiments.harness.goal_schedule`), in order.
        start_pose: the arm's start pose (named or joints).
        dt_s: control period [s].
        arm: further :class:`~services.arm.sim.ArmSimConfig` fields.
        collision: the obstacle monitor in process (e.g. :func:`segment_predictor`): called on
            every state with the planner's last goal (as the planner publishes it: the last goal
            it used, kept while it has none), its prediction is applied at once (as in a
            lockstep run over the bus).
        prediction_max_age_s: the planner's ``prediction_max_age_s`` (with ``collision``).
        joint_accel_fraction: the planner's ``joint_accel_fraction`` (None: its default; 0: the
            commands are not scaled into the joint limits).
    """
    from services.arm.config import ArmSection
    from services.arm.sim import ArmSim
    from services.planner.config import PlannerSection
    from services.planner.feasibility import JointAccelerationScaling
    from services.robot.protocol import Command, CommandMode

    section = ArmSection(dt_s=dt_s, start_pose=start_pose, **dict(arm or {}))
    robot = section.load_robot()
    sim = ArmSim(robot, section)
    policy = CollisionPolicy(prediction_max_age_s) if collision is not None else None
    if joint_accel_fraction is None:
        joint_accel_fraction = PlannerSection.model_fields["joint_accel_fraction"].default
    # The planner's own instance of the robot (the simulator's model data is the arm's).
    feasibility = None
    if joint_accel_fraction > 0.0:
        feasibility = JointAccelerationScaling(robot.with_own_data(), joint_accel_fraction)
    runner = TaskRunner(
        config.task, config.scene.positions(), models.models, models.profiles, models.demos, collision=policy,
        feasibility=feasibility,
    )
    goal_every = max(1, round(1.0 / (goal_rate_hz * dt_s))) if goals is not None else 0
    pending = sorted(goal_updates, key=lambda u: u.tick)
    next_update = 0
    n_max = int(max_s / dt_s)
    names = ("tick", "t", "x", "v", "a", "a_cmd", "omega_cmd", "quat", "quat_ref", "goal", "step", "state",
             "q", "dq")
    if collision is not None:
        names += ("collision", "protective_stop", "min_clearance")
    rows: dict[str, list[Any]] = {k: [] for k in names}
    events: list[Any] = []
    last_stamp: int | None = None  # the last state answered: the planner's clock for goal stamps
    monitor_goal = None  # the goal the planner last published (kept while it has none)
    for k in range(n_max):
        snap = sim.snapshot()
        t_ns = snap.time_ns
        if goal_every and k % goal_every == 0:
            assert goals is not None
            for name, (pos, valid) in goals(t_ns * 1e-9).items():
                runner.update_goal(name, pos, t_ns, valid)
        while next_update < len(pending) and pending[next_update].tick <= snap.tick:
            u = pending[next_update]
            runner.update_goal(u.name, u.position, u.stamp_ns, u.valid, now_ns=last_stamp)
            next_update += 1
        ee = snap.ee
        info = None
        if collision is not None:
            if runner.goal is not None:
                monitor_goal = runner.goal
            info = collision(
                t_ns, snap.tick, ee.position, ee.linear_velocity, monitor_goal, snap.q, snap.dq, dt_s
            )
            if info is not None:
                runner.set_collision(info)
        out = runner.step(
            t_ns,
            ee.position,
            ee.linear_velocity,
            ee.quat_xyzw,
            dt_s,
            tick=snap.tick,
            measured_accel=ee.linear_acceleration,
            joints=lambda snap=snap: (snap.q, snap.dq),
        )
        last_stamp = t_ns
        events.extend(runner.drain_events())
        g = runner.goal
        rows["tick"].append(snap.tick)
        rows["t"].append(t_ns * 1e-9)
        rows["x"].append(ee.position)
        rows["v"].append(ee.linear_velocity)
        rows["a"].append(ee.linear_acceleration)
        rows["a_cmd"].append(out.acceleration)
        rows["omega_cmd"].append(out.angular_velocity)
        rows["quat"].append(ee.quat_xyzw)
        rows["quat_ref"].append(out.orientation)
        rows["goal"].append(g if g is not None else np.full(3, np.nan))
        rows["step"].append(runner.index)
        rows["state"].append(runner.state)
        rows["q"].append(snap.q)
        rows["dq"].append(snap.dq)
        if collision is not None:
            rows["collision"].append(bool(info.collision) if info is not None else False)
            rows["protective_stop"].append(bool(info.protective_stop) if info is not None else False)
            rows["min_clearance"].append(float(info.min_clearance_m) if info is not None else math.nan)
        if runner.state in ("DONE", "FAULT"):
            break
        sim.submit(
            Command(snap.tick, CommandMode.CARTESIAN, out.acceleration, out.orientation, out.angular_velocity)
        )
        sim.step()
    trace = {k: np.asarray(v) for k, v in rows.items()}
    return SimulationResult(runner.summary(), trace, events, runner)
