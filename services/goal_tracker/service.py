"""The goal-tracker service (``psm track``) and the synthetic camera (``psm camera synth``).

Tracker inputs: frames from the configured source (synthetic, device, file, url, or the
``<prefix>/camera/<id>/image`` topic). Outputs, per analysed frame:

* ``<prefix>/vision/faces`` — :class:`FaceDetections` (pixel boxes, confidence, target index);
* ``<prefix>/camera/<id>/annotations`` — foxglove ``ImageAnnotations``: the same boxes drawn on
  the camera's images by Foxglove's Image panel (stamped with the frame's stamp);
* ``<prefix>/goals/<goal_name>`` — :class:`Goal` (position, covariance, valid, invalid_reason,
  source, ``frame_stamp_ns``), and ``<prefix>/viz/goals/<goal_name>`` (foxglove PoseInFrame) when
  valid;
* ``<prefix>/camera/<id>/image`` — JPEG foxglove CompressedImage, at most ``image_rate_hz`` (frame
  time), unless the frames came from that topic already.

Liveliness token and status counters come from :class:`services.bus.runtime.Service`.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation

from services.bus.config import ConfigError
from services.bus.messages import (
    CompressedImage,
    FaceBox,
    FaceDetections,
    Goal,
    ImageAnnotations,
    PoseInFrame,
    Vec3,
)
from services.bus.runtime import Service, ServiceApp
from services.goal_tracker.config import (
    GoalTrackerSection,
    TrackerConfig,
    build_synthetic_camera,
    build_tracker,
)
from services.goal_tracker.sources import (
    CameraOpenError,
    Frame,
    FrameSource,
    QueueSource,
    SourceEndedError,
    SyntheticSource,
    VideoCaptureSource,
)
from services.goal_tracker.tracker import TrackOutput
from services.threads import limit_blas_threads, limit_opencv_threads

SERVICE_NAME = "goal_tracker"
CAMERA_SERVICE_NAME = "camera_synth"
#: Lockstep, frames on the arm's clock: the synthetic camera sends its last frame again after
#: this long [s, wall clock] without a new one (the arm's time standing still).
RESEND_S = 0.5
STREAM_CAMERA_SERVICE_NAME = "camera"


def _timestamp(msg_ts: Any, stamp_ns: int) -> None:
    msg_ts.seconds = stamp_ns // 1_000_000_000
    msg_ts.nanos = stamp_ns % 1_000_000_000


def jpeg_image(image: np.ndarray, stamp_ns: int, frame_id: str, quality: int) -> CompressedImage:
    """A foxglove ``CompressedImage`` (JPEG) of an H×W×3 BGR frame."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    msg = CompressedImage(frame_id=frame_id, data=buf.tobytes(), format="jpeg")
    _timestamp(msg.timestamp, stamp_ns)
    return msg


#: Topic source: this many images in a row stamped before the last one are a camera whose clock
#: restarted (e.g. an arm restarted in lockstep), followed from then on.
_CLOCK_RESTART_FRAMES = 30


def image_stamp_ns(msg: CompressedImage) -> int:
    """The stamp of a ``CompressedImage`` in ns."""
    return int(msg.timestamp.seconds) * 1_000_000_000 + int(msg.timestamp.nanos)


def faces_message(out: TrackOutput, seq: int, camera_id: str, size: tuple[int, int]) -> FaceDetections:
    """The :class:`FaceDetections` of one tracked frame (``size`` = (width, height) px)."""
    msg = FaceDetections(
        stamp_ns=out.stamp_ns,
        seq=seq,
        frame_stamp_ns=out.stamp_ns,
        camera_id=camera_id,
        image_width=size[0],
        image_height=size[1],
        target_index=out.target_index,
    )
    for d in out.detections:
        msg.boxes.append(
            FaceBox(
                x_px=d.x,
                y_px=d.y,
                w_px=d.w,
                h_px=d.h,
                confidence=float(min(1.0, max(0.0, d.confidence))),
            )
        )
    return msg


#: Face box outlines on the image (r, g, b, a): the tracked target, the other faces.
TARGET_RGBA = (0.1, 0.9, 0.2, 1.0)
OTHER_RGBA = (1.0, 0.8, 0.1, 1.0)


