"""Target selection across frames and the workspace check."""

from __future__ import annotations

import math

import pytest

from psm.errors import ParameterError
from services.goal_tracker.selection import Detection, TargetSelector, iou
from services.goal_tracker.workspace import Workspace


def test_iou() -> None:
    assert iou([0, 0, 10, 10], [0, 0, 10, 10]) == 1.0
    assert iou([0, 0, 10, 10], [20, 20, 5, 5]) == 0.0
    assert iou([0, 0, 10, 10], [5, 0, 10, 10]) == pytest.approx(50 / 150)


def test_largest_face_becomes_target_and_is_kept() -> None:
    sel = TargetSelector(min_hits=2)
    small = Detection(100, 100, 40, 40)
    big = Detection(300, 100, 80, 80)
    assert sel.update([small, big]) is None  # nobody seen twice yet
    assert sel.update([small, big]) is big
    # the small face grows larger than the target: the target is sticky
    bigger = Detection(95, 95, 90, 90)
    assert sel.update([bigger, Detection(302, 101, 80, 80)]).x == 302


def test_one_frame_false_positive_never_becomes_target() -> None:
    sel = TargetSelector(min_hits=2)
    assert sel.update([Detection(10, 10, 200, 200)]) is None
    assert sel.update([]) is None
    assert sel.target is None


def test_target_survives_short_misses_then_switches() -> None:
    sel = TargetSelector(min_hits=1, max_misses=2)
    a, b = Detection(100, 100, 80, 80), Detection(400, 100, 50, 50)
    assert sel.update([a, b]) is a
    for _ in range(2):
        assert sel.update([b]) is None  # target missing, but kept
        assert sel.target is not None and sel.target.detection.x == 100
    assert sel.update([b]) is b  # dropped after max_misses: next-largest takes over


def test_bad_selector_params() -> None:
    with pytest.raises(ParameterError):
        TargetSelector(iou_threshold=1.5)


def test_workspace_reasons() -> None:
    ws = Workspace(lower=(0.2, -0.5, 0.0), upper=(0.9, 0.5, 1.0), centre=(0, 0, 0.3), max_radius=0.85)
    assert ws.violation([0.5, 0.0, 0.5]) is None
    assert ws.violation([1.2, 0.0, 0.5]) == "outside workspace: x=1.200 m > max 0.900 m"
    assert ws.violation([0.5, -0.7, 0.5]) == "outside workspace: y=-0.700 m < min -0.500 m"
    reason = ws.violation([0.85, 0.45, 0.5])
    assert reason is not None and "max_radius" in reason
    assert ws.violation([math.nan, 0, 0]) == "goal is not finite"


def test_bad_workspace() -> None:
    with pytest.raises(ParameterError):
        Workspace(lower=(1, 0, 0), upper=(0, 1, 1))
