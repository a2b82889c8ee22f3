"""Frame sources: VideoCapture (file, reconnect with backoff), synthetic clocks, queue."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest

from services.goal_tracker.detectors import DetectionPipeline, HaarDetector
from services.goal_tracker.selection import iou
from services.goal_tracker.sources import (
    CameraOpenError,
    QueueSource,
    SourceEndedError,
    SyntheticSource,
    VideoCaptureSource,
)
from services.goal_tracker.synthetic import SyntheticCamera


class FakeCapture:
    """Scripted stand-in for cv2.VideoCapture: ``opens`` decides each open attempt, ``reads``
    how many frames a session delivers before the stream drops."""

    def __init__(self, opened: bool, frames: int) -> None:
        self.opened, self.frames = opened, frames

    def isOpened(self) -> bool:  # noqa: N802 -- OpenCV's name
        return self.opened

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self.frames <= 0:
            return False, None
        self.frames -= 1
        return True, np.zeros((48, 64, 3), np.uint8)

    def get(self, _prop: int) -> float:
        return 0.0

    def release(self) -> None:
        self.opened = False


def scripted(attempts: list[tuple[bool, int]]):
    calls: list[object] = []

    def opener(target: object) -> FakeCapture:
        calls.append(target)
        ok, n = attempts[min(len(calls) - 1, len(attempts) - 1)]
        return FakeCapture(ok, n)

    return opener, calls


def test_unopenable_feed_is_one_clear_error() -> None:
    opener, calls = scripted([(False, 0)])
    with pytest.raises(CameraOpenError, match=r"cannot open url 'rtsp://cam/stream'"):
        VideoCaptureSource("rtsp://cam/stream", "url", opener=opener)
    assert len(calls) == 1  # no retry loop on the first open


def test_dropped_stream_reconnects_with_backoff(monkeypatch: pytest.MonkeyPatch) -> None:
    # session 1 delivers 2 frames; two failed reopen attempts; session 2 delivers 3 frames
    opener, calls = scripted([(True, 2), (False, 0), (False, 0), (True, 3)])
    waits: list[float] = []
    stop = threading.Event()
    monkeypatch.setattr(stop, "wait", lambda t: waits.append(t) or False)
    src = VideoCaptureSource(
        0, "device", opener=opener, reconnect_initial_s=0.1, reconnect_max_s=0.3, give_up_s=0, stop=stop
    )
    frames = [src.read() for _ in range(6)]
    got = [f for f in frames if f is not None]
    assert len(got) == 5 and [f.seq for f in got] == [0, 1, 2, 3, 4]
    assert waits == [0.1, 0.2, 0.3]  # exponential backoff, capped
    assert len(calls) == 4 and src.reconnects == 3


def test_stream_down_too_long_gives_up(monkeypatch: pytest.MonkeyPatch) -> None:
    opener, _ = scripted([(True, 1), (False, 0)])
    src = VideoCaptureSource(
        0, "device", opener=opener, reconnect_initial_s=0.01, reconnect_max_s=0.02, give_up_s=0.1
    )
    assert src.read() is not None
    with pytest.raises(CameraOpenError, match="no reconnect within"):
        for _ in range(3):
            src.read()


@pytest.fixture(scope="module")
def video_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, list[np.ndarray]]:
    path = str(tmp_path_factory.mktemp("video") / "synthetic.avi")
    cam = SyntheticCamera()
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
    assert writer.isOpened()
    frames = [cam.render(k / 30) for k in range(12)]
    for f in frames:
        writer.write(f)
    writer.release()
    return path, frames


def test_file_source_reads_all_frames_then_ends(video_file: tuple) -> None:
    path, frames = video_file
    src = VideoCaptureSource(path, "file", realtime=False)
    got = []
    with pytest.raises(SourceEndedError):
        for _ in range(50):
            got.append(src.read())
    assert len(got) == len(frames)
    stamps = [f.stamp_ns for f in got]
    assert np.all(np.diff(stamps) > 0)
    # MJPEG round trip: close to the rendered frame
    assert np.abs(got[3].image.astype(int) - frames[3]).mean() < 4.0


def test_file_source_loops(video_file: tuple) -> None:
    path, frames = video_file
    src = VideoCaptureSource(path, "file", realtime=False, loop=True)
    got = [src.read() for _ in range(2 * len(frames) + 2)]
    assert sum(f is not None for f in got) == 2 * len(frames)  # one None per restart
    stamps = [f.stamp_ns for f in got if f is not None]
    assert np.all(np.diff(stamps) > 0)


def test_missing_file_is_one_clear_error(tmp_path) -> None:
    with pytest.raises(CameraOpenError, match="cannot open file"):
        VideoCaptureSource(str(tmp_path / "none.mp4"), "file")


def test_synthetic_sim_clock_is_deterministic() -> None:
    cam = SyntheticCamera()
    now = {"t": None}
    src = SyntheticSource(cam, 30.0, sim_clock=lambda: now["t"], max_frames=3)
    assert src.read(0.01) is None  # no sim time yet
    now["t"] = 0
    got = [src.read(0.01)]
    for t in (40_000_000, 70_000_000):  # frames 1 (33.3 ms) and 2 (66.7 ms) fall due
        now["t"] = t
        got.append(src.read(0.01))
    assert [f.stamp_ns for f in got] == [0, 33_333_333, 66_666_667]
    np.testing.assert_array_equal(got[1].image, cam.render(1 / 30))
    assert src.dropped == 0
    with pytest.raises(SourceEndedError):
        src.read(0.01)


def test_synthetic_sim_clock_drops_frames_instead_of_lagging() -> None:
    """Sim time ran past several frame times before the camera got to them: the camera shows the
    latest due frame, stamped with its time on the arm's clock, and counts the skipped ones."""
    cam = SyntheticCamera(noise_sigma=0)
    epoch = 1_700_000_000_000_000_000  # a realtime arm's sim time is UNIX time
    now = {"t": epoch}
    src = SyntheticSource(cam, 30.0, sim_clock=lambda: now["t"])
    first = src.read(0.01)
    assert first is not None and first.stamp_ns <= epoch < first.stamp_ns + 33_333_334
    assert src.read(0.01) is None  # the next frame is not due yet
    now["t"] = epoch + 200_000_000  # 200 ms later: 6 frame times passed
    late = src.read(0.01)
    assert late is not None and epoch + 166_666_666 < late.stamp_ns <= epoch + 200_000_000
    assert src.dropped == 5
    # The scene is the one at the frame's time since the first frame.
    scene_s = (late.stamp_ns - first.stamp_ns) * 1e-9
    np.testing.assert_array_equal(late.image, cam.render(scene_s))


