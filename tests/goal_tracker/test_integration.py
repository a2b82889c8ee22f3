"""The tracker as real processes on loopback: synthetic camera -> tracker -> MCAP, and a replay of
the recorded frames through a second tracker giving the same goals."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.bus.config import load_config
from services.bus.log import read_log
from services.bus.messages import CompressedImage, FaceDetections, Goal, Keys, decode
from services.goal_tracker.config import TrackerConfig, build_geometry, build_synthetic_camera

from .gt_procs import Procs, alive, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

FRAMES = 75
# The recorders run with --no-history: with late-joiner history on, the recorder's advanced
# subscriber drops samples of one session that arrive out of timestamp order (priorities can
# reorder them), which is a recorder matter, not the tracker's.
TRACK = "services.goal_tracker.cli"
BUS = "services.bus.cli"


class GoalCounter:
    """Counts the frame goals (frame_stamp_ns != 0) arriving on a goal key."""

    def __init__(self, session: object, key: str) -> None:
        self.count = 0
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on)  # type: ignore[attr-defined]

    def _on(self, sample: object) -> None:
        msg = decode(sample.payload.to_bytes(), str(sample.encoding), Goal)  # type: ignore[attr-defined]
        if msg.frame_stamp_ns:
            with self._lock:
                self.count += 1


def goals_by_frame(path: Path, key: str) -> dict[int, Goal]:
    return {m.frame_stamp_ns: m for _, m, _ in read_log(path, topics=[key]) if m.frame_stamp_ns}


def record_and_track(bus: Procs, session: object, prefix: str, out: Path) -> tuple:
    """Start a recorder of ``<prefix>/**`` and a topic-fed tracker under ``prefix``; wait until
    both are alive. Returns (recorder, tracker, goal counter)."""
    keys = Keys(prefix)
    recorder = bus.start(
        f"recorder-{prefix}", BUS, "record", "--no-history", "-o", str(out), *bus.bus_args(prefix)
    )
    tracker = bus.start(f"tracker-{prefix}", TRACK, "track", "--source", "topic", *bus.bus_args(prefix))
    counter = GoalCounter(session, keys.goal("person").key)
    for name, proc in (("recorder", recorder), ("goal_tracker", tracker)):

        def up(name: str = name, proc=proc) -> bool:
            if proc.poll() is not None:
                pytest.fail(f"{name} exited early:\n{bus.log(proc)}")
            return alive(session, keys.liveliness(name).key)

        wait_until(up, 30.0, f"{prefix}/{name} liveliness")
    return recorder, tracker, counter


def test_recorded_frames_replayed_through_the_tracker_give_the_same_goals(
    bus: Procs, session: object, tmp_path: Path
) -> None:
    live, replayed = tmp_path / "live.mcap", tmp_path / "replayed.mcap"
    keys, rkeys = Keys("psm"), Keys("replay")

    # 1. live: synthetic camera -> tracker A, everything recorded
    rec_a, trk_a, count_a = record_and_track(bus, session, "psm", live)
    cam = bus.start("camera", TRACK, "camera", "synth", "--max-frames", str(FRAMES), *bus.bus_args("psm"))
    wait_until(lambda: cam.poll() is not None, 40.0, "the camera to finish")
    assert cam.returncode == 0, bus.log(cam)
    wait_until(lambda: count_a.count >= FRAMES, 30.0, f"{FRAMES} goals from tracker A")
    assert bus.stop(trk_a) == 0, bus.log(trk_a)
    assert bus.stop(rec_a) == 0, bus.log(rec_a)

    images = [m for _, m, _ in read_log(live, topics=[keys.camera_image("cam0").key])]
    assert len(images) == FRAMES and all(isinstance(m, CompressedImage) for m in images)
    assert images[0].format == "jpeg"
    faces = [m for _, m, _ in read_log(live, topics=[keys.vision_faces.key])]
    assert len(faces) == FRAMES and all(isinstance(m, FaceDetections) for m in faces)
    assert sum(f.target_index >= 0 for f in faces) >= FRAMES - 2
    # The same boxes for Foxglove's Image panel, one message per analysed frame at its stamp.
    notes = {stamp: m for _, m, stamp in read_log(live, topics=[keys.camera_annotations("cam0").key])}
    assert sorted(notes) == sorted(f.frame_stamp_ns for f in faces)
    assert all(len(notes[f.frame_stamp_ns].points) == len(f.boxes) for f in faces)
    goals_a = goals_by_frame(live, keys.goal("person").key)
    assert len(goals_a) == FRAMES

    # end-to-end accuracy through JPEG and the bus: frame k shows the path at t = k / fps
    sec = load_config(TrackerConfig, env={}).goal_tracker
    geo, synth = build_geometry(sec), build_synthetic_camera(sec)
    t0 = min(goals_a)
    errs = []
    for stamp, g in goals_a.items():
        if g.valid:
            t = (stamp - t0) * 1e-9
            truth = geo.camera_to_base.apply(synth.truth(t)[0].position_cam + np.asarray(sec.face.offset_m))
            errs.append(np.array([g.position.x, g.position.y, g.position.z]) - truth)
    assert len(errs) >= FRAMES - 2
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    assert rms[0] < 0.025 and rms[1] < 0.010 and rms[2] < 0.010, rms  # 75 frames, JPEG q80

    # 2. replay: the recorded frames only, moved to another prefix, through tracker B
    rec_b, trk_b, count_b = record_and_track(bus, session, "replay", replayed)
    rep = bus.start(
        "replayer",
        BUS,
        "replay",
        str(live),
        "--topics",
        keys.camera_image("cam0").key,
        "--remap-prefix",
        "psm=replay",
        *bus.bus_args("psm"),
    )
    wait_until(lambda: rep.poll() is not None, 40.0, "the replay to finish")
    assert rep.returncode == 0, bus.log(rep)
    wait_until(lambda: count_b.count >= FRAMES, 30.0, f"{FRAMES} goals from tracker B")
    assert bus.stop(trk_b) == 0, bus.log(trk_b)
    assert bus.stop(rec_b) == 0, bus.log(rec_b)

    goals_b = goals_by_frame(replayed, rkeys.goal("person").key)
    assert sorted(goals_b) == sorted(goals_a)
    for stamp, a in goals_a.items():
        b = goals_b[stamp]
        assert (a.valid, a.invalid_reason) == (b.valid, b.invalid_reason)
        assert (a.position.x, a.position.y, a.position.z) == (b.position.x, b.position.y, b.position.z)
        assert list(a.covariance) == list(b.covariance)


def test_builtin_synthetic_source_publishes_goals_faces_and_throttled_images(
    bus: Procs, session: object, tmp_path: Path
) -> None:
    out = tmp_path / "run.mcap"
    keys = Keys("psm")
    rec = bus.start("recorder", BUS, "record", "--no-history", "-o", str(out), *bus.bus_args())
    wait_until(lambda: alive(session, keys.liveliness("recorder").key), 30.0, "recorder")
    trk = bus.start(
        "tracker",
        TRACK,
        "track",
        "--max-frames",
        "45",
        "--set",
        "goal_tracker.camera.image_rate_hz=10",
        *bus.bus_args(),
    )
    wait_until(lambda: trk.poll() is not None, 40.0, "the tracker to finish 45 frames")
    assert trk.returncode == 0, bus.log(trk)
    assert bus.stop(rec) == 0, bus.log(rec)

    goals = [m for _, m, _ in read_log(out, topics=[keys.goal("person").key])]
    assert len(goals) == 45
    assert sum(g.valid for g in goals) >= 43
    assert all(g.source == "goal_tracker" and g.frame_id == "base" for g in goals)
    assert all(len(g.covariance) == 9 for g in goals if g.valid)
    assert not goals[0].valid and goals[0].invalid_reason  # first frame: face not confirmed yet
    images = [m for _, m, _ in read_log(out, topics=[keys.camera_image("cam0").key])]
    # <= 10 Hz of frame time (first frame included): 45 frames at 30 fps span 1.5 s -> 15
    # images; a source that fell behind dropped frames, so the span can be longer.
    span_s = (goals[-1].stamp_ns - goals[0].stamp_ns) * 1e-9
    assert span_s >= 44 / 30 - 1e-6
    assert 0.6 * span_s / 0.1 <= len(images) - 1 <= span_s / 0.1 + 1e-6
    stamps = [m.timestamp.seconds * 10**9 + m.timestamp.nanos for m in images]
    assert min(np.diff(stamps)) >= 100_000_000 - 1
    assert len(list(read_log(out, topics=[keys.vision_faces.key]))) == 45
    assert len(list(read_log(out, topics=[keys.goal_pose("person").key]))) == sum(g.valid for g in goals)


def test_unopenable_camera_is_one_error_line_and_exit_2(bus: Procs, tmp_path: Path) -> None:
    proc = bus.start(
        "tracker", TRACK, "track", "--source", "file", "--uri", str(tmp_path / "missing.mp4"), *bus.bus_args()
    )
    wait_until(lambda: proc.poll() is not None, 30.0, "the tracker to exit")
    assert proc.returncode == 2
    lines = [ln for ln in bus.log(proc).splitlines() if ln.strip()]
    # the command path as typed: ``python -m services.goal_tracker.cli track`` (dispatch)
    assert len(lines) == 1 and lines[0].startswith(f"python -m {TRACK} track: error: cannot open file"), lines


def test_synthetic_camera_takes_frame_times_from_the_arm_clock(bus: Procs, session: object) -> None:
    """``psm camera synth --clock arm``: frame k is published once the arm's sim time reaches
    k / fps and is stamped exactly k / fps, whatever the wall clock does."""
    import zenoh

    from services.bus.messages import ArmState, encode

    keys = Keys("psm")
    got: list[int] = []
    lock = threading.Lock()

    def on_image(sample: object) -> None:
        msg = decode(sample.payload.to_bytes(), str(sample.encoding), CompressedImage)  # type: ignore[attr-defined]
        with lock:
            got.append(msg.timestamp.seconds * 10**9 + msg.timestamp.nanos)

    sub = session.declare_subscriber(keys.camera_image("cam0").key, on_image)  # type: ignore[attr-defined]
    cam = bus.start(
        "camera", TRACK, "camera", "synth", "--clock", "arm", "--max-frames", "5", *bus.bus_args()
    )
    wait_until(lambda: alive(session, keys.liveliness("camera_synth").key), 30.0, "camera liveliness")
    pub = session.declare_publisher(keys.arm_state.key)  # type: ignore[attr-defined]
    time.sleep(0.5)  # nothing is published before the first arm state
    assert got == []
    for tick in range(16):  # sim time 0 .. 150 ms in 10 ms steps, irregular wall pacing
        payload, encoding = encode(
            ArmState(stamp_ns=tick * 10_000_000, tick=tick, sim_time_ns=tick * 10_000_000, dt_s=0.01)
        )
        pub.put(payload, encoding=zenoh.Encoding(encoding))
        time.sleep(0.02 if tick % 3 else 0.1)
    wait_until(lambda: cam.poll() is not None, 20.0, "the camera to stop after 5 frames")
    assert cam.returncode == 0, bus.log(cam)
    wait_until(lambda: len(got) >= 5, 5.0, "5 frames")
    sub.undeclare()
    assert got == [0, 33_333_333, 66_666_667, 100_000_000, 133_333_333]


def test_camera_stream_publishes_a_video_file_for_a_tracker_elsewhere(
    bus: Procs, session: object, tmp_path: Path
) -> None:
    """``psm camera stream --source file``: every frame of the file is published as JPEG on the
    camera topic (the path of a real camera to a tracker on another host); the file's end stops
    it cleanly, and a source that is not a camera is one error line."""
    import cv2

    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    for i in range(12):
        writer.write(np.full((240, 320, 3), 10 * i, np.uint8))
    writer.release()
    keys = Keys("psm")
    sizes: list[tuple[int, int]] = []
    lock = threading.Lock()

    def on_image(sample: object) -> None:
        msg = decode(sample.payload.to_bytes(), str(sample.encoding), CompressedImage)  # type: ignore[attr-defined]
        img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
        with lock:
            sizes.append(img.shape[:2])

    sub = session.declare_subscriber(keys.camera_image("cam0").key, on_image)  # type: ignore[attr-defined]
    cam = bus.start(
        "camera", TRACK, "camera", "stream", "--source", "file", "--uri", str(video), *bus.bus_args()
    )
    wait_until(lambda: cam.poll() is not None, 30.0, "the stream to end with the file")
    assert cam.returncode == 0, bus.log(cam)
    assert "source ended" in bus.log(cam)
    wait_until(lambda: len(sizes) >= 12, 5.0, "12 frames")
    sub.undeclare()
    assert sizes == [(240, 320)] * 12

    bad = bus.start("camera-bad", TRACK, "camera", "stream", "--set", "goal_tracker.camera.source=topic",
                    *bus.bus_args())
    wait_until(lambda: bad.poll() is not None, 30.0, "the bad stream to exit")
    assert bad.returncode == 2
    lines = [ln for ln in bus.log(bad).splitlines() if ln.strip()]
    assert len(lines) == 1 and "goal_tracker.camera.source" in lines[0], lines
