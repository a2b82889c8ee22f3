"""Chessboard calibration recovers known intrinsics from rendered board views."""

from __future__ import annotations

from pathlib import Path

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


# ------------------------------------------------------------------ the nominal face width


def _still_face_frames(overrides: dict, n: int, depth_m: float = 0.5):
    """The configured tracker and ``n`` frames (with stamps) of the synthetic face held still
    ``depth_m`` in front of the camera, frames as a topic's images reach the tracker (JPEG at the
    camera's quality, decoded to grey for Haar)."""
    from services.bus.config import load_config
    from services.goal_tracker.config import TrackerConfig, build_synthetic_camera, build_tracker
    from services.goal_tracker.sources import decode_image

    over = {"goal_tracker.synthetic.amplitude_m": [0.0, 0.0, 0.0],
            "goal_tracker.synthetic.centre_m": [0.0, 0.0, depth_m], **overrides}
    sec = load_config(TrackerConfig, env={}, overrides=over).goal_tracker
    cam = build_synthetic_camera(sec)

    def frames():
        for k in range(n):
            quality = [cv2.IMWRITE_JPEG_QUALITY, sec.camera.jpeg_quality]
            ok, buf = cv2.imencode(".jpg", cam.render(k / 30.0), quality)
            assert ok
            yield decode_image(buf.tobytes(), True), round(k / 30.0 * 1e9)

    return sec, build_tracker(sec), frames()


def test_face_width_of_the_default_detector_is_the_configured_default() -> None:
    """The shipped ``face.width_m`` is what the calibration measures for the shipped detector on
    the synthetic face (whose reference box is 0.16 m wide): the default is calibrated, not
    copied."""
    from services.goal_tracker.calibration import face_width_from_frames
    from services.goal_tracker.config import FaceSection

    sec, tracker, frames = _still_face_frames({}, 150)
    res = face_width_from_frames(frames, tracker, sec.camera.fx, 0.5)
    assert res.frames_used >= 145
    assert res.width_m == pytest.approx(FaceSection().width_m, rel=0.01)
    # The tracker then reads the face's depth: fx · width / box = 0.5 m.
    assert sec.camera.fx * res.width_m / res.box_px == pytest.approx(0.5, rel=1e-12)
    assert "[goal_tracker.face]\nwidth_m = " in res.as_toml()


def test_face_width_belongs_to_the_detector_settings() -> None:
    """OpenCV's default cascade with the ROI settings it was tuned with frames the same face
    ~4 % narrower than the shipped detector: a width is calibrated per detector."""
    from services.goal_tracker.calibration import face_width_from_frames

    model = str(Path(cv2.data.haarcascades) / "haarcascade_frontalface_default.xml")
    old = {"goal_tracker.detector.model_path": model, "goal_tracker.detector.fine_scale_factor": 1.1,
           "goal_tracker.detector.roi_size_range": [0.6, 1.6]}
    sec, tracker, frames = _still_face_frames(old, 150)
    old_w = face_width_from_frames(frames, tracker, sec.camera.fx, 0.5).width_m
    sec, tracker, frames = _still_face_frames({}, 150)
    new_w = face_width_from_frames(frames, tracker, sec.camera.fx, 0.5).width_m
    assert 0.158 < old_w < 0.165
    assert new_w / old_w > 1.03


def test_face_width_needs_a_face_and_a_distance() -> None:
    from services.goal_tracker.calibration import face_width_from_frames

    sec, tracker, frames = _still_face_frames({"goal_tracker.synthetic.hidden_s": [[0.0, 100.0]]}, 20)
    with pytest.raises(CalibrationError, match="a face was found in 0 of 20 frames"):
        face_width_from_frames(frames, tracker, sec.camera.fx, 0.5)
    with pytest.raises(CalibrationError, match="distance must be > 0"):
        face_width_from_frames(iter(()), tracker, sec.camera.fx, 0.0)


def test_psm_camera_face_width_prints_the_width_and_fails_in_one_line() -> None:
    import tomllib

    from services.goal_tracker.config import FaceSection
    from tests.bus.helpers import one_error_line, run_psm

    still = ("--set", "goal_tracker.synthetic.amplitude_m=[0,0,0]",
             "--set", "goal_tracker.synthetic.centre_m=[0,0,0.5]")
    ok = run_psm("camera", "face-width", "--distance", "0.5", "--source", "synthetic",
                 "--frames", "40", *still, timeout_s=120)
    assert ok.returncode == 0, ok.stderr
    width = tomllib.loads(ok.stdout)["goal_tracker"]["face"]["width_m"]
    assert width == pytest.approx(FaceSection().width_m, rel=0.015)
    hidden = run_psm("camera", "face-width", "--distance", "0.5", "--source", "synthetic",
                     "--frames", "12", "--set", "goal_tracker.synthetic.hidden_s=[[0,100]]",
                     timeout_s=120)
    assert "a face was found in 0 of 12 frames" in one_error_line(hidden, "psm camera face-width")
