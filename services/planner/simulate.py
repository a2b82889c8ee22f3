"""A task run in process: the planner's :class:`~services.planner.sequencer.TaskRunner` driving
the simulated arm (:class:`~services.arm.sim.ArmSim`) tick by tick, without the bus.

The same control code as the planner service, with the arm's own integration, limits and
orientation controller, so option choices and generalisation checks (``benchmarks/feeding.py``,
the tests) run in seconds; the end-to-end tests and ``psm up`` run the same thing over Zenoh.

    result = simulate_task(load_feeding(), load_task_models(task, cache), goals=moving_person)
    result.summary["success"], result.trace["x"]
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.planner.models import TaskModels
from services.planner.sequencer import TaskRunner

__all__ = ["LiveGoalFn", "SimulationResult", "simulate_task"]

#: Live goals at sim time ``t`` [s]: ``{name: (position (3,) [m], valid)}``.
LiveGoalFn = Callable[[float], Mapping[str, tuple[Any, bool]]]


@dataclass
class SimulationResult:
    """``summary``: :meth:`TaskRunner.summary`; ``trace``: per tick ``t (N,)`` [s], ``x, v (N, 3)``,
    ``a_cmd (N, 3)``, ``quat, quat_ref (N, 4)``, ``goal (N, 3)`` (NaN while none), ``step (N,)``;
    ``events``: every transition."""

    summary: dict[str, Any]
    trace: dict[str, NDArray[Any]]
    events: list[Any]
    runner: TaskRunner


def simulate_task(
    config: Any,
    models: TaskModels,
    *,
    goals: LiveGoalFn | None = None,
    goal_rate_hz: float = 30.0,
    start_pose: str | list[float] = "ready",
    dt_s: float = 0.002,
    max_s: float = 120.0,
    arm: Mapping[str, Any] | None = None,
) -> SimulationResult:
    """Run ``config`` (a :class:`~services.tasks.feeding.FeedingConfig`: scene + task) to its end
    (done or aborted) or ``max_s`` of sim time.

    Args:
        models: from :func:`services.planner.models.load_task_models`.
        goals: live goal positions over sim time, sampled at ``goal_rate_hz`` (a camera's rate).
        start_pose: the arm's start pose (named or joints).
        dt_s: control period [s].
        arm: further :class:`~services.arm.sim.ArmSimConfig` fields.
    """
    from services.arm.config import ArmSection
    from services.arm.sim import ArmSim
    from services.robot.protocol import Command, CommandMode

    section = ArmSection(dt_s=dt_s, start_pose=start_pose, **dict(arm or {}))
    robot = section.load_robot()
    sim = ArmSim(robot, section)
    runner = TaskRunner(config.task, config.scene.positions(), models.models, models.profiles, models.demos)
    goal_every = max(1, round(1.0 / (goal_rate_hz * dt_s))) if goals is not None else 0
    n_max = int(max_s / dt_s)
    rows: dict[str, list[Any]] = {k: [] for k in ("t", "x", "v", "a_cmd", "quat", "quat_ref", "goal", "step")}
    events: list[Any] = []
    for k in range(n_max):
        snap = sim.snapshot()
        t_ns = snap.time_ns
        if goal_every and k % goal_every == 0:
            assert goals is not None
            for name, (pos, valid) in goals(t_ns * 1e-9).items():
                runner.update_goal(name, pos, t_ns, valid)
        ee = snap.ee
        out = runner.step(
            t_ns,
            ee.position,
            ee.linear_velocity,
            ee.quat_xyzw,
            dt_s,
            tick=snap.tick,
            measured_accel=ee.linear_acceleration,
        )
        events.extend(runner.drain_events())
        g = runner.goal
        rows["t"].append(t_ns * 1e-9)
        rows["x"].append(ee.position)
        rows["v"].append(ee.linear_velocity)
        rows["a_cmd"].append(out.acceleration)
        rows["quat"].append(ee.quat_xyzw)
        rows["quat_ref"].append(out.orientation)
        rows["goal"].append(g if g is not None else np.full(3, np.nan))
        rows["step"].append(runner.index)
        if runner.state in ("DONE", "FAULT"):
            break
        sim.submit(
            Command(snap.tick, CommandMode.CARTESIAN, out.acceleration, out.orientation, out.angular_velocity)
        )
        sim.step()
    trace = {k: np.asarray(v) for k, v in rows.items()}
    return SimulationResult(runner.summary(), trace, events, runner)
