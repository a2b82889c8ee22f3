"""Face detectors (Haar cascade, YuNet) and the fast detection pipeline.

The pipeline runs a *full* detection on a reduced-resolution copy of the frame only every
``full_every`` frames (or when the target is lost) and, in between, an *ROI* detection around the
predicted target box at near full resolution with a narrow size range. Every full detection is
refined by an ROI pass too, so all boxes the filter sees have the same statistics.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import ConfigDict, Field, field_validator

from psm.errors import ParameterError
from services.bus.config import Section
from services.goal_tracker.selection import Detection, iou

Image = NDArray[np.uint8]

#: Default Haar model file (ships with opencv-python-headless).
HAAR_DEFAULT = "haarcascade_frontalface_alt2.xml"


class FaceDetector(Protocol):
    """Finds faces in an image region."""

    name: str

    def detect(
        self,
        image: Image,
        min_size: int,
        max_size: int | None = None,
        fine: bool = False,
    ) -> list[Detection]:
        """Faces in ``image`` (H×W×3 BGR or H×W grey uint8), boxes in that image's pixels.

        Args:
            min_size, max_size: face width range in pixels (``max_size`` None: unbounded).
            fine: use a finer scale step (ROI refinement; slower per pixel, more precise size).
        """
        ...


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


class HaarParams(Section):
    """Settings of :class:`HaarDetector` (part of ``[goal_tracker.detector]``)."""

    model_config = ConfigDict(frozen=True)

    scale_factor: float = Field(1.1, gt=1.0, le=2.0, description="Haar scale step of full detections")
    fine_scale_factor: float = Field(1.07, gt=1.0, le=2.0, description="Haar scale step of ROI detections")
    min_neighbors: int = Field(4, ge=0, description="Haar minNeighbors")


class YuNetParams(Section):
    """Settings of :class:`YuNetDetector` (part of ``[goal_tracker.detector]``)."""

    model_config = ConfigDict(frozen=True)

    score_threshold: float = Field(0.7, gt=0.0, lt=1.0, description="YuNet score threshold")
    nms_threshold: float = Field(0.3, gt=0.0, lt=1.0, description="YuNet non-maximum suppression IoU")


class HaarDetector:
    """OpenCV Haar cascade. Confidence is the logistic of the cascade's last-stage weight."""

    name = "haar"

    def __init__(self, model_path: str | None = None, params: HaarParams | None = None) -> None:
        params = params or HaarParams()
        path = model_path or os.path.join(cv2.data.haarcascades, HAAR_DEFAULT)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"Haar cascade file not found: {path}")
        self._cascade = cv2.CascadeClassifier()
        try:
            loaded = self._cascade.load(path)
        except (cv2.error, SystemError):
            loaded = False
        if not loaded or self._cascade.empty():
            raise ParameterError(f"Haar cascade file could not be loaded: {path}")
        self.scale_factor = params.scale_factor
        self.fine_scale_factor = params.fine_scale_factor
        self.min_neighbors = params.min_neighbors

    def detect(
        self, image: Image, min_size: int, max_size: int | None = None, fine: bool = False
    ) -> list[Detection]:
        """See :class:`FaceDetector`."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        min_size = max(int(min_size), 24)
        if max_size is not None and max_size < min_size:
            return []
        boxes, _levels, weights = self._cascade.detectMultiScale3(
            gray,
            scaleFactor=self.fine_scale_factor if fine else self.scale_factor,
            minNeighbors=self.min_neighbors,
            minSize=(min_size, min_size),
            maxSize=(int(max_size), int(max_size)) if max_size else (0, 0),
            outputRejectLevels=True,
        )
        return [
            Detection(float(x), float(y), float(w), float(h), _sigmoid(float(wt)))
            for (x, y, w, h), wt in zip(
                np.asarray(boxes).reshape(-1, 4), np.asarray(weights).reshape(-1), strict=True
            )
        ]


class YuNetDetector:
    """OpenCV's YuNet CNN face detector (``cv2.FaceDetectorYN``); needs an ONNX model file."""

    name = "yunet"

    def __init__(self, model_path: str, params: YuNetParams | None = None) -> None:
        params = params or YuNetParams()
        if not model_path or not os.path.isfile(model_path):
            raise FileNotFoundError(
                f"YuNet model file not found: {model_path!r} (set goal_tracker.detector.model_path "
                "to a face_detection_yunet_*.onnx file, or use detector.kind = 'haar')"
            )
        self._net = cv2.FaceDetectorYN.create(
            model_path, "", (320, 320), params.score_threshold, params.nms_threshold
        )
        self._size: tuple[int, int] = (320, 320)

    def detect(
        self, image: Image, min_size: int, max_size: int | None = None, fine: bool = False
    ) -> list[Detection]:
        """See :class:`FaceDetector`; ``fine`` has no effect (YuNet regresses boxes directly)."""
        h, w = image.shape[:2]
        if (w, h) != self._size:
            self._net.setInputSize((w, h))
            self._size = (w, h)
        bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        _, faces = self._net.detect(bgr)
        out: list[Detection] = []
        for row in np.asarray(faces if faces is not None else []).reshape(-1, 15):
            fw = float(row[2])
            if fw < min_size or (max_size is not None and fw > max_size):
                continue
            out.append(Detection(float(row[0]), float(row[1]), fw, float(row[3]), float(row[14])))
        return out


