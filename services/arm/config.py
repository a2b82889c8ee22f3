"""Configuration of the arm service: the ``[arm]`` table on top of the shared bus settings.

``[arm]`` is the simulator's own parameter model (:class:`~services.arm.sim.ArmSimConfig`:
period, start pose, watchdog, ``[arm.gains]``, ``[arm.validation]``) plus the service's fields
(robot model, frames, rates, statistics). The clock mode is the stack's ``clock``. Loaded with
:func:`services.bus.config.load_config` (TOML < ``PSM_ARM__*`` env vars < flags)::

    clock = "lockstep"          # shared by the whole stack
    [arm]
    dt_s = 0.002                # control period, s (500 Hz); 0.001 for 1 kHz
    start_pose = "ready"        # named pose, or a list of 7 joint angles [rad]
    watchdog_timeout_s = 0.02   # sim time without a valid command before braking
    [arm.gains]
    orientation_kp = 100.0
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from services.arm.sim import ArmSimConfig
from services.bus.config import ConfigError, ServiceConfig, StrList
from services.robot.description import RobotDescription
from services.robot.model import RobotModel


class ArmSection(ArmSimConfig, RobotDescription):
    """The ``[arm]`` table (units in the field descriptions): the simulator's parameters, the
    robot it simulates (:class:`~services.robot.description.RobotDescription`, which the planner
    reads too) and the service's own fields."""

    frame_id: str = Field("base", description="name of the robot base frame (Cartesian quantities, TF root)")
    lockstep_timeout_s: float = Field(
        0.5, gt=0.0, le=60.0, description="lockstep: wall time to wait for the command answering a state [s]"
    )
    transforms_rate_hz: float = Field(
        30.0, ge=0.0, le=1000.0, description="FrameTransforms publication rate (sim time) [Hz]; 0 = off"
    )
    model: Literal["visual", "collision", "off"] = Field(
        "visual",
        description="the URDF geometry published once, latched, on <prefix>/viz/arm for Foxglove's 3-D panel "
        "('off' = none)",
    )
    model_max_bytes: int = Field(
        1_500_000, ge=20_000, le=16_000_000,
        description="budget of the model's mesh data [bytes]: the meshes are decimated to fit",
    )
    max_ticks: int = Field(0, ge=0, description="stop after this many ticks (0 = run until stopped)")
    stats_file: str = Field("", description="write a JSON timing/counter summary here at shutdown")
    rt_priority: int = Field(
        0, ge=0, le=99, description="SCHED_FIFO priority of the arm process, 1-99 (0 = normal scheduling)"
    )
    cpu_latency_us: int = Field(
        -1, ge=-1, le=100_000,
        description="while the arm runs, keep every CPU's wake-up latency at most this [us] (PM QoS, "
        "/dev/cpu_dma_latency; 0: idle CPUs poll instead of halting, which costs power; needs root); "
        "-1 = the machine's idle states apply",
    )
    watch_services: StrList = Field(
        default_factory=list,
        description="services whose liveliness loss drops the held command (brake at once)",
    )

    def load_robot(self) -> RobotModel:
        """Load the configured robot model and check the poses against it (raises
        :class:`ConfigError` on a bad model or pose)."""
        robot = self.robot_model()
        for name in ("start_pose", "posture"):
            pose = getattr(self, name)
            if pose is None:
                continue
            try:
                robot.resolve_pose(pose)
            except ValueError as exc:
                raise ConfigError(f"arm.{name}", str(exc)) from None
        return robot


class ArmConfig(ServiceConfig):
    """Config of the ``psm arm`` service: bus settings + ``[arm]``."""

    arm: ArmSection = Field(default_factory=ArmSection)
