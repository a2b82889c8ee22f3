"""Chessboard calibration of the pinhole intrinsics (``psm camera calibrate``).

``calibrate_from_images`` finds the inner corners of a chessboard in each image
(``cv2.findChessboardCorners`` + sub-pixel refinement) and solves ``cv2.calibrateCamera``. The
result prints as a ``[goal_tracker.camera]`` TOML table. Distortion coefficients are estimated
and reported, but the tracker's model is undistorted pinhole: use a camera with low distortion
or undistort upstream.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray


class CalibrationError(ValueError):
    """Calibration impossible: unreadable images, too few boards found, sizes differ."""


@dataclass(frozen=True)
class CalibrationResult:
    """Intrinsics (px), distortion (OpenCV order k1 k2 p1 p2 k3), RMS reprojection error (px)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...]
    rms_px: float
    images_used: int

    def as_toml(self) -> str:
        """A ``[goal_tracker.camera]`` table with these intrinsics."""
        return (
            f"# chessboard calibration: {self.images_used} images, RMS reprojection "
            f"{self.rms_px:.3f} px, distortion {[round(d, 4) for d in self.distortion]}\n"
            "[goal_tracker.camera]\n"
            f"width = {self.width}\nheight = {self.height}\n"
            f"fx = {self.fx:.3f}\nfy = {self.fy:.3f}\ncx = {self.cx:.3f}\ncy = {self.cy:.3f}\n"
        )


def board_points(pattern: tuple[int, int], square_m: float) -> NDArray[np.float32]:
    """3-D inner-corner coordinates (N, 3) of a ``pattern = (cols, rows)`` board, z = 0, m."""
    cols, rows = pattern
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


def calibrate(
    images: Sequence[NDArray[np.uint8]], pattern: tuple[int, int], square_m: float
) -> CalibrationResult:
    """Calibrate from images (H×W or H×W×3 uint8, all the same size); needs ≥ 3 boards found."""
    if square_m <= 0 or min(pattern) < 2:
        raise CalibrationError("pattern needs >= 2x2 inner corners and square_m > 0")
    obj, img_pts = [], []
    size: tuple[int, int] | None = None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    for image in images:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif size != (gray.shape[1], gray.shape[0]):
            raise CalibrationError(f"image sizes differ: {size} vs {gray.shape[1::-1]}")
        found, corners = cv2.findChessboardCorners(gray, pattern)
        if not found:
            continue
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
        obj.append(board_points(pattern, square_m))
        img_pts.append(corners)
    if len(obj) < 3 or size is None:
        raise CalibrationError(
            f"chessboard {pattern[0]}x{pattern[1]} found in {len(obj)} of {len(images)} images "
            "(need at least 3)"
        )
    rms, k, dist, _, _ = cv2.calibrateCamera(obj, img_pts, size, None, None)
    return CalibrationResult(
        float(k[0, 0]),
        float(k[1, 1]),
        float(k[0, 2]),
        float(k[1, 2]),
        size[0],
        size[1],
        tuple(float(d) for d in np.ravel(dist)),
        float(rms),
        len(obj),
    )


def calibrate_from_images(
    paths: Sequence[str | Path], pattern: tuple[int, int], square_m: float
) -> CalibrationResult:
    """:func:`calibrate` on image files; an unreadable file is a :class:`CalibrationError`."""
    images = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"cannot read image {p}")
        images.append(img)
    return calibrate(images, pattern, square_m)
