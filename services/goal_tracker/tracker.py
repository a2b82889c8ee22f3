"""The goal tracker's per-frame logic, free of any bus or camera I/O.

``GoalTracker.process(frame, stamp_ns)`` runs detection (reduced-resolution full detection plus ROI
tracking), target selection, pixel → 3-D conversion, the Kalman filter and the workspace check, and
returns a :class:`TrackOutput` describing the frame's detections and the goal to publish.
Time is the frame stamp only, so the same frames always give the same goals.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from services.goal_tracker.detectors import DetectionPipeline, Image
from services.goal_tracker.geometry import FaceGeometry
from services.goal_tracker.kalman import ConstantVelocityKalman, KalmanParams, UpdateResult
from services.goal_tracker.selection import Detection, TargetSelector
from services.goal_tracker.workspace import Workspace


class TrackState(enum.Enum):
    """Tracking state of the goal after a frame."""

    SEARCHING = "searching"  #: no target yet (start-up, or after lost)
    TRACKING = "tracking"  #: the target was measured in this frame
    PREDICTING = "predicting"  #: target not measured this frame; estimate is a prediction
    LOST = "lost"  #: the target was not seen for longer than the lost timeout (this frame)


@dataclass
class TrackOutput:
    """Result of one frame.

    Attributes:
        stamp_ns: the frame's stamp, ns.
        detections: every face box reported this frame (full-frame pixels).
        target_index: index of the target in ``detections`` or -1.
        mode: "full" or "roi" (how detection ran).
        state: see :class:`TrackState`.
        position: (3,) goal in the base frame, metres (NaN when there is no estimate).
        velocity: (3,) m/s (NaN when there is no estimate).
        covariance: (3, 3) position covariance, m² (NaN when there is no estimate).
        valid: the goal may be used as a target.
        reason: why it is invalid ("" when valid).
        measurement: (3,) the raw measured goal this frame, or None.
        update: what the filter did with the measurement, or None.
    """

    stamp_ns: int
    detections: list[Detection]
    target_index: int
    mode: str
    state: TrackState
    position: NDArray[np.float64]
    velocity: NDArray[np.float64]
    covariance: NDArray[np.float64]
    valid: bool
    reason: str
    measurement: NDArray[np.float64] | None = None
    update: UpdateResult | None = None


@dataclass
class TrackerStats:
    """Counters since start."""

    frames: int = 0
    full_detections: int = 0
    roi_detections: int = 0
    measurements: int = 0
    rejected: int = 0
    reinitialised: int = 0
    lost_events: int = 0
    found_events: int = 0
    out_of_workspace: int = 0
    valid_goals: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counters as a plain dict (for logs)."""
        return dict(self.__dict__)


_NAN3 = np.full(3, np.nan)


@dataclass
class GoalTracker:
    """Frames in, goals out. See the module docstring."""

    geometry: FaceGeometry
    pipeline: DetectionPipeline
    kalman_params: KalmanParams = field(default_factory=KalmanParams)
    workspace: Workspace = field(default_factory=Workspace)
    selector: TargetSelector = field(default_factory=TargetSelector)

    def __post_init__(self) -> None:
        self.kf = ConstantVelocityKalman(self.kalman_params)
        self.stats = TrackerStats()
        self._target_id: int | None = None
        self._last_stamp_ns: int | None = None

    def set_image_size(self, width: int, height: int) -> None:
        """Rescale the intrinsics when frames arrive at another resolution than configured
        (e.g. a 1280×720 stream for intrinsics given at 640×360)."""
        intr = self.geometry.intrinsics
        if (width, height) != (intr.width, intr.height):
            self.geometry = replace(self.geometry, intrinsics=intr.scaled(width, height))

    def _predicted_box(self, t: float) -> Detection | None:
        """Where the filter expects the target face at time ``t``, as a full-frame box."""
        if not self.kf.initialised or self.kf.is_lost(t):
            return None
        dt = max(0.0, t - (self.kf.t or t))
        p = self.kf.position + self.kf.velocity * dt
        try:
            x, y, w, h = self.geometry.goal_to_box(p)
        except ValueError:
            return None
        return Detection(float(x), float(y), float(w), float(h))

    def process(self, frame: Image, stamp_ns: int) -> TrackOutput:
        """Run one frame (H×W×3 BGR or H×W grey uint8) with stamp ``stamp_ns`` (ns) through the tracker."""
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            # Out-of-order or repeated stamp: keep time monotonic for the filter.
            stamp_ns = self._last_stamp_ns + 1
        self._last_stamp_ns = stamp_ns
        t = stamp_ns * 1e-9
        self.stats.frames += 1
        hint = self._predicted_box(t)
        result = self.pipeline.process(frame, hint)
        if result.mode == "full":
            self.stats.full_detections += 1
        else:
            self.stats.roi_detections += 1
        target = self.selector.update(result.detections)
        target_index = -1
        if target is not None:
            target_index = next(i for i, d in enumerate(result.detections) if d is target)
        new_id = self.selector.target_id
        if new_id is not None and new_id != self._target_id:
            # A different face became the target: its filter starts afresh. (A target whose
            # track merely died keeps being predicted until the lost timeout.)
            if self._target_id is not None:
                self.kf.reset()
            self._target_id = new_id
        was_tracking = self.kf.initialised
        measurement = None
        update = None
        if target is not None:
            measurement, r = self.geometry.measure(target.box)
            update = self.kf.update(t, measurement, r)
            self.stats.measurements += 1
            if update is UpdateResult.REJECTED:
                self.stats.rejected += 1
            elif update is UpdateResult.REINITIALISED:
                self.stats.reinitialised += 1
            elif update is UpdateResult.INITIALISED and not was_tracking:
                self.stats.found_events += 1
        else:
            self.kf.predict(t)
        measured = update in (
            UpdateResult.ACCEPTED,
            UpdateResult.INITIALISED,
            UpdateResult.REINITIALISED,
        )
        if self.kf.initialised and self.kf.is_lost(t):
            since = t - (self.kf.last_update_t or t)
            self.kf.reset()
            self.selector.reset()
            self._target_id = None
            self.pipeline.force_full()
            self.stats.lost_events += 1
            return TrackOutput(
                stamp_ns,
                result.detections,
                target_index,
                result.mode,
                TrackState.LOST,
                _NAN3.copy(),
                _NAN3.copy(),
                np.full((3, 3), np.nan),
                False,
                f"lost: no face accepted for {since:.2f} s "
                f"(timeout {self.kalman_params.lost_timeout_s:.2f} s)",
                measurement,
                update,
            )
        if not self.kf.initialised:
            return TrackOutput(
                stamp_ns,
                result.detections,
                target_index,
                result.mode,
                TrackState.SEARCHING,
                _NAN3.copy(),
                _NAN3.copy(),
                np.full((3, 3), np.nan),
                False,
                "searching: no face tracked",
                measurement,
                update,
            )
        position = self.kf.position
        reason = self.workspace.violation(position)
        if reason is not None:
            self.stats.out_of_workspace += 1
        else:
            self.stats.valid_goals += 1
        return TrackOutput(
            stamp_ns,
            result.detections,
            target_index,
            result.mode,
            TrackState.TRACKING if measured else TrackState.PREDICTING,
            position,
            self.kf.velocity,
            self.kf.position_cov,
            reason is None,
            reason or "",
            measurement,
            update,
        )
