"""Synthetic camera: determinism and consistency with the pinhole model."""

from __future__ import annotations

import numpy as np

from services.goal_tracker.detectors import HaarDetector, HaarParams
from services.goal_tracker.geometry import Intrinsics, camera_point_to_box
from services.goal_tracker.synthetic import (
    LissajousPath,
    SyntheticCamera,
    SyntheticFace,
    make_background,
)


def test_frames_are_a_pure_function_of_time() -> None:
    a, b = SyntheticCamera(seed=3), SyntheticCamera(seed=3)
    np.testing.assert_array_equal(a.render(1.25), b.render(1.25))
    assert not np.array_equal(a.render(1.25), a.render(1.30))
    assert a.render(0.0).shape == (480, 640, 3)


def test_truth_follows_pinhole_model() -> None:
    intr = Intrinsics.from_fov(640, 480, 60.0)
    face = SyntheticFace(LissajousPath(centre=(0.1, -0.05, 1.2)), width_m=0.15)
    cam = SyntheticCamera(intr, [face])
    t = 2.0
    truth = cam.truth(t)[0]
    np.testing.assert_allclose(truth.position_cam, face.path.position(t))
    np.testing.assert_allclose(truth.box, camera_point_to_box(truth.position_cam, intr, 0.15))
    assert truth.box[2] == np.float64(intr.fx * 0.15 / truth.position_cam[2])


def test_rendered_face_is_where_the_truth_says() -> None:
    """The default Haar cascade, run plainly on full frames, finds the face at the true box."""
    cam = SyntheticCamera(noise_sigma=0.0)
    det = HaarDetector(params=HaarParams(scale_factor=1.05))
    for t in (0.0, 3.0, 7.0, 11.0):
        truth = cam.truth(t)[0].box
        found = det.detect(cam.render(t), 24)
        assert len(found) == 1
        d = found[0]
        tu, tv = truth[0] + truth[2] / 2, truth[1] + truth[3] / 2
        assert abs(d.centre[0] - tu) < 3.0 and abs(d.centre[1] - tv) < 3.0
        assert abs(d.w / truth[2] - 1.0) < 0.08


def test_hidden_window_removes_the_face() -> None:
    face = SyntheticFace(hidden=((1.0, 2.0),))
    cam = SyntheticCamera(faces=[face], noise_sigma=0.0)
    assert not cam.truth(1.5)[0].visible and cam.truth(2.0)[0].visible
    np.testing.assert_array_equal(cam.render(1.5), cam.background)
    assert HaarDetector().detect(cam.render(1.5), 24) == []


def test_path_velocity_is_derivative() -> None:
    path = LissajousPath()
    h = 1e-6
    np.testing.assert_allclose(
        path.velocity(0.7), (path.position(0.7 + h) - path.position(0.7 - h)) / (2 * h), atol=1e-6
    )


def test_background_is_deterministic() -> None:
    np.testing.assert_array_equal(make_background(64, 48, 1), make_background(64, 48, 1))
