"""Quaternion ↔ rotation-matrix conversions on :class:`scipy.spatial.transform.Rotation`.

Quaternions are ``(x, y, z, w)`` (scalar last, scipy's order) and returned with ``w >= 0``.
Kept free of Pinocchio so the protocol helpers (:mod:`services.robot.protocol`) import quickly.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation


def quat_xyzw_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(x, y, z, w)`` with ``w >= 0`` of rotation matrices.

    Args:
        R: one rotation matrix ``(3, 3)`` or a stack ``(N, 3, 3)``.

    Returns:
        ``(4,)`` for one matrix, ``(N, 4)`` for a stack.
    """
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return np.where(q[..., 3:4] < 0, -q, q)


def matrix_from_quat_xyzw(quat: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a quaternion ``(x, y, z, w)`` ``(4,)`` (normalised first).

    Raises:
        ValueError: the quaternion has zero or non-finite norm.
    """
    q = np.asarray(quat, dtype=float)
    n = float(np.sqrt(q @ q))
    if not np.isfinite(n) or n == 0.0:
        raise ValueError("quaternion has zero or non-finite norm")
    return Rotation.from_quat(q / n).as_matrix()


__all__ = ["matrix_from_quat_xyzw", "quat_xyzw_from_matrix"]
