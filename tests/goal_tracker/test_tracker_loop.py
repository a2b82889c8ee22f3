"""The tracker's frame loop (``services.goal_tracker.service._loop``) on a scripted source: one
goal per analysed frame, a copy of the last frame (a lockstep camera sending it again) not
analysed twice, and no wall-clock stall in lockstep."""

from __future__ import annotations

import logging
import threading
from typing import Any

from services.bus.config import load_config
from services.goal_tracker.config import TrackerConfig, build_synthetic_camera, build_tracker
from services.goal_tracker.service import _loop
from services.goal_tracker.sources import Frame, SourceEndedError

FRAME_NS = 33_333_333


class _Pub:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def put(self, msg: Any) -> None:
        self.sent.append(msg)


class _Svc:
    def __init__(self) -> None:
        self.stop_event = threading.Event()
        self.log = logging.getLogger("test.tracker")
        self.errors: list[str] = []

    def record_error(self, text: str, exc: Any = None) -> None:
        self.errors.append(text)


class _Script:
    """Frames then, per ``None``, one empty read; the end after the last."""

    def __init__(self, items: list[Frame | None]) -> None:
        self.items = items

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        if not self.items:
            raise SourceEndedError("script done")
        return self.items.pop(0)


def _run(items: list[Frame | None], stall_s: float | None) -> tuple[int, _Pub, _Svc]:
    sec = load_config(TrackerConfig, env={}, overrides={}).goal_tracker
    goal, svc = _Pub(), _Svc()
    rc = _loop(svc, sec, build_tracker(sec), _Script(items), _Pub(), _Pub(), goal, _Pub(), None, 0, stall_s)
    return rc, goal, svc


def _frames(n: int) -> list[Frame]:
    sec = load_config(TrackerConfig, env={}, overrides={}).goal_tracker
    cam = build_synthetic_camera(sec)
    return [Frame(cam.render(k * FRAME_NS * 1e-9), k * FRAME_NS, k) for k in range(n)]


def test_a_copy_of_the_last_frame_is_not_analysed_again() -> None:
    f0, f1 = _frames(2)
    rc, goal, svc = _run([f0, Frame(f0.image, f0.stamp_ns, 1), f1, Frame(f1.image, f1.stamp_ns, 3)], None)
    assert rc == 0 and not svc.errors
    assert [m.stamp_ns for m in goal.sent] == [0, FRAME_NS]
    assert [m.seq for m in goal.sent] == [0, 1]


def test_no_stall_goal_without_a_stall_timeout() -> None:
    import time

    (f0,) = _frames(1)

    class _Slow(_Script):
        def read(self, timeout_s: float = 1.0) -> Frame | None:
            if self.items and self.items[0] is None:
                time.sleep(0.06)
            return super().read(timeout_s)

    sec = load_config(TrackerConfig, env={}, overrides={}).goal_tracker
    for stall_s in (None, 0.05):
        goal = _Pub()
        _loop(_Svc(), sec, build_tracker(sec), _Slow([f0, None, None]), _Pub(), _Pub(), goal, _Pub(), None, 0,
              stall_s)
        stalls = sum(m.invalid_reason.startswith("camera stalled") for m in goal.sent)
        assert stalls == (0 if stall_s is None else 1), [m.invalid_reason for m in goal.sent]
