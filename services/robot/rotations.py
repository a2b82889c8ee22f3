"""Quaternion ↔ rotation-matrix conversions (matrix → quaternion on
:class:`scipy.spatial.transform.Rotation`, quaternion → matrix in closed form).

Quaternions are ``(x, y, z, w)`` (scalar last, scipy's order) and returned with ``w >= 0``.
Kept free of Pinocchio so the protocol helpers (:mod:`services.robot.protocol`) import quickly.
"""

from __future__ import annotations

import math
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

    Plain float arithmetic (no numpy on the four components: this runs every control tick in
    the arm): the quaternion is normalised twice and expanded with the same operations, in the
    same order, as ``Rotation.from_quat(q / |q|).as_matrix()``, so the result is scipy's to the
    last bits (identical where scipy's compiled path does not fuse multiply-adds).

    Raises:
        ValueError: the quaternion has zero or non-finite norm.
    """
    x, y, z, w = (float(c) for c in quat)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n == 0.0:
        raise ValueError("quaternion has zero or non-finite norm")
    x, y, z, w = x / n, y / n, z / n, w / n
    n = math.sqrt(x * x + y * y + z * z + w * w)  # scipy's own normalisation
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array(
        [
            [x2 - y2 - z2 + w2, 2.0 * (xy - zw), 2.0 * (xz + yw)],
            [2.0 * (xy + zw), -x2 + y2 - z2 + w2, 2.0 * (yz - xw)],
            [2.0 * (xz - yw), 2.0 * (yz + xw), -x2 - y2 + z2 + w2],
        ]
    )


__all__ = ["matrix_from_quat_xyzw", "quat_xyzw_from_matrix"]
