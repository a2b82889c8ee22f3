"""Chessboard calibration recovers known intrinsics from rendered board views."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.goal_tracker.calibration import CalibrationError, board_points, calibrate


def render_board(
    k: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    pattern: tuple[int, int],
    square: float,
    size: tuple[int, int],
) -> np.ndarray:
    """A chessboard with ``pattern`` inner corners seen by camera ``k`` (no distortion)."""
    cols, rows = pattern
    px = 40  # board texture resolution: px per square
    tex = np.full(((rows + 3) * px, (cols + 3) * px), 255, np.uint8)
    for r in range(rows + 1):
        for c in range(cols + 1):
            if (r + c) % 2 == 0:
                tex[(r + 1) * px : (r + 2) * px, (c + 1) * px : (c + 2) * px] = 0
    # texture pixel (u, v) -> board point ((u/px - 2) * square, (v/px - 2) * square, 0)
    corners_tex = np.array(
        [[0, 0], [tex.shape[1], 0], [tex.shape[1], tex.shape[0]], [0, tex.shape[0]]], np.float32
    )
    board = np.c_[(corners_tex / px - 2) * square, np.zeros(4)].astype(np.float32)
    img_pts, _ = cv2.projectPoints(board, rvec, tvec, k, None)
    h = cv2.getPerspectiveTransform(corners_tex, img_pts.reshape(4, 2).astype(np.float32))
    return cv2.warpPerspective(tex, h, size, borderValue=128)


def test_recovers_intrinsics() -> None:
    k = np.array([[600.0, 0, 330.0], [0, 605.0, 235.0], [0, 0, 1]])
    pattern, square = (7, 5), 0.03
    rng = np.random.default_rng(1)
    images = []
    for _ in range(8):
        rvec = rng.uniform(-0.35, 0.35, 3)
        tvec = np.array([rng.uniform(-0.12, 0.0), rng.uniform(-0.08, 0.0), rng.uniform(0.45, 0.6)])
        images.append(render_board(k, rvec, tvec, pattern, square, (640, 480)))
    res = calibrate(images, pattern, square)
    assert res.images_used >= 6
    assert res.fx == pytest.approx(600, rel=0.01) and res.fy == pytest.approx(605, rel=0.01)
    assert res.cx == pytest.approx(330, abs=5) and res.cy == pytest.approx(235, abs=5)
    assert res.rms_px < 0.5
    assert "[goal_tracker.camera]" in res.as_toml()
    assert board_points(pattern, square).shape == (35, 3)


def test_too_few_boards() -> None:
    blank = [np.full((480, 640), 128, np.uint8)] * 3
    with pytest.raises(CalibrationError, match="found in 0 of 3 images"):
        calibrate(blank, (7, 5), 0.03)
