"""Target selection: keep one face across frames (largest, most stable), ignore the others.

Detections are associated frame to frame by intersection-over-union into short tracks. The target
is kept while its track lives; when it dies, the new target is the largest track that has been
seen in at least ``min_hits`` consecutive frames, so a one-frame false positive never wins.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from psm.errors import ParameterError


@dataclass(frozen=True)
class Detection:
    """One face box in full-frame pixels: ``(x, y, w, h)``, detector confidence in [0, 1]."""

    x: float
    y: float
    w: float
    h: float
    confidence: float = 1.0

    @property
    def box(self) -> np.ndarray:
        """``(x, y, w, h)`` as a float array (4,)."""
        return np.array([self.x, self.y, self.w, self.h], dtype=float)

    @property
    def area(self) -> float:
        """Box area in pixels²."""
        return self.w * self.h

    @property
    def centre(self) -> tuple[float, float]:
        """Box centre (u, v) in pixels."""
        return self.x + self.w / 2.0, self.y + self.h / 2.0


def iou(a: ArrayLike, b: ArrayLike) -> float:
    """Intersection over union of two ``(x, y, w, h)`` boxes, in [0, 1]."""
    ax, ay, aw, ah = (float(v) for v in np.asarray(a).reshape(4))
    bx, by, bw, bh = (float(v) for v in np.asarray(b).reshape(4))
    ix = max(0.0, min(ax + aw, bx + bw) - max(ax, bx))
    iy = max(0.0, min(ay + ah, by + bh) - max(ay, by))
    inter = ix * iy
    union = aw * ah + bw * bh - inter
    return inter / union if union > 0 else 0.0


@dataclass
class Track:
    """A face followed across frames."""

    track_id: int
    detection: Detection
    hits: int = 1  #: consecutive frames with a match
    misses: int = 0  #: consecutive frames without one


@dataclass
class TargetSelector:
    """Greedy IoU tracker with a sticky target.

    Attributes:
        iou_threshold: minimum IoU to continue a track.
        min_hits: consecutive hits before a track can become the target.
        max_misses: a track is dropped after this many frames without a match.
    """

    iou_threshold: float = 0.3
    min_hits: int = 2
    max_misses: int = 3
    tracks: list[Track] = field(default_factory=list)
    target_id: int | None = None
    _next_id: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.iou_threshold < 1 or self.min_hits < 1 or self.max_misses < 0:
            raise ParameterError("selection needs 0 < iou_threshold < 1, min_hits >= 1, max_misses >= 0")

    def reset(self) -> None:
        """Forget every track and the target."""
        self.tracks.clear()
        self.target_id = None

    @property
    def target(self) -> Track | None:
        """The current target track, if any."""
        for track in self.tracks:
            if track.track_id == self.target_id:
                return track
        return None

    def update(self, detections: list[Detection]) -> Detection | None:
        """Associate this frame's detections; return the target's detection *in this frame*, or
        None when the target was not seen this frame (it may still be alive, see ``target``)."""
        pairs = sorted(
            (
                (iou(t.detection.box, d.box), ti, di)
                for ti, t in enumerate(self.tracks)
                for di, d in enumerate(detections)
            ),
            reverse=True,
        )
        used_t: set[int] = set()
        used_d: set[int] = set()
        for score, ti, di in pairs:
            if score < self.iou_threshold or ti in used_t or di in used_d:
                continue
            used_t.add(ti)
            used_d.add(di)
            track = self.tracks[ti]
            track.detection = detections[di]
            track.hits += 1
            track.misses = 0
        for ti, track in enumerate(self.tracks):
            if ti not in used_t:
                track.misses += 1
                track.hits = 0
        self.tracks = [t for t in self.tracks if t.misses <= self.max_misses]
        for di, det in enumerate(detections):
            if di not in used_d:
                self.tracks.append(Track(self._next_id, det))
                self._next_id += 1
        if self.target is None:
            ready = [t for t in self.tracks if t.hits >= self.min_hits]
            self.target_id = max(ready, key=lambda t: t.detection.area).track_id if ready else None
        target = self.target
        return target.detection if target is not None and target.misses == 0 else None