def test_synthetic_wall_clock_drops_frames_when_late() -> None:
    src = SyntheticSource(SyntheticCamera(noise_sigma=0), 50.0)
    t0 = time.time_ns()
    a = src.read(1.0)
    time.sleep(0.13)  # the consumer stalls for 6.5 frame periods
    b = src.read(1.0)
    assert a is not None and b is not None
    assert (b.stamp_ns - a.stamp_ns) % 20_000_000 == 0 and b.stamp_ns - a.stamp_ns >= 120_000_000
    assert src.dropped >= 5
    # Stamped with the time it shows on the wall clock: not behind the wall clock by a period.
    assert abs(b.stamp_ns - time.time_ns()) < 40_000_000
    assert abs(a.stamp_ns - t0) < 40_000_000


def test_synthetic_wall_clock_paces_frames() -> None:
    src = SyntheticSource(SyntheticCamera(noise_sigma=0), 50.0)
    got = [src.read(1.0) for _ in range(4)]
    assert [f.seq for f in got] == [0, 1, 2, 3]
    assert np.diff([f.stamp_ns for f in got]).tolist() == [20_000_000] * 3


def test_queue_source_keeps_order_and_rejects_garbage() -> None:
    q = QueueSource("test")
    _, buf = cv2.imencode(".jpg", np.full((8, 8, 3), 100, np.uint8))
    q.push_jpeg(buf.tobytes(), 5)
    q.push_jpeg(buf.tobytes(), 7)
    with pytest.raises(ValueError, match="cannot decode"):
        q.push_jpeg(b"not a jpeg", 9)
    assert [q.read(0.1).stamp_ns, q.read(0.1).stamp_ns] == [5, 7]
    assert q.read(0.01) is None


def test_a_grey_queue_source_decodes_the_luma_plane_a_haar_detector_finds_faces_in() -> None:
    cam = SyntheticCamera(noise_sigma=0)
    _, buf = cv2.imencode(".jpg", cam.render(0.0), [cv2.IMWRITE_JPEG_QUALITY, 90])
    grey, colour = QueueSource("grey", grayscale=True), QueueSource("colour")
    g = grey.push_jpeg(buf.tobytes(), 1).image
    c = colour.push_jpeg(buf.tobytes(), 1).image
    assert g.shape == c.shape[:2] and g.dtype == np.uint8
    # The grey levels of the colour decode converted, to the rounding of the chroma (clipped
    # at saturated edges).
    diff = np.abs(g.astype(int) - cv2.cvtColor(c, cv2.COLOR_BGR2GRAY).astype(int))
    assert diff.mean() < 0.5 and diff.max() <= 8
    with pytest.raises(ValueError, match="cannot decode"):
        grey.push_jpeg(b"", 2)
    (truth,) = cam.truth(0.0)
    found = DetectionPipeline(HaarDetector()).process(g, None).detections
    assert any(iou(d.box, truth.box) > 0.5 for d in found)


class _MjpegHandler(BaseHTTPRequestHandler):
    """Serves ``server.frames`` JPEG frames as an HTTP MJPEG stream, then closes the stream."""

    def log_message(self, *args: object) -> None:
        pass

    def do_GET(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.end_headers()
        try:
            for k in range(self.server.frames):  # type: ignore[attr-defined]
                jpg = self.server.jpegs[k % len(self.server.jpegs)]  # type: ignore[attr-defined]
                head = b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpg)
                self.wfile.write(head + jpg + b"\r\n")
                time.sleep(0.01)
        except (BrokenPipeError, ConnectionResetError):
            pass