def annotations_message(out: TrackOutput) -> ImageAnnotations:
    """Foxglove ``ImageAnnotations`` of one tracked frame: each face box as a closed outline
    (pixel coordinates, the tracked target in :data:`TARGET_RGBA`) with its confidence as text,
    stamped with the frame's stamp so the Image panel draws it on that frame."""
    msg = ImageAnnotations()
    sec, nanos = divmod(out.stamp_ns, 1_000_000_000)
    msg.timestamp.seconds, msg.timestamp.nanos = sec, nanos
    for i, d in enumerate(out.detections):
        rgba = TARGET_RGBA if i == out.target_index else OTHER_RGBA
        box = msg.points.add()
        box.timestamp.CopyFrom(msg.timestamp)
        box.type = PointsAnnotation.LINE_LOOP
        for x, y in ((d.x, d.y), (d.x + d.w, d.y), (d.x + d.w, d.y + d.h), (d.x, d.y + d.h)):
            pt = box.points.add()
            pt.x, pt.y = float(x), float(y)
        c = box.outline_color
        c.r, c.g, c.b, c.a = rgba
        box.thickness = 2.0
        text = msg.texts.add()
        text.timestamp.CopyFrom(msg.timestamp)
        text.position.x, text.position.y = float(d.x), float(d.y) - 4.0
        text.text = ("target " if i == out.target_index else "") + f"{d.confidence:.2f}"
        text.font_size = 14.0
        tc = text.text_color
        tc.r, tc.g, tc.b, tc.a = rgba
        bg = text.background_color
        bg.r, bg.g, bg.b, bg.a = 0.0, 0.0, 0.0, 0.6
    return msg


def goal_message(out: TrackOutput, seq: int, name: str, frame_id: str) -> Goal:
    """The :class:`Goal` of one tracked frame. Without an estimate the position is (0, 0, 0)
    and the covariance empty; ``valid`` is then always false."""
    msg = Goal(
        stamp_ns=out.stamp_ns,
        seq=seq,
        name=name,
        valid=bool(out.valid),
        invalid_reason=out.reason,
        source=SERVICE_NAME,
        frame_stamp_ns=out.stamp_ns,
        frame_id=frame_id,
    )
    if np.all(np.isfinite(out.position)):
        msg.position.CopyFrom(
            Vec3(x=float(out.position[0]), y=float(out.position[1]), z=float(out.position[2]))
        )
        msg.covariance.extend(float(v) for v in out.covariance.reshape(-1))
    return msg


def pose_message(out: TrackOutput, frame_id: str) -> PoseInFrame:
    """A foxglove ``PoseInFrame`` at the goal (identity orientation) for the 3-D panel."""
    msg = PoseInFrame(frame_id=frame_id)
    _timestamp(msg.timestamp, out.stamp_ns)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in out.position)
    msg.pose.orientation.w = 1.0
    return msg


def open_capture(sec: GoalTrackerSection, stop: threading.Event) -> FrameSource | None:
    """The non-bus frame source of a config (None for ``source = "topic"``).

    Raises :class:`CameraOpenError` (one line) when the device/file/URL cannot be opened."""
    cam = sec.camera
    if cam.source == "synthetic":
        if sec.synthetic.clock == "arm":
            return None  # needs the bus: built by the service once the session is open
        return SyntheticSource(
            build_synthetic_camera(sec),
            sec.synthetic.fps,
            max_frames=sec.synthetic.frames,
            stop=stop,
        )
    if cam.source in ("device", "file", "url"):
        target: int | str = cam.device if cam.source == "device" else cam.uri
        return VideoCaptureSource(
            target,
            cam.source,
            loop=cam.loop,
            realtime=cam.realtime,
            reconnect_initial_s=cam.reconnect_initial_s,
            reconnect_max_s=cam.reconnect_max_s,
            give_up_s=cam.reconnect_give_up_s,
            stop=stop,
        )
    return None


#: The sim clock's largest accepted gap between two states it looks at [s of the arm's time]:
#: the camera looks about once a frame in realtime, every millisecond of wall time in lockstep.
MAX_SAMPLED_GAP_S = 1.0


