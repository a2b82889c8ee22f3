"""Configuration of the planner service: the ``[planner]`` table on top of the shared bus settings.

The task itself (scene and steps) is its own file, ``task_file`` (default the shipped
``configs/feeding.toml``; :mod:`services.planner.task`)::

    [planner]
    task_file = "configs/feeding.toml"
    cache_dir = "out/models"        # learned models, by content hash
    status_rate_hz = 20.0
    exit_when_done = true           # psm up: the stack ends when the task does
    collision_check = "required"    # act on the obstacle monitor; no fresh prediction = brake
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.bus.config import ConfigError, Section, ServiceConfig
from services.goal_tracker.frames import SyntheticSection
from services.robot.description import ArmRobotView
from services.robot.protocol import MAX_TICK_GAP, RESYNC_AFTER, STAMP_TOLERANCE_S

__all__ = ["PlannerConfig", "PlannerSection"]


class PlannerSection(Section):
    """The ``[planner]`` table (units in the field descriptions)."""

    task_file: str = Field("", description="scene + task TOML ('' = the shipped configs/feeding.toml)")
    demos_dir: str = Field("", description="directory of the step demonstrations ('' = data/demos)")
    cache_dir: str = Field("out/models", description="learned models are cached here ('' = no cache)")
    status_rate_hz: float = Field(20.0, ge=1.0, le=100.0, description="PlannerStatus rate [Hz]")
    viz_path_points: int = Field(
        400, ge=2, le=10_000,
        description="most points of the end-effector path on <prefix>/viz/plan (halved when full)",
    )
    viz_path_step_m: float = Field(
        0.002, ge=0.0, le=0.1,
        description="the viz path gets a point once the end effector moved this far [m]",
    )
    exit_when_done: bool = Field(
        False, description="exit once the task is done (code 0) or aborted (code 1), after linger_s"
    )
    linger_s: float = Field(
        0.5, ge=0.0, le=60.0, description="keep answering states this long after the task ends [s]"
    )
    summary_file: str = Field("", description="write the task summary (JSON) here at exit")
    progress_file: str = Field(
        "",
        description="the task's progress (JSON), written atomically at each step transition and read at "
        "start: a restarted planner resumes the step that was running ('' = every start runs the task "
        "from its first step)",
    )
    max_tick_gap: int = Field(
        MAX_TICK_GAP, ge=1, description="an arm state more than this many ticks ahead of the last is rejected"
    )
    resync_after: int = Field(
        RESYNC_AFTER, ge=1,
        description="after this many rejected states in a row that form a stream of their own, follow it "
        "(arm restart)",
    )
    stamp_tolerance_s: float = Field(
        STAMP_TOLERANCE_S, gt=0.0,
        description="a state stamp this far off tick x dt from the last is rejected [s]",
    )
    source: str = Field("planner", min_length=1, description="the commands' source field")
    rt_priority: int = Field(
        0, ge=0, le=99, description="SCHED_FIFO priority of the planner process, 1-99 (0 = normal scheduling)"
    )
    collision_check: Literal["off", "required"] = Field(
        "off",
        description="'required': act on the obstacle monitor's predictions and brake to rest without a "
        "fresh one; 'off': no obstacle handling",
    )
    prediction_max_age_s: float = Field(
        0.02,
        gt=0.0,
        le=5.0,
        description="a collision prediction older than this (stack clock) counts as none [s]",
    )
    joint_accel_fraction: float = Field(
        0.8, ge=0.0, le=1.0,
        description="scale each command so that its linear acceleration needs at most this fraction of "
        "every joint's acceleration limit, the rest left to the arm's orientation and posture terms (the "
        "robot: the [arm] table's; 0 = no scaling)",
    )
    monitor_service: str = Field(
        "obstacle_monitor", min_length=1, description="the obstacle monitor's service name (liveliness)"
    )
    live_goal_sync: bool = Field(
        False,
        description="lockstep: answer a state only once the live goals of every camera frame due at its "
        "time are in (the synthetic camera's frames on the arm's clock, [goal_tracker.synthetic]), so that "
        "a run with live goals is reproducible tick by tick; realtime: no effect",
    )
    live_goal_wait_s: float = Field(
        10.0, gt=0.0, le=600.0,
        description="live_goal_sync: the longest wait for one frame's goals [s, wall clock]; after it the "
        "state is answered with the goals known and the sync pauses until the next goal arrives",
    )
    tracker_service: str = Field(
        "goal_tracker", min_length=1,
        description="live_goal_sync: the goal tracker's service name (liveliness: once it is gone, no wait)",
    )

    def task_path(self) -> Path:
        """The task file to load."""
        from services.tasks.feeding import DEFAULT_FEEDING_CONFIG

        return Path(self.task_file) if self.task_file else DEFAULT_FEEDING_CONFIG

    def check(self) -> None:
        """The task file exists."""
        if not self.task_path().exists():
            raise ConfigError("task_file", f"{self.task_path()}: no such file")


class TrackerFramesView(BaseModel):
    """The ``[goal_tracker]`` table as the planner reads it: the synthetic camera's section only
    (its frame grid, for ``live_goal_sync``), the tracker's other fields ignored."""

    model_config = ConfigDict(extra="ignore", validate_default=True, allow_inf_nan=False)

    synthetic: SyntheticSection = Field(default_factory=SyntheticSection)


class PlannerConfig(ServiceConfig):
    """Config of the ``psm plan`` service: bus settings + ``[planner]``."""

    planner: PlannerSection = Field(default_factory=PlannerSection)
    arm: ArmRobotView = Field(
        default_factory=ArmRobotView,
        description="the robot the arm simulates: the [arm] table's robot fields",
    )
    goal_tracker: TrackerFramesView = Field(
        default_factory=TrackerFramesView,
        description="the synthetic camera's frame grid: the [goal_tracker.synthetic] table",
    )

    @model_validator(mode="after")
    def _sync_needs_frames_on_the_arm_clock(self) -> PlannerConfig:
        if self.planner.live_goal_sync and self.goal_tracker.synthetic.clock != "arm":
            raise ConfigError(
                "planner.live_goal_sync",
                "needs the synthetic camera's frames on the arm's clock "
                "([goal_tracker.synthetic] clock = 'arm')",
            )
        return self