def test_network_stream_reads_and_reconnects_after_a_drop() -> None:
    """A real HTTP MJPEG stream on 127.0.0.1 that drops the connection every 15 frames."""
    cam = SyntheticCamera(noise_sigma=0.0)
    rendered = [cam.render(k / 30) for k in range(5)]
    server = ThreadingHTTPServer(("127.0.0.1", 0), _MjpegHandler)
    server.frames = 15  # type: ignore[attr-defined]
    server.jpegs = [cv2.imencode(".jpg", f)[1].tobytes() for f in rendered]  # type: ignore[attr-defined]
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/stream.mjpg"
        src = VideoCaptureSource(url, "url", reconnect_initial_s=0.05, give_up_s=10.0)
        got = [src.read() for _ in range(34)]
        src.close()
    finally:
        server.shutdown()
        server.server_close()
    frames = [f for f in got if f is not None]
    assert src.reconnects >= 2 and len(frames) >= 30
    assert np.abs(frames[1].image.astype(int) - rendered[1]).mean() < 4.0
    assert np.all(np.diff([f.stamp_ns for f in frames]) > 0)


def test_unreachable_stream_is_one_clear_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound but not listening: connection refused
        with pytest.raises(CameraOpenError, match="cannot open url"):
            VideoCaptureSource(f"http://127.0.0.1:{port}/stream.mjpg", "url")


def test_synthetic_sim_clock_in_realtime_sleeps_until_the_frame_is_due() -> None:
    """A realtime arm's sim time advances with the wall clock: the camera sleeps until the next
    frame is due instead of asking the clock every millisecond, and still stamps each frame with
    its grid time."""
    cam = SyntheticCamera(noise_sigma=0)
    epoch = 1_700_000_000_000_000_000
    t0 = time.monotonic_ns()
    calls = {"realtime": 0, "polled": 0}

    def clock(kind: str) -> Callable[[], int]:
        def now() -> int:
            calls[kind] += 1
            return epoch + (time.monotonic_ns() - t0) // 2_000_000 * 2_000_000  # 500 Hz ticks
        return now

    for kind, realtime in (("realtime", True), ("polled", False)):
        src = SyntheticSource(cam, 30.0, sim_clock=clock(kind), sim_realtime=realtime)
        frames = [src.read(1.0) for _ in range(6)]
        assert all(f is not None for f in frames)
        stamps = [f.stamp_ns for f in frames if f is not None]
        assert set(np.diff(stamps).tolist()) <= {33_333_333, 33_333_334}  # consecutive grid frames
        assert src.dropped == 0
    # 5 frame periods (167 ms): about 2 looks a frame against one a millisecond
    assert calls["realtime"] <= 25 < 80 <= calls["polled"], calls


class _FakeService:
    """What :class:`services.goal_tracker.service._SimClock` uses of a service: ``subscribe``
    (``"latest"`` delivery: ``take`` hands over the newest queued state), ``record_rejection``."""

    def __init__(self) -> None:
        from services.bus.messages import Keys

        self.keys = Keys()
        self.states: list[object] = []
        self.rejected: list[str] = []

    def subscribe(self, topic, callback, *, delivery):  # type: ignore[no-untyped-def]
        assert delivery == "latest"
        fake = self

        class Sub:
            def take(self) -> bool:
                if not fake.states:
                    return False
                callback(fake.states.pop(), topic.key)
                fake.states.clear()
                return True
        return Sub()

    def record_rejection(self, key: str, why: str, kind: str) -> None:
        self.rejected.append(kind)


def test_sim_clock_samples_the_arm_state_and_rejects_states_off_its_stream() -> None:
    """The camera's sim clock looks at a state now and then (a realtime camera: about once a
    frame, 16+ ticks apart): those continue the stream; a replayed state or one forged far
    ahead does not move the clock, and is counted."""
    from services.bus.messages import ArmState
    from services.goal_tracker.service import MAX_SAMPLED_GAP_S, _SimClock

    svc = _FakeService()
    clock = _SimClock(svc)
    assert clock() is None
    epoch = 1_700_000_000_000_000_000

    def state(tick: int) -> ArmState:
        t = epoch + tick * 2_000_000
        return ArmState(tick=tick, stamp_ns=t, sim_time_ns=t, dt_s=0.002)

    for tick in (0, 17, 33, 50, 67, 84, 150):  # up to 66 ticks apart (> the 50 of a follower)
        svc.states.append(state(tick))
        assert clock() == epoch + tick * 2_000_000
    far = round(MAX_SAMPLED_GAP_S / 0.002) + 200
    svc.states.append(state(150 + far))  # forged: consistent, but far ahead
    assert clock() == epoch + 150 * 2_000_000
    svc.states.append(state(100))  # replayed
    assert clock() == epoch + 150 * 2_000_000
    svc.states.append(ArmState(tick=160, stamp_ns=epoch, sim_time_ns=epoch, dt_s=0.002))  # bad stamp
    assert clock() == epoch + 150 * 2_000_000
    svc.states.append(state(170))
    assert clock() == epoch + 170 * 2_000_000
    assert svc.rejected == ["tick", "tick", "stamp"]