class _SimClock:
    """Latest sim time from the arm's state (``<prefix>/arm/state``), like ROS ``/clock``.

    The camera samples the 500 Hz stream when it asks for the time (``"latest"`` delivery: the
    states it does not look at cost it nothing). Only states that continue the arm's stream move
    the clock (:class:`~services.robot.protocol.StateStream`, with a tick gap of up to
    :data:`MAX_SAMPLED_GAP_S` of the arm's time between two looks): a stale, replayed or forged
    state with a stamp far ahead would otherwise freeze the frames until the real clock caught
    up; those are rejected by reason on the status."""

    def __init__(self, svc: Any) -> None:
        self.now_ns: int | None = None
        self._svc = svc
        self._stream: Any = None  # a StateStream, made at the first state (it needs dt)
        self._sub = svc.subscribe(svc.keys.arm_state, self.on_state, delivery="latest")

    def on_state(self, msg: Any, key: str) -> None:
        dt = float(msg.dt_s)
        if not (math.isfinite(dt) and dt > 0.0):
            self._svc.record_rejection(key, f"tick {msg.tick}: dt_s {dt} is not a positive number", "dt")
            return
        if self._stream is None:
            from services.robot.protocol import MAX_TICK_GAP, StateStream

            self._stream = StateStream(max_tick_gap=max(MAX_TICK_GAP, math.ceil(MAX_SAMPLED_GAP_S / dt)))
        verdict, why = self._stream.check(int(msg.tick), int(msg.stamp_ns), dt)
        if verdict in ("tick", "stamp"):
            self._svc.record_rejection(key, why, verdict)
            return
        self.now_ns = int(msg.sim_time_ns or msg.stamp_ns)

    def __call__(self) -> int | None:
        self._sub.take()
        return self.now_ns


def _synthetic_on_bus(svc: Any, sec: GoalTrackerSection) -> SyntheticSource:
    return SyntheticSource(
        build_synthetic_camera(sec),
        sec.synthetic.fps,
        sim_clock=_SimClock(svc),
        sim_realtime=svc.config.clock == "realtime",
        max_frames=sec.synthetic.frames,
        stop=svc.stop_event,
    )


def main(config: TrackerConfig, *, max_frames: int = 0) -> int:
    """Run the goal tracker until SIGINT/SIGTERM, the end of a file source, or ``max_frames``
    analysed frames (0 = no limit). Returns the exit code.

    Raises :class:`CameraOpenError` / ``FileNotFoundError`` before joining the bus when the
    source or a model file cannot be opened (the CLI prints them as one line)."""
    from services.bus.runtime import run_service

    return run_service(GoalTrackerService(config, max_frames=max_frames))


class GoalTrackerService(ServiceApp):
    """Camera frames -> face detections -> the person's goal (see the module docstring).

    The detector, the filter and a device, file or URL source are opened before the bus."""

    name = SERVICE_NAME

    def __init__(self, config: TrackerConfig, *, max_frames: int = 0) -> None:
        super().__init__(config)
        self.sec = config.goal_tracker
        self.max_frames = max_frames
        # One frame at a time on this thread: OpenCV's and OpenBLAS's pools would busy-wait
        # between frames (measured: an OpenCV worker at ~70 % of the main thread's CPU).
        limit_opencv_threads(1)
        limit_blas_threads(1)
        self.tracker = build_tracker(self.sec)
        self.source: FrameSource | None = open_capture(self.sec, threading.Event())

    def setup(self, svc: Service) -> None:
        """The bus-fed sources (synthetic on the arm's clock, an image topic) and the
        publishers."""
        sec, cam, keys = self.sec, self.sec.camera, svc.keys
        source = self.source
        if isinstance(source, VideoCaptureSource | SyntheticSource):
            source.stop = svc.stop_event  # SIGTERM also aborts a source's waits
        if source is None and cam.source == "synthetic":
            source = _synthetic_on_bus(svc, sec)
        elif source is None:
            # Haar looks at grey levels only: the JPEG's luma plane is decoded without colour.
            queue_source = QueueSource(
                f"topic {keys.camera_image(cam.camera_id).key}", cam.topic_max_pending,
                grayscale=sec.detector.kind == "haar",
            )

            last = [-1, 0]  # the last image's stamp [ns], images stamped before it in a row

            def on_image(msg: CompressedImage, key: str) -> None:
                # An image stamped before the last one is stale (a replay, a forged stamp) and
                # rejected, unless that many come in a row: the camera's clock restarted.
                stamp = image_stamp_ns(msg)
                if stamp < last[0] and last[1] < _CLOCK_RESTART_FRAMES:
                    last[1] += 1
                    svc.record_rejection(key, f"image stamped {stamp} before the last one {last[0]}", "stamp")
                    return
                try:
                    queue_source.push_jpeg(msg.data, stamp)
                except ValueError as exc:
                    svc.record_rejection(key, str(exc), "image")
                    return
                last[0], last[1] = stamp, 0

            svc.subscribe(keys.camera_image(cam.camera_id), on_image)
            source = queue_source
        self.source = source
        self.faces_pub = svc.publisher(keys.vision_faces)
        self.annotations_pub = svc.publisher(keys.camera_annotations(cam.camera_id))
        self.goal_pub = svc.publisher(keys.goal(sec.goal_name))
        self.pose_pub = svc.publisher(keys.goal_pose(sec.goal_name))
        self.image_pub = None if cam.source == "topic" else svc.publisher(keys.camera_image(cam.camera_id))
        svc.log.info(
            "tracking",
            extra={"source": source.description, "goal": sec.goal_name, "detector": sec.detector.kind},
        )

    def loop(self, svc: Service) -> None:
        assert self.source is not None
        # In lockstep time is the arm's: a camera without frames while the arm waits is not
        # stalled, and a stall declared by the wall clock would make the goals depend on how
        # fast the processes started (the planner's goal_timeout_s, on the arm's clock, still
        # loses a goal whose frames stop).
        stall_s = None if svc.config.clock == "lockstep" else self.sec.camera.stall_timeout_s
        self.exit_code = _loop(svc, self.sec, self.tracker, self.source, self.faces_pub,
                               self.annotations_pub, self.goal_pub, self.pose_pub, self.image_pub,
                               self.max_frames, stall_s)

    def teardown(self, svc: Service) -> None:
        if self.source is not None:
            self.source.close()
        svc.log.info("tracker stats", extra=self.tracker.stats.as_dict())


