"""Configuration of the arm service: the ``[arm]`` section on top of the bus settings.

Loaded with :func:`services.bus.config.load_config` (TOML < ``PSM_ARM_*`` env vars < flags)::

    [arm]
    dt_s = 0.002                # control period, s (500 Hz); 0.001 for 1 kHz
    clock = "lockstep"          # or "realtime"
    start_pose = "ready"        # named pose, or set start_joints = [7 values, rad]
    watchdog_timeout_s = 0.02   # sim time without a valid command before braking
"""

from __future__ import annotations

from dataclasses import dataclass, field

from services.arm.controller import ControllerGains, ValidationLimits
from services.arm.sim import ArmSimConfig
from services.bus.config import ConfigError, ServiceConfig, meta, spec
from services.robot.model import RobotModel


@dataclass
class ArmSection:
    """The ``[arm]`` section (units in the field names' help)."""

    urdf: str = spec("", "URDF file of the robot ('' = Franka Panda from example-robot-data)")
    ee_frame: str = spec("", "end-effector frame ('' = panda_hand_tcp / the last frame)")
    locked_joints: list[str] | None = field(
        default=None,
        metadata=meta("joints fixed at their neutral value (unset = the Panda's fingers)"),
    )
    accel_limits: list[float] = field(
        default_factory=list,
        metadata=meta("joint acceleration limits, rad/s^2 (empty = Panda datasheet / 10)"),
    )
    frame_id: str = spec("base", "name of the robot base frame (Cartesian quantities, TF root)")
    start_pose: str = spec("ready", "named start pose (ready, home, neutral, middle)")
    start_joints: list[float] = field(
        default_factory=list, metadata=meta("explicit start joint vector, rad (wins if set)")
    )
    posture: list[float] = field(
        default_factory=list, metadata=meta("null-space posture, rad (empty = start pose)")
    )
    dt_s: float = spec(0.002, "control period, s", gt=0.0, le=0.1)
    clock: str = spec("realtime", "clock mode", choices=("realtime", "lockstep"))
    lockstep_timeout_s: float = spec(
        0.5, "lockstep: wall time to wait for the command answering a state", gt=0.0, le=60.0
    )
    watchdog_timeout_s: float = spec(
        0.02, "sim time without a valid command before braking, s", ge=0.0, le=10.0
    )
    transforms_rate_hz: float = spec(
        30.0, "FrameTransforms publication rate (sim time), Hz; 0 = off", ge=0.0, le=1000.0
    )
    max_ticks: int = spec(0, "stop after this many ticks (0 = run until stopped)", ge=0)
    stats_file: str = spec("", "write a JSON timing/counter summary here at shutdown")
    rt_priority: int = spec(
        0, "SCHED_FIFO priority of the arm process, 1-99 (0 = normal scheduling)", ge=0, le=99
    )
    watch_services: list[str] = field(
        default_factory=list,
        metadata=meta("services whose liveliness loss drops the held command (brake at once)"),
    )
    orientation_kp: float = spec(100.0, "orientation PD stiffness, 1/s^2", ge=0.0)
    orientation_kd: float = spec(20.0, "orientation PD damping, 1/s", ge=0.0)
    nullspace_kp: float = spec(10.0, "null-space posture stiffness, 1/s^2", ge=0.0)
    nullspace_kd: float = spec(6.0, "null-space joint damping, 1/s", ge=0.0)
    singular_epsilon: float = spec(0.04, "sigma_min(J) below which DLS damping starts", gt=0.0)
    damping_max: float = spec(0.05, "maximum DLS damping lambda", ge=0.0)
    max_linear_acceleration: float = spec(
        50.0, "commands above this EE acceleration norm are rejected, m/s^2", gt=0.0
    )
    max_angular_velocity: float = spec(
        10.0, "commands above this angular velocity norm are rejected, rad/s", gt=0.0
    )
    max_joint_acceleration: float = spec(
        100.0, "joint commands above this magnitude are rejected, rad/s^2", gt=0.0
    )

    def validate(self) -> None:
        """Cross-field checks."""
        if self.watchdog_timeout_s < self.dt_s:
            raise ConfigError("watchdog_timeout_s", "must be at least one control period dt_s")
        if abs(round(self.dt_s * 1e9) - self.dt_s * 1e9) > 1e-3:
            raise ConfigError("dt_s", "must be a whole number of nanoseconds")

    @property
    def dt_ns(self) -> int:
        """Control period in integer ns."""
        return round(self.dt_s * 1e9)

    def load_robot(self) -> RobotModel:
        """Load the configured robot model (raises :class:`ConfigError` on a bad model)."""
        try:
            return RobotModel.load(
                self.urdf or None,
                self.ee_frame or None,
                self.locked_joints,
                self.accel_limits or None,
            )
        except (ValueError, FileNotFoundError) as exc:
            raise ConfigError("arm.urdf", str(exc)) from None

    def sim_config(self, robot: RobotModel) -> ArmSimConfig:
        """The :class:`ArmSimConfig` for this section (start pose checked against ``robot``)."""
        start: str | list[float] = list(self.start_joints) if self.start_joints else self.start_pose
        try:
            robot.resolve_pose(start)
            if self.posture:
                robot.resolve_pose(self.posture)
        except ValueError as exc:
            raise ConfigError("arm.start_pose", str(exc)) from None
        return ArmSimConfig(
            dt_ns=self.dt_ns,
            start_pose=start,
            posture=list(self.posture) if self.posture else None,
            watchdog_timeout_ns=round(self.watchdog_timeout_s * 1e9),
            gains=ControllerGains(
                orientation_kp=self.orientation_kp,
                orientation_kd=self.orientation_kd,
                nullspace_kp=self.nullspace_kp,
                nullspace_kd=self.nullspace_kd,
                singular_epsilon=self.singular_epsilon,
                damping_max=self.damping_max,
            ),
            validation=ValidationLimits(
                max_linear_acceleration=self.max_linear_acceleration,
                max_angular_velocity=self.max_angular_velocity,
                max_joint_acceleration=self.max_joint_acceleration,
            ),
        )


@dataclass
class ArmConfig(ServiceConfig):
    """Config of the ``psm arm`` service: bus settings + ``[arm]``."""

    arm: ArmSection = field(default_factory=ArmSection)
