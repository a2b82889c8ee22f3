"""Pinhole geometry: round trips, Jacobian, transforms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from psm.errors import ParameterError
from services.goal_tracker.geometry import (
    FORWARD_LOOKING,
    FaceGeometry,
    Intrinsics,
    MeasurementNoise,
    Transform,
    box_to_camera_point,
    camera_point_to_box,
    quaternion_xyzw,
    rpy_matrix,
)

INTR = Intrinsics(fx=550.0, fy=560.0, cx=318.0, cy=242.0)

points = st.tuples(st.floats(-0.5, 0.5), st.floats(-0.4, 0.4), st.floats(0.3, 3.0)).map(np.array)


@settings(max_examples=200, deadline=None)
@given(p=points, width=st.floats(0.08, 0.3))
def test_point_box_round_trip(p: np.ndarray, width: float) -> None:
    box = camera_point_to_box(p, INTR, width)
    back, _ = box_to_camera_point(box, INTR, width)
    np.testing.assert_allclose(back, p, atol=1e-9)


def test_box_width_is_fx_w_over_z() -> None:
    box = camera_point_to_box([0.0, 0.0, 2.0], INTR, 0.16)
    assert box[2] == pytest.approx(550.0 * 0.16 / 2.0)
    # centred on the principal point
    assert box[0] + box[2] / 2 == pytest.approx(INTR.cx)
    assert box[1] + box[3] / 2 == pytest.approx(INTR.cy)


def test_jacobian_matches_finite_differences() -> None:
    box = np.array([300.0, 200.0, 80.0, 80.0])
    p0, jac = box_to_camera_point(box, INTR, 0.16)
    eps = 1e-4
    num = np.zeros((3, 3))
    # columns: u (centre x), v (centre y), w (width, centre fixed)
    for j, delta in enumerate(
        (np.array([eps, 0, 0, 0]), np.array([0, eps, 0, 0]), np.array([-eps / 2, 0, eps, 0]))
    ):
        p1, _ = box_to_camera_point(box + delta, INTR, 0.16)
        num[:, j] = (p1 - p0) / eps
    np.testing.assert_allclose(jac, num, rtol=1e-4, atol=1e-7)


def test_forward_looking_mount_axes() -> None:
    # camera z (forward) -> base +x, camera x (right) -> base -y, camera y (down) -> base -z
    np.testing.assert_allclose(FORWARD_LOOKING @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(FORWARD_LOOKING @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(FORWARD_LOOKING @ [0, 1, 0], [0, 0, -1], atol=1e-12)
    t = Transform.from_rpy([-0.2, 0.0, 0.5], [-90, 0, -90])
    np.testing.assert_allclose(t.rotation, FORWARD_LOOKING, atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(
    rpy=st.tuples(*(st.floats(-math.pi, math.pi),) * 3),
    t=st.tuples(*(st.floats(-2, 2),) * 3),
    p=st.tuples(*(st.floats(-2, 2),) * 3),
)
def test_transform_inverse_round_trip(rpy: tuple, t: tuple, p: tuple) -> None:
    tf = Transform(rpy_matrix(*rpy), np.array(t))
    np.testing.assert_allclose(tf.inverse().apply(tf.apply(p)), p, atol=1e-9)


def test_quaternion_of_rotation() -> None:
    q = quaternion_xyzw(rpy_matrix(0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(q, [0, 0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)


def test_face_geometry_measure_and_inverse() -> None:
    geo = FaceGeometry(INTR, 0.16, Transform.from_rpy([-0.2, 0, 0.5], [-90, 0, -90]), (0.0, 0.045, 0.0))
    goal = np.array([0.7, 0.1, 0.45])
    box = geo.goal_to_box(goal)
    measured, cov = geo.measure(box)
    np.testing.assert_allclose(measured, goal, atol=1e-9)
    # covariance is symmetric PSD and depth (base x) is the least certain direction
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)
    eig = np.linalg.eigvalsh(cov)
    assert eig.min() > 0
    assert np.argmax(np.diag(cov)) == 0


def test_intrinsics_scaled_and_from_fov() -> None:
    intr = Intrinsics.from_fov(640, 480, 60.0)
    assert intr.fx == pytest.approx(320 / math.tan(math.radians(30)))
    big = intr.scaled(1280, 960)
    assert big.fx == pytest.approx(2 * intr.fx) and big.cx == pytest.approx(640)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Intrinsics(-1.0, 1.0, 0.0, 0.0),
        lambda: Intrinsics(float("nan"), 1.0, 0.0, 0.0),
        lambda: Transform(np.eye(3) * 2, np.zeros(3)),
        lambda: Transform(np.eye(3), np.array([0, 0, np.inf])),
        lambda: box_to_camera_point([0, 0, 0, 10], INTR, 0.16),
        lambda: INTR.project([0, 0, -1.0]),
        lambda: FaceGeometry(INTR, face_width_m=0.0),
    ],
)
def test_bad_geometry_raises(make) -> None:
    with pytest.raises(ParameterError):
        make()


def test_measurement_covariance_from_the_geometry() -> None:
    # Camera looking along base +y (the stack's mount): camera x -> base x, camera z (depth) ->
    # base y, camera y -> base -z. The covariance is diagonal in the base frame with
    # sigma_depth = Z sigma_w / w and sigma_image = Z sigma_u / fx (face on the optical axis).
    noise = MeasurementNoise(pixel_sigma=[1.5, 1.2, 1.0], size_sigma_frac=0.02)
    geo = FaceGeometry(INTR, 0.16, Transform.from_rpy([0.35, 0, 0.45], [-90, 0, 0]), (0, 0, 0), noise)
    z = 0.5
    w = INTR.fx * 0.16 / z
    box = [INTR.cx - w / 2, INTR.cy - w / 2, w, w]
    p, cov = geo.measure(box)
    np.testing.assert_allclose(p, [0.35, 0.5, 0.45], atol=1e-12)
    sigma_w = math.hypot(1.0, 0.02 * w)
    np.testing.assert_allclose(
        np.diag(cov), [(z * 1.5 / INTR.fx) ** 2, (z * sigma_w / w) ** 2, (z * 1.2 / INTR.fy) ** 2], rtol=1e-12
    )
    np.testing.assert_allclose(cov - np.diag(np.diag(cov)), 0.0, atol=1e-18)
    # for a large face the relative size noise dominates: depth 1-sigma -> Z * size_sigma_frac
    assert math.sqrt(cov[1, 1]) == pytest.approx(z * 0.02, rel=0.05)
    np.testing.assert_allclose(noise.box_sigma(100.0), [1.5, 1.2, math.hypot(1.0, 2.0)])


def test_measurement_noise_rejects_non_positive_sigma() -> None:
    with pytest.raises(ValidationError, match="pixel_sigma"):
        MeasurementNoise(pixel_sigma=[1.0, 0.0, 1.0])
