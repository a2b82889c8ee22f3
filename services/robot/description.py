"""The robot the stack drives, described once: the robot fields of the ``[arm]`` table.

The arm simulates this robot; the planner reads the same fields of the same ``[arm]`` table
(:class:`ArmRobotView`, which ignores the arm's other fields) to know the joint acceleration
limits its commands must respect. So a stack file names its URDF, end-effector frame, locked
joints and acceleration limits in one place::

    [arm]
    urdf = ""                   # '' = the Franka Panda of example-robot-data
    accel_limits = []           # [rad/s^2] per joint; [] = the Panda datasheet
"""

from __future__ import annotations

from pydantic import ConfigDict, Field

from services.bus.config import ConfigError, Section
from services.robot.model import RobotModel

__all__ = ["ArmRobotView", "RobotDescription"]


class RobotDescription(Section):
    """The robot fields of the ``[arm]`` table (units in the field descriptions)."""

    urdf: str = Field("", description="URDF file of the robot ('' = Franka Panda from example-robot-data)")
    ee_frame: str = Field("", description="end-effector frame ('' = panda_hand_tcp / the last frame)")
    locked_joints: list[str] | None = Field(
        None, description="joints fixed at their neutral value (unset = the Panda's fingers)"
    )
    accel_limits: list[float] = Field(
        default_factory=list,
        description="joint acceleration limits [rad/s^2] (empty = Panda datasheet; 10 for other robots)",
    )

    def robot_model(self) -> RobotModel:
        """Load the described robot (a bad model raises :class:`ConfigError` naming
        ``arm.urdf``)."""
        try:
            return RobotModel.load(
                self.urdf or None, self.ee_frame or None, self.locked_joints, self.accel_limits or None
            )
        except (ValueError, FileNotFoundError) as exc:
            raise ConfigError("arm.urdf", str(exc)) from None


class ArmRobotView(RobotDescription):
    """The ``[arm]`` table as another service reads it: the robot fields only, the arm's other
    fields ignored (they are the arm's to validate)."""

    model_config = ConfigDict(
        extra="ignore", validate_default=True, validate_assignment=True, allow_inf_nan=False
    )
