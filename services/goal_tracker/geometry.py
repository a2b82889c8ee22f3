"""Pinhole geometry: pixel face box ↔ 3-D point, and the camera → robot-base transform.

Conventions
-----------
- Camera frame is OpenCV's: x right, y down, z forward (along the optical axis), metres.
- Pixel coordinates (u, v): u to the right, v down, origin at the top-left pixel corner.
- A face box is ``(x, y, w, h)`` in pixels (top-left corner, width, height).
- Depth comes from the apparent face width: ``Z = fx · W / w`` with ``W`` the nominal face width
  (metres) and ``w`` the box width (pixels).
- ``T_base_camera`` maps camera-frame points to the robot base frame: ``p_base = R p_cam + t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ConfigDict, Field

from psm.errors import ParameterError
from services.bus.config import ConfigError, Section, Vec3

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an undistorted camera.

    Attributes:
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels.
        width, height: image size in pixels the intrinsics refer to.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 640
    height: int = 480

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ParameterError(f"intrinsics.{name} must be finite, got {value!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise ParameterError(f"intrinsics fx, fy must be > 0, got {self.fx}, {self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ParameterError(f"intrinsics width/height must be > 0, got {self.width}x{self.height}")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Square-pixel intrinsics with the principal point at the image centre.

        Args:
            width, height: image size in pixels.
            hfov_deg: horizontal field of view in degrees, in (0, 180).
        """
        if not 0.0 < hfov_deg < 180.0:
            raise ParameterError(f"hfov_deg must be in (0, 180), got {hfov_deg}")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(fx=f, fy=f, cx=width / 2.0, cy=height / 2.0, width=width, height=height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution (e.g. a source that delivers 1280×720)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    @property
    def matrix(self) -> FloatArray:
        """The 3×3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, p_cam: ArrayLike) -> FloatArray:
        """Project camera-frame points (…, 3) in metres to pixels (…, 2). Requires z > 0."""
        p = np.asarray(p_cam, dtype=float)
        z = p[..., 2]
        if np.any(z <= 0):
            raise ParameterError("cannot project a point with z <= 0 (behind the camera)")
        return np.stack([self.fx * p[..., 0] / z + self.cx, self.fy * p[..., 1] / z + self.cy], -1)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Rotation matrix R = Rz(yaw) · Ry(pitch) · Rx(roll) (fixed-axis XYZ), angles in radians."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def quaternion_xyzw(rotation: ArrayLike) -> FloatArray:
    """Unit quaternion (x, y, z, w) of a 3×3 rotation matrix (w ≥ 0)."""
    m = np.asarray(rotation, dtype=float)
    tr = float(np.trace(m))
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    out = np.asarray(q)
    out /= np.linalg.norm(out)
    return -out if out[3] < 0 else out


#: Camera looking along the base +x axis, image right = base −y, image down = base −z.
FORWARD_LOOKING = rpy_matrix(-math.pi / 2, 0.0, -math.pi / 2)


@dataclass(frozen=True)
class Transform:
    """Rigid transform ``p_out = rotation @ p_in + translation`` (metres)."""

    rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    translation: FloatArray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=float)
        t = np.asarray(self.translation, dtype=float).reshape(-1)
        if r.shape != (3, 3) or t.shape != (3,):
            raise ParameterError(f"transform needs a 3x3 rotation and a 3-vector, got {r.shape}, {t.shape}")
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
            raise ParameterError("transform contains NaN or inf")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise ParameterError("transform rotation is not a proper rotation matrix")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @classmethod
    def from_rpy(cls, translation: ArrayLike, rpy_deg: ArrayLike) -> Transform:
        """Build from a translation (m) and roll/pitch/yaw in degrees (see :func:`rpy_matrix`)."""
        r, p, y = (math.radians(float(a)) for a in np.asarray(rpy_deg, dtype=float).reshape(3))
        return cls(rpy_matrix(r, p, y), np.asarray(translation, dtype=float))

    def apply(self, p: ArrayLike) -> FloatArray:
        """Transform points (…, 3)."""
        return np.asarray(p, dtype=float) @ self.rotation.T + self.translation

    def apply_cov(self, cov: ArrayLike) -> FloatArray:
        """Rotate a 3×3 covariance into the output frame: R Σ Rᵀ."""
        return self.rotation @ np.asarray(cov, dtype=float) @ self.rotation.T

    def inverse(self) -> Transform:
        """The inverse transform."""
        rt = self.rotation.T
        return Transform(rt, -rt @ self.translation)


def box_to_camera_point(
    box: ArrayLike, intr: Intrinsics, face_width_m: float
) -> tuple[FloatArray, FloatArray]:
    """Camera-frame face centre of a pixel box, and the Jacobian d(X,Y,Z)/d(u,v,w).

    Args:
        box: ``(x, y, w, h)`` pixels, top-left corner and size.
        intr: camera intrinsics.
        face_width_m: nominal physical face width W in metres.

    Returns:
        ``(p, J)``: p shape (3,) metres; J shape (3, 3) with columns for the box centre u, v and
        the box width w, used to propagate pixel noise into a 3-D covariance.
    """
    x, y, w, h = (float(a) for a in np.asarray(box, dtype=float).reshape(4))
    if not (w > 0 and h > 0) or face_width_m <= 0:
        raise ParameterError(f"box width/height and face width must be > 0, got {w}, {h}, {face_width_m}")
    u, v = x + w / 2.0, y + h / 2.0
    z = intr.fx * face_width_m / w
    xu = (u - intr.cx) / intr.fx
    yv = (v - intr.cy) / intr.fy
    p = np.array([xu * z, yv * z, z])
    dz_dw = -z / w
    jac = np.array(
        [
            [z / intr.fx, 0.0, xu * dz_dw],
            [0.0, z / intr.fy, yv * dz_dw],
            [0.0, 0.0, dz_dw],
        ]
    )
    return p, jac


def camera_point_to_box(
    p_cam: ArrayLike, intr: Intrinsics, face_width_m: float, aspect: float = 1.0
) -> FloatArray:
    """Inverse of :func:`box_to_camera_point`: the pixel box ``(x, y, w, h)`` a face of width
    ``face_width_m`` centred at ``p_cam`` (metres, z > 0) appears as; ``aspect`` = h / w."""
    p = np.asarray(p_cam, dtype=float).reshape(3)
    uv = intr.project(p)
    w = intr.fx * face_width_m / p[2]
    h = intr.fy * face_width_m * aspect / p[2]
    return np.array([uv[0] - w / 2.0, uv[1] - h / 2.0, w, h])


class MeasurementNoise(Section):
    """Pixel noise of a detected face box (part of ``[goal_tracker.filter]``).

    The box width's 1-σ is ``σ_w = hypot(pixel_sigma[2], size_sigma_frac · w)`` px: a detector
    quantises box sizes on a geometric scale grid, so its size error is a fraction of the size,
    plus a floor. Propagated through the pinhole model, depth ``Z = fx W / w`` gets
    ``σ_Z = Z · σ_w / w`` (≈ ``Z · size_sigma_frac``, 9 mm at 0.5 m for 1.8 %), while the
    image-plane axes get ``Z · σ_u / fx`` (about 1.4 mm at 0.5 m): the filter trusts the image
    axes about 6× more than depth.
    """

    model_config = ConfigDict(frozen=True)

    pixel_sigma: Vec3 = Field(
        default_factory=lambda: [1.5, 1.5, 1.0],
        description="1-sigma noise of box centre u, v and the floor of the width w noise, px",
    )
    size_sigma_frac: float = Field(
        0.018, ge=0.0, lt=1.0,
        description="1-sigma noise of the box width as a fraction of the width (Haar: measured "
        "1.7-1.9 %)",
    )

    def check(self) -> None:
        """Noise levels are positive."""
        if any(not v > 0 for v in self.pixel_sigma):
            raise ConfigError("pixel_sigma", f"expected numbers > 0, got {self.pixel_sigma}")

    def box_sigma(self, width_px: float) -> FloatArray:
        """1-σ of (u, v, w), px, shape (3,), for a box ``width_px`` pixels wide."""
        su, sv, sw = self.pixel_sigma
        return np.array([su, sv, math.hypot(sw, self.size_sigma_frac * width_px)])


@dataclass(frozen=True)
class FaceGeometry:
    """Everything needed to turn a face box into a goal point in the robot base frame.

    Attributes:
        intrinsics: camera intrinsics at the resolution the boxes are measured in.
        face_width_m: nominal face width W (metres) used for depth.
        camera_to_base: ``T_base_camera``.
        offset_camera_m: goal offset from the face centre in the camera frame (metres), e.g. the
            mouth ≈ (0, +0.045, 0): 4.5 cm below the centre of the detected face box.
        noise: pixel noise model of the box, see :class:`MeasurementNoise`.
    """

    intrinsics: Intrinsics
    face_width_m: float = 0.16
    camera_to_base: Transform = field(default_factory=Transform)
    offset_camera_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.face_width_m) and self.face_width_m > 0):
            raise ParameterError(f"face_width_m must be > 0, got {self.face_width_m}")

    def measure(self, box: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Goal point (3,) in the base frame and its 3×3 measurement covariance (m²).

        The covariance is ``J · diag(σ_u², σ_v², σ_w²) · Jᵀ`` (J = ∂(X, Y, Z)/∂(u, v, w), see
        :func:`box_to_camera_point`; σ from :meth:`MeasurementNoise.box_sigma`) rotated into the
        base frame: depth's variance is (Z σ_w / w)², the image axes' (Z σ_u / fx)²."""
        p_cam, jac = box_to_camera_point(box, self.intrinsics, self.face_width_m)
        goal_cam = p_cam + np.asarray(self.offset_camera_m, dtype=float)
        sigma = self.noise.box_sigma(float(np.asarray(box, dtype=float).reshape(4)[2]))
        cov_cam = jac @ np.diag(np.square(sigma)) @ jac.T
        return self.camera_to_base.apply(goal_cam), self.camera_to_base.apply_cov(cov_cam)

    def goal_to_box(self, goal_base: ArrayLike) -> FloatArray:
        """Pixel box of the face whose goal point is ``goal_base`` (inverse of :meth:`measure`)."""
        p_cam = self.camera_to_base.inverse().apply(goal_base) - np.asarray(self.offset_camera_m)
        return camera_point_to_box(p_cam, self.intrinsics, self.face_width_m)