def make_detector(
    kind: str, model_path: str | None = None, params: HaarParams | YuNetParams | None = None
) -> FaceDetector:
    """Build the configured detector: ``"haar"`` (default model when ``model_path`` is empty) or
    ``"yunet"`` (``model_path`` required), with its settings (default: the model's)."""
    if kind == "haar":
        return HaarDetector(model_path or None, params if isinstance(params, HaarParams) else None)
    if kind == "yunet":
        return YuNetDetector(model_path or "", params if isinstance(params, YuNetParams) else None)
    raise ParameterError(f"detector.kind must be 'haar' or 'yunet', got {kind!r}")


class PipelineParams(Section):
    """Speed/accuracy knobs of :class:`DetectionPipeline` (part of ``[goal_tracker.detector]``)."""

    model_config = ConfigDict(frozen=True)

    detect_width: int = Field(
        320, ge=64, description="full detections run on the frame resized to this width [px]"
    )
    full_every: int = Field(
        30, ge=1, description="full detection at least every N frames (ROI tracking between)"
    )
    min_face_px: int = Field(
        40, ge=8, description="smallest face width searched by a full detection [px]"
    )
    roi_margin: float = Field(
        1.5, ge=1.2,
        description="ROI side = predicted face size x this (below ~1.4 the side cuts off the "
        "largest faces of roi_size_range and biases the boxes)",
    )
    roi_max_face_px: int = Field(
        128, ge=48,
        description="faces wider than this are searched in an ROI at 1/2, 1/4... resolution [px]",
    )
    roi_size_range: tuple[float, float] = Field(
        (0.75, 1.45), description="(min, max) face width in an ROI relative to the predicted width"
    )
    max_refine: int = Field(
        3, ge=0, description="how many faces of a full detection get an ROI refinement"
    )
    roi_origin_step: int = Field(
        8, ge=1, le=64,
        description="the ROI's origin and side lie on a grid of this many ROI pixels, its offset "
        "cycled through all values over this many ROI detections [px]",
    )
    roi_size_step: float = Field(
        1.1, gt=1.0, le=2.0,
        description="the ROI and its face-size window follow the predicted face width in "
        "geometric steps of this factor (never continuously: no prediction feedback)",
    )

    @field_validator("roi_size_range")
    @classmethod
    def _size_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        lo, hi = value
        if not 0.3 <= lo < 1.0 < hi <= 3.0:
            raise ValueError(f"must satisfy 0.3 <= min < 1 < max <= 3, got {lo}, {hi}")
        return value


def _snap_geometric(value: float, step: float) -> float:
    """``value`` (> 0) rounded to the nearest power of ``step`` (> 1): a grid fixed in log space."""
    return float(step ** round(math.log(value) / math.log(step)))


@dataclass
class PipelineResult:
    """Detections of one frame (full-frame pixels) and how they were obtained."""

    detections: list[Detection]
    mode: str  #: "full" (reduced-resolution full frame, refined) or "roi"


