"""Recordings of the arm read back as end-effector trajectories (what ``psm learn DEMO.mcap`` and
the planner learn from).

:func:`ee_trajectory` computes the trajectory by forward kinematics from the recorded joint
states, with the robot model the recording names (``psm.teach`` metadata) or a given one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.robot.model import RobotModel

__all__ = ["TEACH_METADATA", "ee_poses", "ee_trajectory"]

#: MCAP metadata record of a guided demonstration (``psm teach``): the task, its via-points,
#: the tremor seed and the end-effector frame.
TEACH_METADATA = "psm.teach"


def ee_trajectory(
    path: str | Path,
    robot: RobotModel | None = None,
    *,
    topic: str | None = None,
    orientation: bool = False,
) -> tuple[np.ndarray, ...]:
    """End-effector trajectory of a recording by forward kinematics from its joint states.

    Args:
        path: MCAP file (from ``psm teach`` or ``psm record``).
        robot: robot model; default the Panda with the EE frame stored in the recording's
            ``psm.teach`` metadata (else ``panda_hand_tcp``).
        topic: the ArmState key (default: every key ending in ``/arm/state``).
        orientation: also return the orientations (see :func:`ee_poses`).

    Returns:
        ``t (T,)`` seconds from the first state (sim time), ``X (T, 3)`` metres, base frame
        (and ``quats (T, 4)`` xyzw with ``orientation``).
        Duplicate ticks (a lockstep arm re-offering state 0) are dropped; samples are sorted
        by tick.

    Raises:
        ValueError: no ArmState in the file, or joints that do not match the robot.
    """
    from services.bus.log import read_log, read_metadata
    from services.bus.messages import ArmState

    if robot is None:
        meta = read_metadata(path).get(TEACH_METADATA, {})
        robot = RobotModel.load(ee_frame=meta.get("ee_frame") or None)
    ticks: dict[int, tuple[int, list[float]]] = {}
    names: list[str] | None = None
    for key, msg, _ in read_log(path, topic):
        if not isinstance(msg, ArmState) or (topic is None and not key.endswith("/arm/state")):
            continue
        if names is None:
            names = list(msg.joint_names)
        if msg.tick not in ticks:
            ticks[msg.tick] = (msg.sim_time_ns, list(msg.q))
    if not ticks:
        raise ValueError(f"{path}: no ArmState messages")
    if names and tuple(names) != robot.joint_names:
        raise ValueError(
            f"{path}: recorded joints {names} do not match the robot's {list(robot.joint_names)}"
        )
    order = sorted(ticks)
    t_ns = np.array([ticks[k][0] for k in order], dtype=np.int64)
    Q = np.array([ticks[k][1] for k in order], dtype=float)
    if Q.shape[1] != robot.n:
        raise ValueError(f"{path}: states have {Q.shape[1]} joints, robot has {robot.n}")
    t = (t_ns - t_ns[0]) * 1e-9
    if orientation:
        from services.robot.rotations import quat_xyzw_from_matrix

        poses = [robot.fk(q) for q in Q]
        X = np.array([p for p, _ in poses])
        quats = quat_xyzw_from_matrix(np.stack([R for _, R in poses]))
        return t, X, quats
    return t, robot.fk_positions(Q)


def ee_poses(
    path: str | Path, robot: RobotModel | None = None, *, topic: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Like :func:`ee_trajectory`, with the orientation: ``t (T,)`` [s], ``X (T, 3)`` [m],
    ``quats (T, 4)`` xyzw (``w >= 0``) of the end effector in the base frame."""
    return ee_trajectory(path, robot, topic=topic, orientation=True)  # type: ignore[return-value]
