"""Configuration of the goal tracker and the synthetic camera (``[goal_tracker.*]`` TOML tables).

Loaded with :func:`services.bus.config.load_config` (file < ``PSM_GOAL_TRACKER_…`` environment
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
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from services.bus.config import ConfigError, ServiceConfig, meta, spec

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


def _vec3(path: str, values: list[float], positive: bool = False) -> None:
    if len(values) != 3:
        raise ConfigError(path, f"expected 3 numbers, got {len(values)}")
    if any(not math.isfinite(v) for v in values):
        raise ConfigError(path, f"expected finite numbers, got {values}")
    if positive and any(v <= 0 for v in values):
        raise ConfigError(path, f"expected numbers > 0, got {values}")


@dataclass
class CameraSection:
    """``[goal_tracker.camera]``: where frames come from and the pinhole intrinsics."""

    source: str = spec("synthetic", "frame source", choices=("synthetic", "device", "file", "url", "topic"))
    device: int = spec(0, "camera device index (source = device)", ge=0)
    uri: str = spec("", "video file path (source = file) or stream URL (source = url)")
    camera_id: str = spec(
        "cam0",
        "camera id: images go to <prefix>/camera/<id>/image (source = topic: the id subscribed to)",
        min_len=1,
    )
    width: int = spec(640, "image width the intrinsics refer to, px", gt=0)
    height: int = spec(480, "image height the intrinsics refer to, px", gt=0)
    fx: float = spec(_DEFAULT_F, "focal length x, px", gt=0.0)
    fy: float = spec(_DEFAULT_F, "focal length y, px", gt=0.0)
    cx: float = spec(320.0, "principal point x, px")
    cy: float = spec(240.0, "principal point y, px")
    loop: bool = spec(False, "source = file: restart at the end instead of stopping")
    realtime: bool = spec(True, "source = file: pace frames at the file's frame rate")
    reconnect_initial_s: float = spec(0.5, "first reconnect delay after a dropped stream, s", gt=0.0)
    reconnect_max_s: float = spec(5.0, "reconnect delay cap (exponential backoff), s", gt=0.0)
    reconnect_give_up_s: float = spec(60.0, "give up after a stream is down this long, s (0 = never)", ge=0.0)
    image_rate_hz: float = spec(5.0, "publish JPEG frames at most this often (frame time), 0 = never", ge=0.0)
    jpeg_quality: int = spec(80, "JPEG quality of published frames", ge=1, le=100)
    stall_timeout_s: float = spec(2.0, "no frame for this long (wall clock) -> goal invalid", gt=0.0)

    def validate(self) -> None:
        """Cross-field checks."""
        if self.source in ("file", "url") and not self.uri:
            raise ConfigError("uri", f"source = {self.source!r} needs camera.uri")
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ConfigError("reconnect_max_s", "must be >= reconnect_initial_s")


@dataclass
class MountSection:
    """``[goal_tracker.mount]``: camera → robot-base transform ``p_base = R p_cam + t``.

    ``R = Rz(yaw) Ry(pitch) Rx(roll)`` from ``rpy_deg``; the default is a camera 20 cm behind and
    50 cm above the base origin looking along the base +x axis.
    """

    translation_m: list[float] = field(
        default_factory=lambda: [-0.2, 0.0, 0.5], metadata=meta("camera origin in base, m")
    )
    rpy_deg: list[float] = field(
        default_factory=lambda: [-90.0, 0.0, -90.0], metadata=meta("roll, pitch, yaw, degrees")
    )
    frame_id: str = spec("base", "frame of the published goal", min_len=1)

    def validate(self) -> None:
        """Vector lengths."""
        _vec3("translation_m", self.translation_m)
        _vec3("rpy_deg", self.rpy_deg)


@dataclass
class FaceSection:
    """``[goal_tracker.face]``: face model and the goal offset."""

    width_m: float = spec(0.16, "nominal face (detector box) width, m", gt=0.0, le=1.0)
    offset_m: list[float] = field(
        default_factory=lambda: [0.0, 0.045, 0.0],
        metadata=meta(
            "goal = face centre + this, camera frame (x right, y down, z forward), m; default: the mouth"
        ),
    )

    def validate(self) -> None:
        """Vector length."""
        _vec3("offset_m", self.offset_m)


@dataclass
class DetectorSection:
    """``[goal_tracker.detector]``: face detector and the speed knobs of the pipeline."""

    kind: str = spec("haar", "face detector", choices=("haar", "yunet"))
    model_path: str = spec(
        "",
        "model file: Haar XML (empty = OpenCV's default frontal face) or YuNet ONNX (required for yunet)",
    )
    detect_width: int = spec(320, "full detections run on the frame resized to this width, px", ge=64)
    full_every: int = spec(10, "full detection at least every N frames (ROI tracking between)", ge=1)
    min_face_px: int = spec(40, "smallest face width searched by a full detection, px", ge=8)
    scale_factor: float = spec(1.1, "Haar scale step of full detections", gt=1.0, le=2.0)
    fine_scale_factor: float = spec(1.1, "Haar scale step of ROI detections", gt=1.0, le=2.0)
    min_neighbors: int = spec(4, "Haar minNeighbors", ge=0)
    roi_margin: float = spec(2.2, "ROI side = predicted face size x this", ge=1.2)
    roi_max_face_px: int = spec(
        128, "faces wider than this are searched in an ROI at 1/2, 1/4... resolution, px", ge=48
    )
    score_threshold: float = spec(0.7, "YuNet score threshold", gt=0.0, lt=1.0)

    def validate(self) -> None:
        """YuNet needs a model."""
        if self.kind == "yunet" and not self.model_path:
            raise ConfigError("model_path", "detector.kind = 'yunet' needs a YuNet ONNX model file")


@dataclass
class FilterSection:
    """``[goal_tracker.filter]``: Kalman filter, outlier gate, lost timeout, target selection."""

    accel_psd: float = spec(0.5, "white-acceleration spectral density, m^2/s^3", ge=0.0)
    initial_velocity_sigma: float = spec(0.5, "velocity 1-sigma at (re)start, m/s", gt=0.0)
    gate_probability: float = spec(0.999, "chi-square gate probability (3 dof)", gt=0.0, lt=1.0)
    max_consecutive_rejections: int = spec(5, "restart the filter after N rejections in a row", ge=1)
    lost_timeout_s: float = spec(0.5, "no accepted face for this long (frame time) -> lost", gt=0.0)
    pixel_sigma: list[float] = field(
        default_factory=lambda: [1.5, 1.5, 2.0],
        metadata=meta("1-sigma noise of box centre u, v and width w, px"),
    )
    min_hits: int = spec(2, "frames a face must be seen before it can become the target", ge=1)

    def validate(self) -> None:
        """Vector length."""
        _vec3("pixel_sigma", self.pixel_sigma, positive=True)


@dataclass
class WorkspaceSection:
    """``[goal_tracker.workspace]``: reachable box (base frame), optionally a spherical shell."""

    lower_m: list[float] = field(default_factory=lambda: [0.2, -0.6, 0.0], metadata=meta("m"))
    upper_m: list[float] = field(default_factory=lambda: [0.95, 0.6, 1.0], metadata=meta("m"))
    centre_m: list[float] = field(
        default_factory=lambda: [0.0, 0.0, 0.3], metadata=meta("centre of the shell, m")
    )
    min_radius_m: float = spec(0.0, "min distance from centre_m, m", ge=0.0)
    max_radius_m: float = spec(0.0, "max distance from centre_m, m (0 = no limit)", ge=0.0)

    def validate(self) -> None:
        """Bounds ordered."""
        _vec3("lower_m", self.lower_m)
        _vec3("upper_m", self.upper_m)
        _vec3("centre_m", self.centre_m)
        if any(lo >= hi for lo, hi in zip(self.lower_m, self.upper_m, strict=True)):
            raise ConfigError("lower_m", f"must be < upper_m per axis, got {self.lower_m} vs {self.upper_m}")
        if self.max_radius_m and self.max_radius_m <= self.min_radius_m:
            raise ConfigError("max_radius_m", "must be > min_radius_m (or 0 = no limit)")


@dataclass
class SyntheticSection:
    """``[goal_tracker.synthetic]``: the synthetic camera (astronaut face on a known path)."""

    fps: float = spec(30.0, "frame rate, Hz (frame k is the scene at t = k / fps)", gt=0.0, le=1000.0)
    clock: str = spec(
        "wall",
        "wall: pace with the wall clock; arm: frame times from the arm's "
        "sim time (<prefix>/arm/state), for deterministic lockstep runs",
        choices=("wall", "arm"),
    )
    frames: int = spec(0, "stop after this many frames (0 = endless)", ge=0)
    centre_m: list[float] = field(
        default_factory=lambda: [0.0, 0.0, 0.9], metadata=meta("path centre, camera frame, m")
    )
    amplitude_m: list[float] = field(
        default_factory=lambda: [0.15, 0.06, 0.15], metadata=meta("path amplitude per axis, m")
    )
    frequency_hz: list[float] = field(
        default_factory=lambda: [0.10, 0.13, 0.07], metadata=meta("path frequency per axis, Hz")
    )
    phase_rad: list[float] = field(
        default_factory=lambda: [0.0, 0.5, 1.0], metadata=meta("path phase per axis, rad")
    )
    face_width_m: float = spec(0.16, "physical width of the synthetic face box, m", gt=0.0)
    hidden_s: list[list[float]] = field(
        default_factory=list, metadata=meta("time windows [[t0, t1], ...] (s) the face is hidden")
    )
    noise_sigma: float = spec(2.0, "sensor noise, grey levels", ge=0.0)
    seed: int = spec(0, "background / noise seed", ge=0)

    def validate(self) -> None:
        """Vector lengths, path in front of the camera, windows ordered."""
        for name in ("centre_m", "amplitude_m", "frequency_hz", "phase_rad"):
            _vec3(name, getattr(self, name))
        if self.centre_m[2] - abs(self.amplitude_m[2]) <= 0.1:
            raise ConfigError("centre_m", "the path must stay > 0.1 m in front of the camera")
        for i, w in enumerate(self.hidden_s):
            if len(w) != 2 or not w[0] < w[1]:
                raise ConfigError(f"hidden_s[{i}]", f"expected [t0, t1] with t0 < t1, got {w}")


@dataclass
class GoalTrackerSection:
    """``[goal_tracker]``."""

    goal_name: str = spec("person", "goal published on <prefix>/goals/<goal_name>", min_len=1)
    camera: CameraSection = field(default_factory=CameraSection)
    mount: MountSection = field(default_factory=MountSection)
    face: FaceSection = field(default_factory=FaceSection)
    detector: DetectorSection = field(default_factory=DetectorSection)
    filter: FilterSection = field(default_factory=FilterSection)
    workspace: WorkspaceSection = field(default_factory=WorkspaceSection)
    synthetic: SyntheticSection = field(default_factory=SyntheticSection)

    def validate(self) -> None:
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


@dataclass
class TrackerConfig(ServiceConfig):
    """Goal tracker / synthetic camera service configuration."""

    goal_tracker: GoalTrackerSection = field(default_factory=GoalTrackerSection)


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
        intr, sec.face.width_m, mount, tuple(sec.face.offset_m), tuple(sec.filter.pixel_sigma)
    )


def build_tracker(sec: GoalTrackerSection) -> GoalTracker:
    """The pure :class:`~services.goal_tracker.tracker.GoalTracker` of a config.

    Raises ``FileNotFoundError`` when a configured model file is missing."""
    from services.goal_tracker.detectors import DetectionPipeline, PipelineParams, make_detector
    from services.goal_tracker.kalman import KalmanParams
    from services.goal_tracker.selection import TargetSelector
    from services.goal_tracker.tracker import GoalTracker
    from services.goal_tracker.workspace import Workspace

    d = sec.detector
    if d.kind == "haar":
        detector = make_detector(
            "haar",
            d.model_path,
            scale_factor=d.scale_factor,
            fine_scale_factor=d.fine_scale_factor,
            min_neighbors=d.min_neighbors,
        )
    else:
        detector = make_detector("yunet", d.model_path, score_threshold=d.score_threshold)
    pipeline = DetectionPipeline(
        detector,
        PipelineParams(
            detect_width=d.detect_width,
            full_every=d.full_every,
            min_face_px=d.min_face_px,
            roi_margin=d.roi_margin,
            roi_max_face_px=d.roi_max_face_px,
        ),
    )
    f = sec.filter
    kalman = KalmanParams(
        f.accel_psd,
        f.initial_velocity_sigma,
        f.gate_probability,
        f.max_consecutive_rejections,
        f.lost_timeout_s,
    )
    w = sec.workspace
    workspace = Workspace(
        tuple(w.lower_m),
        tuple(w.upper_m),
        tuple(w.centre_m),
        w.min_radius_m,
        w.max_radius_m if w.max_radius_m > 0 else math.inf,
    )
    return GoalTracker(build_geometry(sec), pipeline, kalman, workspace, TargetSelector(min_hits=f.min_hits))


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