class DetectionPipeline:
    """Reduced-resolution full detection + ROI tracking; see the module docstring."""

    def __init__(self, detector: FaceDetector, params: PipelineParams | None = None) -> None:
        self.detector = detector
        self.params = params or PipelineParams()
        self._since_full = 1 << 30
        self._roi_calls = 0  #: ROI detections run so far: the index of the grid offset
        self.full_count = 0
        self.roi_count = 0

    def force_full(self) -> None:
        """Make the next frame a full detection."""
        self._since_full = 1 << 30

    def full(self, frame: Image) -> list[Detection]:
        """Full-frame detection at ``detect_width`` (boxes in full-frame pixels, unrefined)."""
        h, w = frame.shape[:2]
        scale = min(1.0, self.params.detect_width / w)
        small = (
            frame
            if scale == 1.0
            else cv2.resize(frame, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
        )
        min_px = max(24, round(self.params.min_face_px * scale))
        dets = self.detector.detect(small, min_px)
        return [Detection(d.x / scale, d.y / scale, d.w / scale, d.h / scale, d.confidence) for d in dets]

    def roi(self, frame: Image, hint: Detection) -> Detection | None:
        """Re-detect the face near ``hint`` (a full-frame box) in an ROI; None if not found."""
        p = self.params
        h, w = frame.shape[:2]
        cu, cv_ = hint.centre
        # The ROI's size and its face-size window come from the hint's width snapped to a
        # geometric grid (steps of roi_size_step), not from the hint itself: Haar's box size
        # depends on the searched size window (which scales are grouped), so a window that
        # followed the prediction continuously would pull the measured size towards the
        # prediction — a lagging prediction would make the measurement lag too.
        ref = _snap_geometric(max(hint.w, hint.h, 1.0), p.roi_size_step)
        # Large faces are searched at a power-of-two reduced resolution. The scale must not
        # follow the hint continuously: the detector's box sizes are quantised on its scale grid,
        # and a grid that moves with the prediction would feed the prediction back into the
        # measurement.
        scale = 0.5 ** max(0, math.ceil(math.log2(ref / p.roi_max_face_px)))
        # For the same reason the window's side and origin sit on a grid of roi_origin_step
        # ROI pixels: a still face gets the same crop every frame (only the sensor noise
        # differs), instead of one that shifts by a pixel, and changes the downsampling phase and
        # hence the box size, whenever the prediction crosses a pixel boundary.
        # The grid itself is shifted from one ROI to the next through all roi_origin_step
        # offsets (a fixed 1-D lattice of (3k, 5k) mod step in ROI pixels, frame counter k): the
        # box size Haar finds depends on where the face sits on the crop's pixel grid, a bias that
        # a fixed grid would make constant for a still face. Cycling the offsets turns it into a
        # zero-mean periodic error that the filter averages out (period roi_origin_step frames).
        grid = p.roi_origin_step / scale
        k = self._roi_calls
        self._roi_calls += 1
        off_x = (3 * k) % p.roi_origin_step / scale
        off_y = (5 * k) % p.roi_origin_step / scale
        side = math.ceil(ref * p.roi_margin / grid) * grid
        x0 = max(0, int(math.floor((cu - side / 2 - off_x) / grid) * grid + off_x))
        y0 = max(0, int(math.floor((cv_ - side / 2 - off_y) / grid) * grid + off_y))
        x1, y1 = min(w, int(x0 + side)), min(h, int(y0 + side))
        if x1 - x0 < 24 or y1 - y0 < 24:
            return None
        crop = frame[y0:y1, x0:x1]
        size = (max(24, round((x1 - x0) * scale)), max(24, round((y1 - y0) * scale)))
        if scale < 1.0:
            crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        scale_x, scale_y = size[0] / (x1 - x0), size[1] / (y1 - y0)
        expected = ref * scale
        lo, hi = p.roi_size_range
        dets = self.detector.detect(crop, int(expected * lo), math.ceil(expected * hi) + 1, fine=True)
        if not dets:
            return None
        full = [
            Detection(x0 + d.x / scale_x, y0 + d.y / scale_y, d.w / scale_x, d.h / scale_y, d.confidence)
            for d in dets
        ]
        return max(full, key=lambda d: (iou(d.box, hint.box), -abs(d.w - hint.w)))

    def process(self, frame: Image, hint: Detection | None) -> PipelineResult:
        """Detect faces in ``frame`` (H×W×3 BGR). ``hint`` is the predicted target box or None.

        ROI mode when a hint is given and a full detection is not due; falls back to a full
        detection in the same frame when the ROI finds nothing."""
        self._since_full += 1
        if hint is not None and self._since_full < self.params.full_every:
            found = self.roi(frame, hint)
            if found is not None:
                self.roi_count += 1
                return PipelineResult([found], "roi")
        self._since_full = 0
        self.full_count += 1
        coarse = self.full(frame)
        refined: list[Detection] = []
        for i, det in enumerate(sorted(coarse, key=lambda d: -d.area)):
            better = self.roi(frame, det) if i < self.params.max_refine else None
            refined.append(better if better is not None else det)
        return PipelineResult(refined, "full")
