"""Synthetic camera: the real astronaut face (scikit-image's bundled ``astronaut``) moved along a
known 3-D path in front of a textured background, rendered with the pinhole model.

Ground truth: a face at camera-frame position ``P = (X, Y, Z)`` (metres, the centre of the face box)
with physical width ``W`` appears centred at pixel ``(fx X/Z + cx, fy Y/Z + cy)`` with a face-box
width of ``fx W / Z`` pixels — exactly the model the tracker inverts, so tests can compare the
tracker's goal with the path. The *face box* of the sprite is the box OpenCV's
``haarcascade_frontalface_default.xml`` finds on the unscaled crop; its centre is the face centre.
(Other detectors' boxes differ by a few per cent: ``[goal_tracker.face] width_m`` is calibrated
per detector.)

Frames are a pure function of the frame time ``t`` (seconds) and the seed, so any clock (the arm's
sim time in lockstep, or the wall clock) gives reproducible images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from psm.errors import ParameterError
from services.goal_tracker.geometry import Intrinsics, camera_point_to_box

Image = NDArray[np.uint8]

#: Crop of ``skimage.data.astronaut()`` used as the face sprite: rows, cols (pixels).
SPRITE_ROWS = (20, 230)
SPRITE_COLS = (140, 310)
#: Face box ``(x, y, w, h)`` inside the sprite (``haarcascade_frontalface_default.xml`` on the unscaled crop).
SPRITE_FACE_BOX = (38.0, 46.0, 95.0, 95.0)


@lru_cache(maxsize=1)
def _sprite() -> tuple[Image, NDArray[np.float32]]:
    """The BGR face sprite (210×170×3 uint8) and its feathered elliptical alpha mask (float32)."""
    from skimage import data  # bundled image: no download

    rgb = data.astronaut()[SPRITE_ROWS[0] : SPRITE_ROWS[1], SPRITE_COLS[0] : SPRITE_COLS[1]]
    bgr = np.ascontiguousarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    h, w = bgr.shape[:2]
    mask = np.zeros((h, w), np.float32)
    cv2.ellipse(mask, (w // 2, h // 2), (w // 2 - 6, h // 2 - 6), 0, 0, 360, 1.0, -1)
    mask = cv2.GaussianBlur(mask, (0, 0), 4.0)
    return bgr, mask


def sprite_levels() -> list[tuple[float, Image, NDArray[np.float32]]]:
    """Sprite pyramid ``[(scale, image, mask), …]`` at scales 1, 1/2, 1/4, 1/8 (anti-aliased)."""
    return _levels()


@lru_cache(maxsize=1)
def _levels() -> list[tuple[float, Image, NDArray[np.float32]]]:
    img, mask = _sprite()
    out = [(1.0, img, mask)]
    for _ in range(3):
        img, mask = cv2.pyrDown(img), cv2.pyrDown(mask)
        out.append((out[-1][0] / 2.0, img, mask))
    return out


@dataclass(frozen=True)
class LissajousPath:
    """Face-centre path in the camera frame: ``p(t) = centre + amplitude · sin(2π f t + phase)``.

    Attributes (all per axis x, y, z of the camera frame):
        centre: metres; z is the mean distance from the camera.
        amplitude: metres.
        frequency_hz: Hz.
        phase_rad: radians.
    """

    centre: tuple[float, float, float] = (0.0, 0.0, 1.0)
    amplitude: tuple[float, float, float] = (0.20, 0.08, 0.20)
    frequency_hz: tuple[float, float, float] = (0.10, 0.13, 0.07)
    phase_rad: tuple[float, float, float] = (0.0, 0.5, 1.0)

    def position(self, t: float) -> NDArray[np.float64]:
        """Camera-frame face centre (3,) in metres at time ``t`` seconds."""
        c, a = np.asarray(self.centre, float), np.asarray(self.amplitude, float)
        f, ph = np.asarray(self.frequency_hz, float), np.asarray(self.phase_rad, float)
        return c + a * np.sin(2 * math.pi * f * t + ph)

    def velocity(self, t: float) -> NDArray[np.float64]:
        """Camera-frame velocity (3,) in m/s at time ``t``."""
        a, f = np.asarray(self.amplitude, float), np.asarray(self.frequency_hz, float)
        ph = np.asarray(self.phase_rad, float)
        return a * 2 * math.pi * f * np.cos(2 * math.pi * f * t + ph)


@dataclass(frozen=True)
class SyntheticFace:
    """One face: its path, physical width (m), and the time windows ``[(t0, t1), …]`` (s) in
    which it is hidden (to test drop-outs and lost/found)."""

    path: LissajousPath = field(default_factory=LissajousPath)
    width_m: float = 0.16
    hidden: tuple[tuple[float, float], ...] = ()

    def visible(self, t: float) -> bool:
        """True unless ``t`` lies in one of the hidden windows."""
        return not any(t0 <= t < t1 for t0, t1 in self.hidden)


@dataclass(frozen=True)
class FaceTruth:
    """Ground truth of one face in one frame."""

    position_cam: NDArray[np.float64]  #: (3,) metres
    box: NDArray[np.float64]  #: (x, y, w, h) pixels
    visible: bool


class SyntheticCamera:
    """Renders frames of :class:`SyntheticFace` objects (see the module docstring).

    Args:
        intrinsics: camera model; the frame size is ``intrinsics.width × height``.
        faces: faces to draw, back to front is by depth (farther first).
        noise_sigma: per-pixel Gaussian sensor noise (grey levels), seeded per frame.
        seed: background and noise seed.
    """

    def __init__(
        self,
        intrinsics: Intrinsics | None = None,
        faces: tuple[SyntheticFace, ...] | list[SyntheticFace] = (SyntheticFace(),),
        noise_sigma: float = 2.0,
        seed: int = 0,
    ) -> None:
        self.intrinsics = intrinsics or Intrinsics.from_fov(640, 480, 60.0)
        self.faces = tuple(faces)
        if noise_sigma < 0:
            raise ParameterError(f"synthetic noise_sigma must be >= 0, got {noise_sigma}")
        self.noise_sigma = float(noise_sigma)
        self.seed = int(seed)
        self.background = make_background(self.intrinsics.width, self.intrinsics.height, seed)
        self._noise_pool: tuple[Image, Image] | None = None

    def truth(self, t: float) -> list[FaceTruth]:
        """Ground truth of every face at time ``t`` (seconds)."""
        out = []
        for face in self.faces:
            p = face.path.position(t)
            box = camera_point_to_box(p, self.intrinsics, face.width_m)
            out.append(FaceTruth(p, box, face.visible(t) and p[2] > 0.05))
        return out

    def render(self, t: float) -> Image:
        """The H×W×3 BGR uint8 frame at time ``t`` (seconds).

        The background is copied, each visible face blended into its own rectangle only, and
        the noise added with saturation from a precomputed pool at a seeded per-frame offset
        (see :meth:`_noise`), so a frame costs a few full-frame uint8 passes."""
        frame = self.background.copy()
        truths = self.truth(t)
        order = sorted(range(len(truths)), key=lambda i: -truths[i].position_cam[2])
        for i in order:
            tr = truths[i]
            if tr.visible:
                _paste_face(frame, tr.box)
        if self.noise_sigma > 0:
            up, down = self._noise(t)
            cv2.add(frame, up, dst=frame)
            cv2.subtract(frame, down, dst=frame)
        return frame

    def _noise(self, t: float) -> tuple[Image, Image]:
        """Sensor noise of the frame at ``t``: ``(up, down)`` uint8 images, the positive and
        negative parts of rounded N(0, noise_sigma²) grey levels (never both non-zero at a
        pixel, so ``frame + up − down`` with saturation is ``clip(frame + noise)``).

        Drawn from a pool of ``H·W·3 + _NOISE_SLACK`` values made once from the seed; frame
        ``t`` starts at an offset seeded by ``(seed, round(t·1e6))``."""
        h, w = self.intrinsics.height, self.intrinsics.width
        n = h * w * 3
        if self._noise_pool is None:
            rng = np.random.default_rng([self.seed, 0x5EED])
            vals = np.rint(rng.standard_normal(n + _NOISE_SLACK) * self.noise_sigma)
            vals = np.clip(vals, -255, 255)
            self._noise_pool = (
                np.maximum(vals, 0).astype(np.uint8),
                np.maximum(-vals, 0).astype(np.uint8),
            )
        off = int(np.random.default_rng([self.seed, round(t * 1e6)]).integers(0, _NOISE_SLACK))
        up, down = self._noise_pool
        return up[off : off + n].reshape(h, w, 3), down[off : off + n].reshape(h, w, 3)


#: Extra noise values beyond one frame: the range of the per-frame offsets.
_NOISE_SLACK = 1 << 16


def make_background(width: int, height: int, seed: int = 0) -> Image:
    """A deterministic textured background (gradient plus soft blobs), H×W×3 BGR uint8."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    base = np.stack([90 + 60 * xx / width, 110 + 40 * yy / height, 140 - 50 * xx / width], -1)
    img = base.astype(np.float32)
    for _ in range(12):
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        r = rng.uniform(20, 90)
        colour = rng.uniform(-50, 50, size=3).astype(np.float32)
        blob = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))[..., None]
        img += blob * colour
    return np.clip(img, 0, 255).astype(np.uint8)


