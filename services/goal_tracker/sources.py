"""Frame sources: OpenCV ``VideoCapture`` (device index, video file, stream URL), the synthetic
camera, and a queue fed by a subscribed image topic.

Every source yields :class:`Frame` objects through ``read(timeout_s)`` and is closed with
``close()``. A source that cannot be opened raises :class:`CameraOpenError` once, with a one-line
message; a dropped stream is reopened with exponential backoff, and only after
``give_up_s`` without a frame does ``read`` raise :class:`CameraOpenError`. A finished file raises
:class:`SourceEndedError`.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from services.goal_tracker.frames import due_frame, frame_period_ns, frame_time_ns
from services.goal_tracker.synthetic import SyntheticCamera

_log = logging.getLogger("psm.goal_tracker.sources")


def quiet_opencv_io() -> None:
    """Silence OpenCV's and FFmpeg's own warnings about feeds that fail to open (our one-line
    :class:`CameraOpenError` replaces them). Respects an explicit ``OPENCV_LOG_LEVEL`` /
    ``OPENCV_FFMPEG_LOGLEVEL`` in the environment; must run before the first FFmpeg open."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
    if "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


class CameraOpenError(OSError):
    """A camera/file/stream cannot be opened (or stayed down past the give-up time)."""


class SourceEndedError(Exception):
    """The source has no more frames (end of a file, frame limit reached)."""


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    Attributes:
        image: H×W×3 BGR uint8, or H×W grey uint8 from a source that decodes to grey
            (:class:`QueueSource` for a grey-only detector).
        stamp_ns: time the frame shows, ns (sim time, or UNIX wall time for real cameras).
        seq: per-source frame counter starting at 0.
        jpeg: the frame's original JPEG bytes when it arrived compressed, else None.
    """

    image: NDArray[np.uint8]
    stamp_ns: int
    seq: int
    jpeg: bytes | None = None


class FrameSource(Protocol):
    """Anything that delivers frames."""

    description: str

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame, or None when none arrived within ``timeout_s`` seconds."""
        ...

    def close(self) -> None:
        """Release the device / file / subscription."""
        ...