def _loop(
    svc: Any,
    sec: GoalTrackerSection,
    tracker: Any,
    source: FrameSource,
    faces_pub: Any,
    annotations_pub: Any,
    goal_pub: Any,
    pose_pub: Any,
    image_pub: Any,
    max_frames: int,
    stall_s: float | None,
) -> int:
    """Analyse frames until the stop, the source's end or ``max_frames``; a source without a
    frame for ``stall_s`` [s, wall clock] gets the goal invalid (None: never)."""
    cam = sec.camera
    seq = 0
    last_image_ns: int | None = None
    image_period_ns = round(1e9 / cam.image_rate_hz) if cam.image_rate_hz > 0 else 0
    last_frame_wall = time.monotonic()
    last_stamp = 0
    stalled = False
    frames = 0
    last_log = time.monotonic()
    while not svc.stop_event.is_set():
        try:
            frame = source.read(0.2)
        except SourceEndedError as exc:
            svc.log.info("source ended", extra={"reason": str(exc)})
            return 0
        except CameraOpenError as exc:
            svc.record_error(str(exc))
            _publish_invalid(goal_pub, seq, sec, last_stamp, f"camera failed: {exc}")
            return 2
        now = time.monotonic()
        if frame is None:
            if stall_s is not None and not stalled and now - last_frame_wall > stall_s:
                stalled = True
                _publish_invalid(
                    goal_pub,
                    seq,
                    sec,
                    last_stamp,
                    f"camera stalled: no frame for {stall_s:.1f} s",
                )
                seq += 1
            continue
        last_frame_wall, stalled = now, False
        if frames and frame.stamp_ns == last_stamp:
            continue  # a copy of the frame analysed last (a lockstep camera sending it again)
        try:
            out = _track_frame(tracker, frame)
        except Exception as exc:
            svc.record_error(f"frame {frame.seq} failed: {exc!r}", exc)
            continue
        last_stamp = out.stamp_ns
        h, w = frame.image.shape[:2]
        # Highest priority first (goal, pose: DATA_HIGH; faces: DATA; image: DATA_LOW), so a
        # later, lower-priority sample is never overtaken by an earlier, higher-priority one.
        goal_pub.put(goal_message(out, seq, sec.goal_name, sec.mount.frame_id))
        if out.valid:
            pose_pub.put(pose_message(out, sec.mount.frame_id))
        faces_pub.put(faces_message(out, seq, cam.camera_id, (w, h)))
        annotations_pub.put(annotations_message(out))
        if (
            image_pub is not None
            and image_period_ns
            and (last_image_ns is None or out.stamp_ns - last_image_ns >= image_period_ns)
        ):
            image_pub.put(jpeg_image(frame.image, out.stamp_ns, cam.camera_id, cam.jpeg_quality))
            last_image_ns = out.stamp_ns
        seq += 1
        frames += 1
        if now - last_log > 10.0:
            svc.log.info("tracker stats", extra=tracker.stats.as_dict())
            last_log = now
        if max_frames and frames >= max_frames:
            return 0
    return 0


def _track_frame(tracker: Any, frame: Frame) -> TrackOutput:
    h, w = frame.image.shape[:2]
    tracker.set_image_size(w, h)
    return tracker.process(frame.image, frame.stamp_ns)


def _publish_invalid(goal_pub: Any, seq: int, sec: GoalTrackerSection, stamp_ns: int, reason: str) -> None:
    goal_pub.put(
        Goal(
            stamp_ns=stamp_ns,
            seq=seq,
            name=sec.goal_name,
            valid=False,
            invalid_reason=reason,
            source=SERVICE_NAME,
            frame_stamp_ns=0,
            frame_id=sec.mount.frame_id,
        )
    )