def _paste_face(frame: Image, box: ArrayLike) -> None:
    """Alpha-blend the sprite into ``frame`` (uint8, in place, only the sprite's rectangle); its
    face box lands on ``box``."""
    bx, by, bw, bh = (float(v) for v in np.asarray(box).reshape(4))
    fx0, fy0, fw, fh = SPRITE_FACE_BOX
    sx, sy = bw / fw, bh / fh
    level_scale, img, mask = _levels()[0]
    for ls, im, mk in _levels():
        if ls >= max(sx, sy):
            level_scale, img, mask = ls, im, mk
    rx, ry = sx / level_scale, sy / level_scale  # residual scale from the chosen level
    # Sprite-level pixel (i, j) → frame pixel: u = rx·i + tx (pixel centres, OpenCV convention).
    # A pyramid level of scale L maps its pixel j to base-sprite pixel j / L + (1 / L − 1) / 2.
    off = 0.5 * (1.0 / level_scale - 1.0)
    tx = bx + sx * (off - fx0)
    ty = by + sy * (off - fy0)
    h, w = frame.shape[:2]
    sh, sw = img.shape[:2]
    x0, y0 = max(0, math.floor(tx)), max(0, math.floor(ty))
    x1, y1 = min(w, math.ceil(tx + rx * sw)), min(h, math.ceil(ty + ry * sh))
    if x1 <= x0 or y1 <= y0:
        return
    m = np.array([[rx, 0.0, tx - x0], [0.0, ry, ty - y0]], dtype=np.float64)
    size = (x1 - x0, y1 - y0)
    patch = cv2.warpAffine(img, m, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    alpha = cv2.warpAffine(mask, m, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    region = frame[y0:y1, x0:x1]
    region[...] = cv2.blendLinear(patch, region, alpha, 1.0 - alpha)
