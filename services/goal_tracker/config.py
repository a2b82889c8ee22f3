"""Configuration of the goal tracker and the synthetic camera (``[goal_tracker.*]`` TOML tables).

Loaded with :func:`services.bus.config.load_config` (file < ``PSM_GOAL_TRACKER__…`` environment
variables < ``--set goal_tracker.x.y=v`` flags); every bad value is a one-line ``ConfigError``.
:func:`build_tracker` turns a validated config into the pure :class:`GoalTracker`.

Example file::

    prefix = "psm"
    [goal_tracker]
    goal_name = "person"
    [goal_tracker.camera]
    source = "device"          # synthetic | device | file | url | topic
    device = 0
    [goal_tracker.mount]       # camera -> robot base
    translation_m = [-0.2, 0.0, 0.5]
    rpy_deg = [-90.0, 0.0, -90.0]
    [goal_tracker.workspace]
    lower_m = [0.2, -0.6, 0.0]
    upper_m = [0.95, 0.6, 1.0]
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

from pydantic import Field

from services.bus.config import ConfigError, Section, ServiceConfig, Vec3
from services.goal_tracker.detectors import HaarParams, PipelineParams, YuNetParams
from services.goal_tracker.frames import SyntheticSection
from services.goal_tracker.geometry import MeasurementNoise
from services.goal_tracker.kalman import KalmanParams

if TYPE_CHECKING:
    from services.goal_tracker.geometry import FaceGeometry
    from services.goal_tracker.synthetic import SyntheticCamera
    from services.goal_tracker.tracker import GoalTracker

__all__ = [
    "CameraSection",
    "DetectorSection",
    "FaceSection",
    "FilterSection",
    "GoalTrackerSection",
    "MountSection",
    "SyntheticSection",
    "TrackerConfig",
    "WorkspaceSection",
    "build_geometry",
    "build_synthetic_camera",
    "build_tracker",
]

_DEFAULT_F = 320.0 / math.tan(math.radians(30.0))  # 640 px wide, 60° horizontal field of view


class CameraSection(Section):
    """``[goal_tracker.camera]``: where frames come from and the pinhole intrinsics."""

    source: Literal['synthetic', 'device', 'file', 'url', 'topic'] = Field(
        "synthetic",
        description="frame source",
    )
    device: int = Field(0, ge=0, description="camera device index (source = device)")
    uri: str = Field("", description="video file path (source = file) or stream URL (source = url)")
    camera_id: str = Field(
        "cam0", min_length=1,
        description="camera id: images go to <prefix>/camera/<id>/image (source = topic: the id subscribed "
        "to)",
    )
    width: int = Field(640, gt=0, description="image width the intrinsics refer to, px")
    height: int = Field(480, gt=0, description="image height the intrinsics refer to, px")
    fx: float = Field(_DEFAULT_F, gt=0.0, description="focal length x, px")
    fy: float = Field(_DEFAULT_F, gt=0.0, description="focal length y, px")
    cx: float = Field(320.0, description="principal point x, px")
    cy: float = Field(240.0, description="principal point y, px")
    loop: bool = Field(False, description="source = file: restart at the end instead of stopping")
    realtime: bool = Field(True, description="source = file: pace frames at the file's frame rate")
    reconnect_initial_s: float = Field(
        0.5, gt=0.0,
        description="first reconnect delay after a dropped stream, s",
    )
    reconnect_max_s: float = Field(5.0, gt=0.0, description="reconnect delay cap (exponential backoff), s")
    reconnect_give_up_s: float = Field(
        60.0, ge=0.0,
        description="give up after a stream is down this long, s (0 = never)",
    )
    image_rate_hz: float = Field(
        5.0, ge=0.0,
        description="publish JPEG frames at most this often (frame time), 0 = never",
    )
    jpeg_quality: int = Field(80, ge=1, le=100, description="JPEG quality of published frames")
    topic_max_pending: int = Field(
        256, ge=1, le=10000,
        description="source = topic: frames kept waiting when the tracker falls behind (oldest dropped); "
        "1-2 for a live stack (always a recent frame), large to analyse every frame of a replay",
    )
    stall_timeout_s: float = Field(
        2.0, gt=0.0,
        description="no frame for this long (wall clock) -> goal invalid (realtime only: in lockstep "
        "the planner's goal_timeout_s on the arm's clock covers a camera that stops)",
    )

    def check(self) -> None:
        """Cross-field checks."""
        if self.source in ("file", "url") and not self.uri:
            raise ConfigError("uri", f"source = {self.source!r} needs camera.uri")
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ConfigError("reconnect_max_s", "must be >= reconnect_initial_s")


class MountSection(Section):
    """``[goal_tracker.mount]``: camera → robot-base transform ``p_base = R p_cam + t``.

    ``R = Rz(yaw) Ry(pitch) Rx(roll)`` from ``rpy_deg``; the default is a camera 20 cm behind and
    50 cm above the base origin looking along the base +x axis.
    """

    translation_m: Vec3 = Field(
        default_factory=lambda: [-0.2, 0.0, 0.5],
        description="camera origin in base, m",
    )
    rpy_deg: Vec3 = Field(
        default_factory=lambda: [-90.0, 0.0, -90.0],
        description="roll, pitch, yaw, degrees",
    )
    frame_id: str = Field("base", min_length=1, description="frame of the published goal")


class FaceSection(Section):
    """``[goal_tracker.face]``: face model and the goal offset."""

    width_m: float = Field(
        0.168, gt=0.0, le=1.0,
        description="nominal face (detector box) width, m; calibrated per detector (this: the default "
        "Haar cascade with the default ROI settings)",
    )
    offset_m: Vec3 = Field(
        default_factory=lambda: [0.0, 0.045, 0.0],
        description="goal = face centre + this, camera frame (x right, y down, z forward), m; default: the "
        "mouth",
    )


class DetectorSection(PipelineParams, HaarParams, YuNetParams):
    """``[goal_tracker.detector]``: the face detector (its kind, model and settings) and the
    speed knobs of the detection pipeline, each field the one of the model it configures."""

    kind: Literal["haar", "yunet"] = Field("haar", description="face detector")
    model_path: str = Field(
        "",
        description="model file: Haar XML (empty = OpenCV's haarcascade_frontalface_alt2.xml) or "
        "YuNet ONNX (required for yunet)",
    )

    def check(self) -> None:
        """YuNet needs a model."""
        if self.kind == "yunet" and not self.model_path:
            raise ConfigError("model_path", "detector.kind = 'yunet' needs a YuNet ONNX model file")


class FilterSection(KalmanParams, MeasurementNoise):
    """``[goal_tracker.filter]``: Kalman filter, outlier gate, lost timeout, measurement noise,
    target selection."""

    min_hits: int = Field(2, ge=1, description="frames a face must be seen before it can become the target")


class WorkspaceSection(Section):
    """``[goal_tracker.workspace]``: reachable box (base frame), optionally a spherical shell."""

    lower_m: Vec3 = Field(default_factory=lambda: [0.2, -0.6, 0.0], description="m")
    upper_m: Vec3 = Field(default_factory=lambda: [0.95, 0.6, 1.0], description="m")
    centre_m: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.3], description="centre of the shell, m")
    min_radius_m: float = Field(0.0, ge=0.0, description="min distance from centre_m, m")
    max_radius_m: float = Field(0.0, ge=0.0, description="max distance from centre_m, m (0 = no limit)")

    def check(self) -> None:
        """Bounds ordered."""
        if any(lo >= hi for lo, hi in zip(self.lower_m, self.upper_m, strict=True)):
            raise ConfigError("lower_m", f"must be < upper_m per axis, got {self.lower_m} vs {self.upper_m}")
        if self.max_radius_m and self.max_radius_m <= self.min_radius_m:
            raise ConfigError("max_radius_m", "must be > min_radius_m (or 0 = no limit)")


class GoalTrackerSection(Section):
    """``[goal_tracker]``."""

    goal_name: str = Field("person", min_length=1, description="goal published on <prefix>/goals/<goal_name>")
    camera: CameraSection = Field(default_factory=CameraSection)
    mount: MountSection = Field(default_factory=MountSection)
    face: FaceSection = Field(default_factory=FaceSection)
    detector: DetectorSection = Field(default_factory=DetectorSection)
    filter: FilterSection = Field(default_factory=FilterSection)
    workspace: WorkspaceSection = Field(default_factory=WorkspaceSection)
    synthetic: SyntheticSection = Field(default_factory=SyntheticSection)

    def check(self) -> None:
        """Key chunks are valid."""
        from services.bus.messages import InvalidKeyError, Keys

        try:
            Keys().goal(self.goal_name)
        except InvalidKeyError as exc:
            raise ConfigError("goal_name", str(exc)) from None
        try:
            Keys().camera_image(self.camera.camera_id)
        except InvalidKeyError as exc:
            raise ConfigError("camera.camera_id", str(exc)) from None


class TrackerConfig(ServiceConfig):
    """Goal tracker / synthetic camera service configuration."""

    goal_tracker: GoalTrackerSection = Field(default_factory=GoalTrackerSection)


# --------------------------------------------------------------------------------------------
# Builders: config -> pure objects
# --------------------------------------------------------------------------------------------


def build_geometry(sec: GoalTrackerSection) -> FaceGeometry:
    """The :class:`~services.goal_tracker.geometry.FaceGeometry` of a config."""
    from services.goal_tracker.geometry import FaceGeometry, Intrinsics, Transform

    cam = sec.camera
    intr = Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    mount = Transform.from_rpy(sec.mount.translation_m, sec.mount.rpy_deg)
    return FaceGeometry(
        intr, sec.face.width_m, mount, tuple(sec.face.offset_m), sec.filter.project(MeasurementNoise)
    )


def build_tracker(sec: GoalTrackerSection) -> GoalTracker:
    """The pure :class:`~services.goal_tracker.tracker.GoalTracker` of a config.

    Raises ``FileNotFoundError`` when a configured model file is missing."""
    from services.goal_tracker.detectors import DetectionPipeline, make_detector
    from services.goal_tracker.selection import TargetSelector
    from services.goal_tracker.tracker import GoalTracker
    from services.goal_tracker.workspace import Workspace

    d = sec.detector
    params = d.project(HaarParams) if d.kind == "haar" else d.project(YuNetParams)
    detector = make_detector(d.kind, d.model_path, params)
    pipeline = DetectionPipeline(detector, d.project(PipelineParams))
    kalman = sec.filter.project(KalmanParams)
    w = sec.workspace
    workspace = Workspace(
        tuple(w.lower_m),
        tuple(w.upper_m),
        tuple(w.centre_m),
        w.min_radius_m,
        w.max_radius_m if w.max_radius_m > 0 else math.inf,
    )
    selector = TargetSelector(min_hits=sec.filter.min_hits)
    return GoalTracker(build_geometry(sec), pipeline, kalman, workspace, selector)


def build_synthetic_camera(sec: GoalTrackerSection) -> SyntheticCamera:
    """The :class:`~services.goal_tracker.synthetic.SyntheticCamera` of a config (same
    intrinsics as the tracker, so the tracker inverts exactly the model that rendered)."""
    from services.goal_tracker.geometry import Intrinsics
    from services.goal_tracker.synthetic import LissajousPath, SyntheticCamera, SyntheticFace

    cam, s = sec.camera, sec.synthetic
    path = LissajousPath(tuple(s.centre_m), tuple(s.amplitude_m), tuple(s.frequency_hz), tuple(s.phase_rad))
    face = SyntheticFace(path, s.face_width_m, tuple((w[0], w[1]) for w in s.hidden_s))
    intr = Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    return SyntheticCamera(intr, (face,), s.noise_sigma, s.seed)