class VideoCaptureSource:
    """A device index, a video file or a network URL, via ``cv2.VideoCapture``.

    Args:
        target: device index (int) or file path / URL (str).
        kind: "device", "file" or "url" (decides end-of-stream handling and stamps).
        loop: files only: restart at the end.
        realtime: files only: pace frames at the file's frame rate (else as fast as read).
        reconnect_initial_s, reconnect_max_s: backoff after a dropped stream, s.
        give_up_s: raise :class:`CameraOpenError` when the stream stays down this long (0: never).
        opener: factory with ``cv2.VideoCapture``'s interface (injectable for tests).
        stop: event that aborts a reconnect wait.
    """

    def __init__(
        self,
        target: int | str,
        kind: str,
        *,
        loop: bool = False,
        realtime: bool = True,
        reconnect_initial_s: float = 0.5,
        reconnect_max_s: float = 5.0,
        give_up_s: float = 60.0,
        opener: Callable[[Any], Any] = cv2.VideoCapture,
        stop: threading.Event | None = None,
    ) -> None:
        if kind not in ("device", "file", "url"):
            raise ValueError(f"VideoCaptureSource kind must be device, file or url, got {kind!r}")
        self.target = target
        self.kind = kind
        self.loop = loop
        self.realtime = realtime
        self.reconnect_initial_s = reconnect_initial_s
        self.reconnect_max_s = reconnect_max_s
        self.give_up_s = give_up_s
        self._opener = opener
        self.stop = stop or threading.Event()
        self.description = f"{kind} {target!r}"
        self.seq = 0
        self.reconnects = 0
        self._cap: Any = None
        self._t0_wall_ns = 0
        self._t0_mono = 0.0
        self._last_stamp = 0
        quiet_opencv_io()
        self._open_or_raise()

    def _open(self) -> bool:
        cap = self._opener(self.target)
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            return False
        self._cap = cap
        self._t0_wall_ns = time.time_ns()
        self._t0_mono = time.monotonic()
        return True

    def _open_or_raise(self) -> None:
        if not self._open():
            hint = {
                "device": "is a camera connected and not in use?",
                "file": "does the file exist and is it a video OpenCV can decode?",
                "url": "is the stream reachable and the URL right?",
            }[self.kind]
            raise CameraOpenError(f"cannot open {self.description}: {hint}")

    def _file_stamp_ns(self) -> int:
        pos_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
        return self._t0_wall_ns + round(pos_ms * 1e6)

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        """Next frame; reconnects (device/url) or loops/ends (file) as configured."""
        if self._cap is None:
            self._reconnect()
        ok, image = self._cap.read()
        if ok and image is not None:
            if image.ndim == 2:
                image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
            elif image.shape[2] == 4:
                image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
            if self.kind == "file":
                stamp = self._file_stamp_ns()
                if self.realtime:
                    wait = self._t0_mono + (stamp - self._t0_wall_ns) * 1e-9 - time.monotonic()
                    if wait > 0:
                        self.stop.wait(wait)
            else:
                stamp = time.time_ns()
            frame = Frame(image, stamp, self.seq)
            self._last_stamp = stamp
            self.seq += 1
            return frame
        if self.kind == "file":
            if not self.loop:
                raise SourceEndedError(f"end of {self.description}")
            self._cap.release()
            self._cap = None
            self._open_or_raise()
            # keep stamps increasing across loops: the replay continues one period later
            fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0) or 30.0
            shift = self._last_stamp + round(1e9 / fps) - self._t0_wall_ns
            if shift > 0:
                self._t0_wall_ns += shift
                self._t0_mono += shift * 1e-9
            return None
        _log.warning("stream dropped, reconnecting", extra={"source": self.description})
        self._cap.release()
        self._cap = None
        self._reconnect()
        return None

    def _reconnect(self) -> None:
        delay = self.reconnect_initial_s
        start = time.monotonic()
        while not self.stop.is_set():
            if self.give_up_s and time.monotonic() - start > self.give_up_s:
                raise CameraOpenError(
                    f"{self.description} is down: no reconnect within {self.give_up_s:.0f} s"
                )
            if self.stop.wait(delay):
                break
            self.reconnects += 1
            if self._open():
                _log.info(
                    "stream reconnected",
                    extra={"source": self.description, "attempts": self.reconnects},
                )
                return
            delay = min(delay * 2.0, self.reconnect_max_s)
        raise SourceEndedError("stopped while reconnecting")

    def close(self) -> None:
        """Release the capture."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class SyntheticSource:
    """Frames of a :class:`SyntheticCamera` at ``fps``, stamped with the time they show.

    Frame times lie on the grid ``k / fps`` of the stack's clock. Without ``sim_clock`` that
    clock is the wall clock: frame ``k`` is due at ``start + k / fps`` (paced by the monotonic
    clock) and stamped ``start_unix_ns + k / fps``. With ``sim_clock`` (a callable returning
    the latest sim time in ns, or None before the first one — e.g. the arm's state) the grid is
    on the sim time itself: frame ``k`` is produced once sim time reaches ``k / fps`` and is
    stamped exactly that. The scene shown is the one at ``stamp − origin`` (origin: the start,
    or the grid time at or before the first sim time seen: 0 for a lockstep arm). The sim clock
    is asked every millisecond while a frame is due; with ``sim_realtime`` (sim time advances
    with the wall clock, as a realtime arm's does) the source first sleeps until the frame is
    due on the latest sim time, so it asks about once a frame.

    A camera that cannot keep its rate (slow rendering, a descheduled process, a sim clock
    running faster than real time) drops frames instead of lagging: ``read`` returns the
    latest due frame and counts the ones skipped in :attr:`dropped`.
    """

    def __init__(
        self,
        camera: SyntheticCamera,
        fps: float = 30.0,
        *,
        sim_clock: Callable[[], int | None] | None = None,
        sim_realtime: bool = False,
        max_frames: int = 0,
        stop: threading.Event | None = None,
    ) -> None:
        if fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.camera = camera
        self.fps = float(fps)
        self._period = frame_period_ns(self.fps)
        self.sim_clock = sim_clock
        self.sim_realtime = sim_realtime
        self.max_frames = max_frames
        self.stop = stop or threading.Event()
        self.seq = 0
        self.dropped = 0
        self._next_k = 0
        self._origin_ns: int | None = None if sim_clock is not None else 0
        self._t0_wall_ns = time.time_ns()
        self._t0_mono = time.monotonic()
        self.description = (
            f"synthetic {camera.intrinsics.width}x{camera.intrinsics.height} "
            f"@ {fps:g} fps ({'arm sim clock' if sim_clock else 'wall clock'})"
        )

    def frame_time_ns(self, k: int) -> int:
        """Time of grid frame ``k`` on the source's clock, ns (from the start for the wall
        clock, absolute sim time for a sim clock)."""
        return frame_time_ns(k, self._period)

    def _due_index(self, now_ns: int) -> int:
        """The latest grid frame whose time is at or before ``now_ns``."""
        return due_frame(now_ns, self._period)

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        """The latest due frame, or None if none is due within ``timeout_s``."""
        if self.max_frames and self.seq >= self.max_frames:
            raise SourceEndedError(f"{self.max_frames} synthetic frames done")
        deadline = time.monotonic() + timeout_s
        if self.sim_clock is not None:
            while True:
                now = self.sim_clock()
                if now is not None:
                    k = self._due_index(now)
                    if self._origin_ns is None:
                        self._origin_ns = self.frame_time_ns(k)
                        self._next_k = k
                    if k >= self._next_k:
                        break
                remaining = deadline - time.monotonic()
                if remaining <= 0.0 or self.stop.is_set():
                    return None
                wait = 0.001
                if self.sim_realtime and now is not None:
                    wait = max(wait, (self.frame_time_ns(self._next_k) - now) * 1e-9)
                self.stop.wait(min(wait, remaining))
            stamp = self.frame_time_ns(k)
        else:
            due = self._t0_mono + self.frame_time_ns(self._next_k) * 1e-9
            wait = due - time.monotonic()
            if wait > timeout_s:
                self.stop.wait(timeout_s)
                return None
            if wait > 0 and self.stop.wait(wait):
                return None
            elapsed_ns = round((time.monotonic() - self._t0_mono) * 1e9)
            k = max(self._next_k, self._due_index(elapsed_ns))
            stamp = self._t0_wall_ns + self.frame_time_ns(k)
        self.dropped += k - self._next_k
        self._next_k = k + 1
        assert self._origin_ns is not None
        scene_ns = self.frame_time_ns(k) - self._origin_ns
        image = self.camera.render(scene_ns * 1e-9)
        seq = self.seq
        self.seq += 1
        return Frame(image, stamp, seq)

    def close(self) -> None:
        """Nothing to release."""


def decode_image(data: bytes, grayscale: bool = False) -> NDArray[np.uint8]:
    """Decode JPEG/PNG bytes to H×W×3 BGR uint8, or to H×W grey when ``grayscale`` (the JPEG's
    luma plane as stored: no colour conversion, about half the cost of a colour decode).
    Raises ``ValueError`` if the bytes do not decode (empty bytes included: OpenCV asserts on
    those)."""
    image = None
    if data:
        try:
            flag = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR
            image = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
        except cv2.error:
            image = None
    if image is None:
        raise ValueError(f"cannot decode image ({len(data)} bytes)")
    return image


class QueueSource:
    """Frames pushed by a subscription callback (``push``), read in arrival order.

    Every frame is kept (FIFO, up to ``max_pending``; beyond that the oldest are dropped and
    counted) so a replayed recording goes through the tracker frame by frame. ``grayscale``:
    decode to grey (:func:`decode_image`), for a detector that only looks at grey levels.
    """

    def __init__(self, description: str, max_pending: int = 256, grayscale: bool = False) -> None:
        self.description = description
        self._q: queue.Queue[Frame] = queue.Queue()
        self.max_pending = max_pending
        self.grayscale = grayscale
        self.dropped = 0
        self.seq = 0

    def push_jpeg(self, data: bytes, stamp_ns: int) -> Frame:
        """Decode ``data`` (JPEG/PNG bytes, :func:`decode_image`) and queue it; raises
        ``ValueError`` if undecodable."""
        frame = Frame(decode_image(data, self.grayscale), int(stamp_ns), self.seq, bytes(data))
        self.seq += 1
        while self._q.qsize() >= self.max_pending:
            try:
                self._q.get_nowait()
                self.dropped += 1
            except queue.Empty:
                break
        self._q.put(frame)
        return frame

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        """The oldest pending frame, or None after ``timeout_s``."""
        try:
            return self._q.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None

    def close(self) -> None:
        """Nothing to release (the subscription belongs to the service)."""
