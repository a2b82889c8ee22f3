"""Configuration of the obstacle monitor: the ``[obstacle_monitor]`` table on top of the shared
bus settings.

The obstacles known at start (they change at run time through ``<prefix>/obstacles/command``)::

    [obstacle_monitor]
    margin_m = 0.03                 # safety margin between the arm and every obstacle
    tool_radius_m = 0.15            # the hand's reach around the end-effector point (+ room)
    clearance_stop_m = 0.03         # whole-arm clearance below this: protective stop

    [[obstacle_monitor.obstacles]]
    id = "box"
    shape = "box"                   # box | sphere | cylinder
    position_m = [0.40, 0.30, 0.20] # centre, base frame
    size_m = [0.30, 0.04, 0.40]     # box: edges; sphere: [diameter, -, -]; cylinder: [diameter, -, height]
    rpy_deg = [0.0, 0.0, 0.0]       # orientation (roll, pitch, yaw about the fixed x, y, z axes)
    velocity_mps = [0.0, 0.0, 0.0]  # a moving obstacle is predicted forward
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from scipy.spatial.transform import Rotation

from psm.obstacles import Obstacle, ObstacleError
from services.bus.config import ConfigError, Section, ServiceConfig, read_toml

__all__ = ["ObstacleMonitorConfig", "ObstacleMonitorSection", "ObstacleSpec"]

Vec3 = list[float]


class ObstacleSpec(Section):
    """One obstacle of the start set (units in the field names)."""

    id: str = Field(min_length=1, description="unique name")
    shape: Literal["box", "sphere", "cylinder"] = Field(description="primitive shape")
    position_m: Vec3 = Field(min_length=3, max_length=3, description="centre in the base frame [m]")
    size_m: Vec3 = Field(
        min_length=3,
        max_length=3,
        description="box: full edges; sphere: [diameter, *, *]; cylinder: [diameter, *, height] [m]",
    )
    rpy_deg: Vec3 = Field([0.0, 0.0, 0.0], min_length=3, max_length=3, description="orientation [deg]")
    velocity_mps: Vec3 = Field([0.0, 0.0, 0.0], min_length=3, max_length=3, description="velocity [m/s]")

    def obstacle(self) -> Obstacle:
        """The validated :class:`~psm.obstacles.Obstacle` (raises :class:`ObstacleError`)."""
        quat = Rotation.from_euler("xyz", self.rpy_deg, degrees=True).as_quat()
        return Obstacle(
            self.id,
            self.shape,
            np.array(self.position_m),
            quat,
            np.array(self.size_m),
            np.array(self.velocity_mps),
        )


class ObstacleMonitorSection(Section):
    """The ``[obstacle_monitor]`` table (units in the field descriptions)."""

    obstacles: list[ObstacleSpec] = Field(default_factory=list, description="the obstacles at start")
    obstacles_file: str = Field(
        "", description="TOML file with more start obstacles as [[obstacles]] tables ('' = none)"
    )
    margin_m: float = Field(
        0.03, ge=0.0, le=0.5, description="safety margin between the arm and every obstacle [m]"
    )
    tool_radius_m: float = Field(
        0.15,
        ge=0.0,
        le=1.0,
        description="the segment test inflates obstacles by margin_m + this: the hand's reach around the "
        "end-effector point, plus room for the whole-arm check's stop distance [m] (the Panda hand's hull "
        "reaches 0.104 m from its TCP)",
    )
    horizon_s: float = Field(
        1.0, ge=0.0, le=10.0, description="moving obstacles: the segment test covers this much motion [s]"
    )
    clearance: bool = Field(True, description="compute the whole-arm clearance (coal, link convex hulls)")
    clearance_every: int = Field(
        5, ge=1, le=500, description="whole-arm clearance every this many ticks (segment test: every tick)"
    )
    clearance_stop_m: float = Field(
        0.02, ge=0.0, le=1.0, description="protective stop when the whole-arm clearance falls below this [m]"
    )
    clearance_resume_m: float = Field(
        0.04, ge=0.0, le=1.0, description="the protective stop ends once the clearance is above this [m]"
    )
    clearance_cutoff_m: float = Field(
        0.5, gt=0.0, le=10.0, description="clearances beyond this are reported as +inf (broad phase) [m]"
    )
    brake_decel_mps2: float = Field(
        3.0,
        gt=0.0,
        le=50.0,
        description="deceleration the planner brakes with on a protective stop (its task hold_max_accel) "
        "[m/s^2]: the stopping distance is added to clearance_stop_m, and the stopping check looks that far",
    )
    stopping_check: bool = Field(
        True,
        description="while the segment to the goal is clear, also test the end effector's stopping path "
        "(one tick at its speed plus braking at brake_decel_mps2, along its velocity)",
    )
    stopping_release_m: float = Field(
        0.01,
        gt=0.0,
        le=0.5,
        description="a stop from the stopping check holds until the end effector is this far from the "
        "surface it headed into, or beside the obstacle [m]",
    )
    scene_rate_hz: float = Field(
        10.0, gt=0.0, le=100.0, description="ObstacleSet/SceneUpdate rate while one moves (stack clock) [Hz]"
    )
    urdf: str = Field("", description="URDF of the robot ('' = the Franka Panda, as the arm)")
    frame_id: str = Field("base", min_length=1, description="frame of the obstacle positions")
    rt_priority: int = Field(
        0, ge=0, le=99,
        description="SCHED_FIFO priority of the monitor process, 1-99 (0 = normal scheduling): it is "
        "part of the control loop when the planner requires its predictions",
    )

    @model_validator(mode="after")
    def _hysteresis(self) -> ObstacleMonitorSection:
        if self.clearance_resume_m < self.clearance_stop_m:
            raise ValueError("clearance_resume_m must be >= clearance_stop_m")
        return self

    def start_obstacles(self) -> list[Obstacle]:
        """The validated start set (raises :class:`ConfigError` naming the obstacle's field)."""
        out: list[Obstacle] = []
        seen: set[str] = set()
        specs = [(f"obstacle_monitor.obstacles[{i}]", s) for i, s in enumerate(self.obstacles)]
        if self.obstacles_file:
            specs += [
                (f"{self.obstacles_file}: obstacles[{i}]", s) for i, s in enumerate(self.file_obstacles())
            ]
        for where, spec in specs:
            if spec.id in seen:
                raise ConfigError(f"{where}.id", f"duplicate obstacle id {spec.id!r}")
            seen.add(spec.id)
            try:
                out.append(spec.obstacle())
            except ObstacleError as exc:
                field = {"position": "position_m", "size": "size_m", "velocity": "velocity_mps"}.get(
                    exc.field, exc.field
                )
                raise ConfigError(f"{where}.{field}", str(exc)) from None
        return out

    def file_obstacles(self) -> list[ObstacleSpec]:
        """The ``[[obstacles]]`` of ``obstacles_file`` (raises :class:`ConfigError` naming the field)."""
        from pydantic import ValidationError

        data = read_toml(self.obstacles_file)
        extra = sorted(set(data) - {"obstacles"})
        if extra:
            raise ConfigError(
                "obstacle_monitor.obstacles_file", f"{self.obstacles_file}: unknown table {extra[0]!r}"
            )
        out = []
        for i, item in enumerate(data.get("obstacles", [])):
            try:
                out.append(ObstacleSpec.model_validate(item))
            except ValidationError as exc:
                err = exc.errors()[0]
                loc = ".".join(str(p) for p in err["loc"])
                where = f"{self.obstacles_file}: obstacles[{i}].{loc}"
                raise ConfigError("obstacle_monitor.obstacles_file", f"{where}: {err['msg']}") from None
        return out

    def check(self) -> None:
        """Every start obstacle is valid."""
        self.start_obstacles()


class ObstacleMonitorConfig(ServiceConfig):
    """Config of the ``psm obstacles`` service: bus settings + ``[obstacle_monitor]``."""

    obstacle_monitor: ObstacleMonitorSection = Field(default_factory=ObstacleMonitorSection)