def camera_main(config: TrackerConfig, *, max_frames: int = 0, stream: bool = False) -> int:
    """Run a camera alone: publish JPEG frames on ``<prefix>/camera/<id>/image`` (every frame,
    no throttling) for a goal tracker with ``source = "topic"``, possibly on another host.
    Without ``stream``: the synthetic camera at ``synthetic.fps`` with wall-clock or arm
    sim-clock frame times. With ``stream``: the device, file or URL of
    ``[goal_tracker.camera]`` (wall-clock frame times). Stops at SIGINT/SIGTERM or after
    ``synthetic.frames`` / ``max_frames`` frames."""
    from services.bus.runtime import run_service

    if not stream:
        return run_service(SyntheticCameraService(config, max_frames=max_frames))
    if config.goal_tracker.camera.source not in ("device", "file", "url"):
        raise ConfigError(
            "goal_tracker.camera.source",
            "psm camera stream needs a device, file or url source "
            f"(got {config.goal_tracker.camera.source!r})",
        )
    return run_service(StreamCameraService(config, max_frames=max_frames))


class SyntheticCameraService(ServiceApp):
    """The synthetic camera on the bus (frame times from the wall clock or the arm's)."""

    name = CAMERA_SERVICE_NAME

    def __init__(self, config: TrackerConfig, *, max_frames: int = 0) -> None:
        super().__init__(config)
        self.sec = config.goal_tracker
        self.limit = max_frames or self.sec.synthetic.frames
        self.sent = 0
        self.resent = 0
        self.source: Any = None
        limit_opencv_threads(1)

    def zenoh_extra(self) -> dict[str, Any]:
        """On the arm's clock the session has the clock sampler's fixed id, to which the arm's
        state is sent droppable (:func:`~services.bus.messages.clock_sampler_qos`)."""
        if self.sec.synthetic.clock != "arm":
            return {}
        from services.bus.messages import clock_sampler_zid

        return {"id": clock_sampler_zid(self.config.prefix)}

    def open_source(self, svc: Service) -> Any:
        """The frame source of this camera."""
        sec = self.sec
        if sec.synthetic.clock == "arm":
            return _synthetic_on_bus(svc, sec)
        return SyntheticSource(build_synthetic_camera(sec), sec.synthetic.fps, stop=svc.stop_event)

    def setup(self, svc: Service) -> None:
        cam = self.sec.camera
        self.source = self.open_source(svc)
        self.pub = svc.publisher(svc.keys.camera_image(cam.camera_id))
        svc.log.info(
            "publishing",
            extra={"source": self.source.description, "key": svc.keys.camera_image(cam.camera_id).key},
        )

    def loop(self, svc: Service) -> None:
        cam, source, limit = self.sec.camera, self.source, self.limit
        # Lockstep on the arm's clock: while the arm's time stands still the last frame goes out
        # again every RESEND_S (a tracker that subscribed after it was sent gets it; the tracker
        # analyses a frame once, whatever the copies).
        resend = svc.config.clock == "lockstep" and self.sec.synthetic.clock == "arm"
        last: Any = None
        last_put = 0.0
        while not svc.stop_event.is_set() and not (limit and self.sent >= limit):
            try:
                frame = source.read(0.2)
            except SourceEndedError:
                svc.log.info("source ended", extra={"source": source.description})
                break
            if frame is None:
                if resend and last is not None and time.monotonic() - last_put >= RESEND_S:
                    self.pub.put(last)
                    last_put = time.monotonic()
                    self.resent += 1
                continue
            last = jpeg_image(frame.image, frame.stamp_ns, cam.camera_id, cam.jpeg_quality)
            self.pub.put(last)
            last_put = time.monotonic()
            self.sent += 1

    def teardown(self, svc: Service) -> None:
        dropped = getattr(self.source, "dropped", 0)
        svc.log.info("camera done", extra={"frames": self.sent, "dropped": dropped, "resent": self.resent})


class StreamCameraService(SyntheticCameraService):
    """A real camera on the bus: frames of the device, file or URL of ``[goal_tracker.camera]``
    (``psm camera stream``), so the tracker can run on another host than the camera."""

    name = STREAM_CAMERA_SERVICE_NAME

    def open_source(self, svc: Service) -> Any:
        source = open_capture(self.sec, svc.stop_event)
        assert source is not None  # camera_main checked the source kind
        return source
