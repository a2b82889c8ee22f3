"""Calibration of the camera model: the pinhole intrinsics (``psm camera calibrate``) and the
detector's nominal face width (``psm camera face-width``).

``calibrate_from_images`` finds the inner corners of a chessboard in each image
(``cv2.findChessboardCorners`` + sub-pixel refinement) and solves ``cv2.calibrateCamera``. The
result prints as a ``[goal_tracker.camera]`` TOML table. Distortion coefficients are estimated
and reported, but the tracker's model is undistorted pinhole: use a camera with low distortion
or undistort upstream.

``face_width_from_frames`` runs the configured tracker on frames of a face held still at a known
depth ``Z`` and returns ``[goal_tracker.face] width_m = Z · w / fx`` from the width ``w`` [px] of
the target's detector box (its 10 % trimmed mean over the frames: the boxes are whole pixels and
vary a few per cent with where the face falls on the ROI's pixel grid, which the tracker's filter
averages): the width the tracker's depth estimate ``fx · width_m / w``
needs to read ``Z``. Each detector (cascade, and the ROI search's size window and scale step)
frames a face differently, so the width belongs to the detector settings it was measured with.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.stats import trim_mean


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


#: A face-width calibration needs the face found in at least this many frames.
MIN_FACE_FRAMES = 10


@dataclass(frozen=True)
class FaceWidthResult:
    """The nominal face width for ``[goal_tracker.face] width_m`` [m] and what it came from: the
    target box width's 10 % trimmed mean, median and quartiles [px] over ``frames_used`` of
    ``frames_read`` frames, the face's depth ``distance_m`` [m] and the focal length ``fx`` [px]."""

    width_m: float
    box_px: float
    box_median_px: float
    box_q25_px: float
    box_q75_px: float
    frames_used: int
    frames_read: int
    distance_m: float
    fx: float

    def as_toml(self) -> str:
        """A ``[goal_tracker.face]`` table with the width (to 0.1 mm)."""
        spread = self.distance_m * (self.box_q75_px - self.box_q25_px) / self.fx
        return (
            f"# face at {self.distance_m:g} m: target box {self.box_px:.2f} px wide (10 % trimmed "
            f"mean of {self.frames_used} of {self.frames_read} frames; median {self.box_median_px:.1f}, "
            f"quartiles {self.box_q25_px:.1f}–{self.box_q75_px:.1f} px, {spread * 1e3:.1f} mm of "
            f"width), fx {self.fx:g} px\n"
            "[goal_tracker.face]\n"
            f"width_m = {self.width_m:.4f}\n"
        )


def face_width_from_frames(
    frames: Iterable[tuple[Any, int]], tracker: Any, fx: float, distance_m: float
) -> FaceWidthResult:
    """The nominal face width [m] from ``frames`` — ``(image, stamp_ns)`` pairs of a face held
    still at the depth ``distance_m`` [m] along the camera's optical axis — run through
    ``tracker`` (a :class:`~services.goal_tracker.tracker.GoalTracker` built from the config the
    width is for); ``fx`` [px] the camera's focal length. Uses the target's box of every frame
    that has a target (their 10 % trimmed mean); raises :class:`CalibrationError` when fewer than
    :data:`MIN_FACE_FRAMES` have one, or when ``distance_m`` or ``fx`` is not positive."""
    if not distance_m > 0.0:
        raise CalibrationError(f"the face's distance must be > 0 m, got {distance_m}")
    if not fx > 0.0:
        raise CalibrationError(f"fx must be > 0 px, got {fx}")
    widths: list[float] = []
    read = 0
    for image, stamp_ns in frames:
        read += 1
        out = tracker.process(image, stamp_ns)
        if out.target_index >= 0:
            widths.append(float(out.detections[out.target_index].w))
    if len(widths) < MIN_FACE_FRAMES:
        raise CalibrationError(
            f"a face was found in {len(widths)} of {read} frames (at least {MIN_FACE_FRAMES} "
            "needed): face the camera, still and unobstructed"
        )
    q25, median, q75 = (float(v) for v in np.percentile(widths, [25, 50, 75]))
    box = float(trim_mean(widths, 0.1))
    return FaceWidthResult(
        width_m=distance_m * box / fx, box_px=box, box_median_px=median, box_q25_px=q25, box_q75_px=q75,
        frames_used=len(widths), frames_read=read, distance_m=float(distance_m), fx=float(fx),
    )
