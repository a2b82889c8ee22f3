"""The robot, shared by every service that needs it (arm, obstacle monitor, planner).

* :mod:`services.robot.model` — :class:`RobotModel`: URDF loading, joint limits, forward
  kinematics, Jacobians, link placements, position IK (Pinocchio);
* :mod:`services.robot.rotations` — quaternion ``(x, y, z, w)`` ↔ rotation matrix (scipy);
* :mod:`services.robot.protocol` — the arm's bus protocol: ``ArmState``/``ArmCommand`` builders
  and parsers and the decoded types (:class:`Command`, :class:`CommandMode`,
  :class:`ArmStateData`, :class:`EEState`), free of Pinocchio and of the arm simulator;
* :mod:`services.robot.recordings` — a recording's end-effector trajectory by forward
  kinematics (what ``psm learn`` and the planner learn from).

The names below are importable from ``services.robot`` directly; each submodule is imported on
first use, so ``from services.robot import cartesian_command`` does not load Pinocchio.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from services.robot.model import (
        PANDA_ACCEL_LIMITS,
        PANDA_EE_FRAME,
        PANDA_LOCKED_JOINTS,
        PANDA_NAMED_POSES,
        JointLimits,
        RobotModel,
        panda_urdf_path,
    )
    from services.robot.protocol import (
        ArmStateData,
        Command,
        CommandMode,
        CommandRejectedError,
        EEState,
        StateLike,
        cartesian_command,
        command_from_message,
        frame_transforms,
        joint_command,
        state_from_message,
        state_message,
    )
    from services.robot.recordings import TEACH_METADATA, ee_trajectory
    from services.robot.rotations import matrix_from_quat_xyzw, quat_xyzw_from_matrix

__all__ = [
    "PANDA_ACCEL_LIMITS",
    "PANDA_EE_FRAME",
    "PANDA_LOCKED_JOINTS",
    "PANDA_NAMED_POSES",
    "TEACH_METADATA",
    "ArmStateData",
    "Command",
    "CommandMode",
    "CommandRejectedError",
    "EEState",
    "JointLimits",
    "RobotModel",
    "StateLike",
    "cartesian_command",
    "command_from_message",
    "ee_trajectory",
    "frame_transforms",
    "joint_command",
    "matrix_from_quat_xyzw",
    "panda_urdf_path",
    "quat_xyzw_from_matrix",
    "state_from_message",
    "state_message",
]

#: Public name -> submodule that defines it.
_EXPORTS: dict[str, str] = {
    "PANDA_ACCEL_LIMITS": "model",
    "PANDA_EE_FRAME": "model",
    "PANDA_LOCKED_JOINTS": "model",
    "PANDA_NAMED_POSES": "model",
    "JointLimits": "model",
    "RobotModel": "model",
    "panda_urdf_path": "model",
    "ArmStateData": "protocol",
    "Command": "protocol",
    "CommandMode": "protocol",
    "CommandRejectedError": "protocol",
    "EEState": "protocol",
    "StateLike": "protocol",
    "cartesian_command": "protocol",
    "command_from_message": "protocol",
    "frame_transforms": "protocol",
    "joint_command": "protocol",
    "state_from_message": "protocol",
    "state_message": "protocol",
    "TEACH_METADATA": "recordings",
    "ee_trajectory": "recordings",
    "matrix_from_quat_xyzw": "rotations",
    "quat_xyzw_from_matrix": "rotations",
}


def __getattr__(name: str) -> Any:
    """Import the submodule defining ``name`` on first access (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
