"""``psm track`` (the goal tracker), ``psm camera synth`` (the synthetic camera) and ``psm camera
stream`` (a real camera published for a tracker on another host).

All take the common bus flags (``--config``, ``--prefix``, ``--connect``, ``--set``…) and read
the ``[goal_tracker]`` tables of the config; source flags are shortcuts for
``--set goal_tracker.camera.*``. Errors reach :func:`services.cli.dispatch` (one line, exit 2).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

__all__ = ["register"]


def _source_overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if getattr(args, "source", None):
        out["goal_tracker.camera.source"] = args.source
    if getattr(args, "device", None) is not None:
        out["goal_tracker.camera.source"] = out.get("goal_tracker.camera.source", "device")
        out["goal_tracker.camera.device"] = args.device
    if getattr(args, "uri", None):
        out["goal_tracker.camera.uri"] = args.uri
    if getattr(args, "camera_id", None):
        out["goal_tracker.camera.camera_id"] = args.camera_id
    if getattr(args, "goal_name", None):
        out["goal_tracker.goal_name"] = args.goal_name
    if getattr(args, "clock", None):
        out["goal_tracker.synthetic.clock"] = args.clock
    return out


def _cmd_track(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.goal_tracker.config import TrackerConfig

    cfg = config_from_args(TrackerConfig, args, _source_overrides(args))
    from services.goal_tracker.service import main

    return main(cfg, max_frames=args.max_frames)


def _cmd_camera_synth(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.goal_tracker.config import TrackerConfig

    cfg = config_from_args(TrackerConfig, args, _source_overrides(args))
    from services.goal_tracker.service import camera_main

    return camera_main(cfg, max_frames=args.max_frames)


def _cmd_camera_stream(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.goal_tracker.config import TrackerConfig

    cfg = config_from_args(TrackerConfig, args, _source_overrides(args))
    from services.goal_tracker.service import camera_main

    return camera_main(cfg, max_frames=args.max_frames, stream=True)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from services.goal_tracker.calibration import calibrate_from_images

    result = calibrate_from_images(args.images, (args.cols, args.rows), args.square_m)
    print(result.as_toml())
    return 0


def _cmd_face_width(args: argparse.Namespace) -> int:
    import threading
    import time

    from services.bus.config import config_from_args
    from services.goal_tracker.calibration import CalibrationError, face_width_from_frames
    from services.goal_tracker.config import TrackerConfig, build_tracker
    from services.goal_tracker.service import open_capture
    from services.goal_tracker.sources import SourceEndedError

    overrides = _source_overrides(args)
    overrides["goal_tracker.synthetic.clock"] = "wall"  # no bus here: the synthetic face on its own
    cfg = config_from_args(TrackerConfig, args, overrides)
    sec = cfg.goal_tracker
    if args.frames < 1:
        raise CalibrationError(f"--frames must be >= 1, got {args.frames}")
    stop = threading.Event()
    source = open_capture(sec, stop)
    if source is None:
        raise CalibrationError(
            f"face-width reads a camera itself: goal_tracker.camera.source must be synthetic, "
            f"device, file or url, not {sec.camera.source}"
        )
    tracker = build_tracker(sec)

    def frames() -> Any:
        deadline = time.monotonic() + args.timeout_s
        n = 0
        while n < args.frames and time.monotonic() < deadline:
            try:
                frame = source.read(min(1.0, max(0.0, deadline - time.monotonic())))
            except SourceEndedError:
                return
            if frame is not None:
                n += 1
                yield frame.image, frame.stamp_ns

    try:
        result = face_width_from_frames(frames(), tracker, sec.camera.fx, args.distance)
    finally:
        stop.set()
        source.close()
    print(result.as_toml(), end="")
    return 0


def register(subparsers: Any) -> None:
    """Add ``track`` and ``camera {synth, stream, calibrate, face-width}`` to the ``psm`` command
    line."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "track",
        help="goal tracker: camera feed -> face detections -> 3-D goal",
        description="Detect the person's face in a camera feed and publish the goal "
        "(<prefix>/goals/<name>), the detections (<prefix>/vision/faces) and throttled JPEG "
        "frames (<prefix>/camera/<id>/image).",
    )
    p.add_argument(
        "--source",
        choices=("synthetic", "device", "file", "url", "topic"),
        help="frame source (goal_tracker.camera.source)",
    )
    p.add_argument("--device", type=int, help="camera device index (implies --source device)")
    p.add_argument("--uri", help="video file or stream URL (source file / url)")
    p.add_argument("--camera-id", help="camera id of the image topic")
    p.add_argument("--goal-name", help="goal name: <prefix>/goals/<name>")
    p.add_argument("--clock", choices=("wall", "arm"), help="synthetic source clock")
    p.add_argument("--max-frames", type=int, default=0, help="stop after N frames (0 = never)")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_track)

    cam = subparsers.add_parser(
        "camera", help="camera tools: synthetic camera, streaming, calibration, face width"
    )
    sub = cam.add_subparsers(dest="camera_command", metavar="CAMERA_COMMAND", required=True)
    s = sub.add_parser(
        "synth",
        help="publish the synthetic camera (astronaut face on a known 3-D path)",
        description="Publish JPEG frames of the synthetic camera on <prefix>/camera/<id>/image; "
        "with --clock arm the frame times follow the arm's sim time.",
    )
    s.add_argument("--camera-id", help="camera id of the image topic")
    s.add_argument("--clock", choices=("wall", "arm"), help="frame clock")
    s.add_argument("--max-frames", type=int, default=0, help="stop after N frames (0 = never)")
    add_config_arguments(s)
    s.set_defaults(func=_cmd_camera_synth)

    st = sub.add_parser(
        "stream",
        help="publish a real camera (device, file or URL) for a tracker elsewhere",
        description="Publish the JPEG frames of a camera device, video file or stream URL on "
        "<prefix>/camera/<id>/image, for a goal tracker with --source topic (on this host or "
        "another). A dropped stream is reopened with backoff.",
    )
    st.add_argument("--source", choices=("device", "file", "url"),
                    help="frame source (goal_tracker.camera.source)")
    st.add_argument("--device", type=int, help="camera device index (implies --source device)")
    st.add_argument("--uri", help="video file or stream URL (source file / url)")
    st.add_argument("--camera-id", help="camera id of the image topic")
    st.add_argument("--max-frames", type=int, default=0, help="stop after N frames (0 = never)")
    add_config_arguments(st)
    st.set_defaults(func=_cmd_camera_stream)

    c = sub.add_parser(
        "calibrate",
        help="pinhole intrinsics from chessboard images",
        description="Estimate fx, fy, cx, cy from images of a chessboard and print them as a "
        "[goal_tracker.camera] TOML table.",
    )
    c.add_argument("images", nargs="+", help="image files showing the chessboard")
    c.add_argument("--cols", type=int, default=9, help="inner corners per row")
    c.add_argument("--rows", type=int, default=6, help="inner corners per column")
    c.add_argument("--square-m", type=float, default=0.025, help="square size, m")
    c.set_defaults(func=_cmd_calibrate)

    fw = sub.add_parser(
        "face-width",
        help="the detector's nominal face width from a face at a known distance",
        description="Run the configured tracker on a face held still, facing the camera, at "
        "--distance metres along its optical axis and print [goal_tracker.face] width_m: the "
        "width for which the tracker's depth reads that distance with this detector (each "
        "cascade and ROI setting frames a face differently). The synthetic face at a known "
        "depth: --source synthetic --set goal_tracker.synthetic.amplitude_m=[0,0,0] --set "
        "goal_tracker.synthetic.centre_m=[0,0,0.5] --distance 0.5.",
    )
    fw.add_argument("--distance", type=float, required=True,
                    help="the face's distance along the camera's optical axis, m")
    fw.add_argument("--frames", type=int, default=90, help="frames to read (default 90)")
    fw.add_argument("--timeout-s", type=float, default=30.0,
                    help="stop reading after this long, s (default 30)")
    fw.add_argument("--source", choices=("synthetic", "device", "file", "url"),
                    help="frame source (goal_tracker.camera.source)")
    fw.add_argument("--device", type=int, help="camera device index (implies --source device)")
    fw.add_argument("--uri", help="video file or stream URL (source file / url)")
    add_config_arguments(fw)
    fw.set_defaults(func=_cmd_face_width)


def main(argv: list[str] | None = None) -> int:
    """Run these commands directly (``python -m services.goal_tracker.cli track ...``)."""
    from services.cli import module_main

    return module_main(register, "python -m services.goal_tracker.cli", argv)

if __name__ == "__main__":
    sys.exit(main())
