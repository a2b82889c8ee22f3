"""End-to-end tracking on the synthetic feed with a known 3-D path (no bus).

Stated tolerance (measured numbers are in docs/goal_tracker.md; about half of each bound): over a
10 s path at 30 fps with the face 0.75-1.05 m from the camera, the filtered goal's RMS error is
< 25 mm along the camera depth axis (dominated by the Haar box-size bias) and < 8 mm across it, and
no valid goal is off by more than 60 mm.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.goal_tracker import best_lag_s
from services.bus.config import load_config
from services.goal_tracker.config import (
    FaceSection,
    TrackerConfig,
    build_geometry,
    build_synthetic_camera,
    build_tracker,
)
from services.goal_tracker.detectors import DetectionPipeline, HaarDetector
from services.goal_tracker.geometry import FaceGeometry, Intrinsics, Transform
from services.goal_tracker.kalman import KalmanParams
from services.goal_tracker.synthetic import LissajousPath, SyntheticCamera, SyntheticFace
from services.goal_tracker.tracker import GoalTracker, TrackState
from services.goal_tracker.workspace import Workspace

FPS = 30.0
MOUNT = Transform.from_rpy([-0.2, 0.0, 0.5], [-90.0, 0.0, -90.0])
OFFSET = (0.0, 0.045, 0.0)
WIDE = Workspace(lower=(-5, -5, -5), upper=(5, 5, 5))


def make_tracker(intr: Intrinsics, workspace: Workspace = WIDE, **kalman: float) -> GoalTracker:
    # The default detector's calibrated box width (the synthetic face's reference box is 0.16 m).
    geo = FaceGeometry(intr, FaceSection().width_m, MOUNT, OFFSET)
    return GoalTracker(geo, DetectionPipeline(HaarDetector()), KalmanParams(**kalman), workspace)


def truth_goal(cam: SyntheticCamera, t: float, i: int = 0) -> np.ndarray:
    return MOUNT.apply(cam.truth(t)[i].position_cam + np.asarray(OFFSET))


def run(tracker: GoalTracker, cam: SyntheticCamera, n: int, t0: float = 0.0) -> list:
    outs = []
    for k in range(n):
        t = t0 + k / FPS
        outs.append((t, tracker.process(cam.render(t), round(t * 1e9))))
    return outs


def test_goal_error_within_stated_tolerance() -> None:
    cam = SyntheticCamera(
        faces=[SyntheticFace(LissajousPath(centre=(0.0, 0.0, 0.9), amplitude=(0.15, 0.06, 0.15)))]
    )
    tracker = make_tracker(cam.intrinsics)
    outs = run(tracker, cam, 300)
    err = np.array([o.position - truth_goal(cam, t) for t, o in outs if o.valid])
    assert len(err) >= 295  # valid from the second frame on (min_hits = 2)
    rms = np.sqrt(np.mean(err**2, axis=0))
    # base x is the camera depth axis with this mount
    assert rms[0] < 0.025, rms
    assert rms[1] < 0.008 and rms[2] < 0.008, rms
    assert np.linalg.norm(err, axis=1).max() < 0.060
    # the reported covariance is a real covariance
    cov = outs[-1][1].covariance
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # most frames took the fast path
    assert tracker.stats.roi_detections > 0.8 * tracker.stats.frames


def test_lost_then_found() -> None:
    face = SyntheticFace(hidden=((1.0, 2.5),))
    cam = SyntheticCamera(faces=[face])
    tracker = make_tracker(cam.intrinsics, lost_timeout_s=0.5)
    outs = run(tracker, cam, 120)
    states = [(t, o.state, o.valid, o.reason) for t, o in outs]
    # predicting through the first part of the drop-out, still valid
    during = [s for s in states if 1.0 <= s[0] < 1.0 + 0.45]
    assert all(s[1] is TrackState.PREDICTING and s[2] for s in during)
    lost = [s for s in states if s[1] is TrackState.LOST]
    # last face at t = 0.967 s; lost one timeout (0.5 s) later
    assert len(lost) == 1 and 1.45 <= lost[0][0] <= 1.55
    assert lost[0][3].startswith("lost: no face")
    # invalid (searching) until the face returns, then valid again within ~3 frames
    between = [s for s in states if 1.55 < s[0] < 2.5]
    assert all(s[1] is TrackState.SEARCHING and not s[2] for s in between)
    back = [s for s in states if s[0] >= 2.5 and s[2]]
    assert back and back[0][0] < 2.5 + 3.5 / FPS
    assert tracker.stats.lost_events == 1 and tracker.stats.found_events == 2


def test_out_of_workspace_goal_is_invalid_with_reason() -> None:
    # the face moves 0.6-1.2 m deep: base x from 0.4 to 1.0; reachable only up to x = 0.8
    cam = SyntheticCamera(
        faces=[
            SyntheticFace(
                LissajousPath(
                    centre=(0.0, 0.0, 0.9),
                    amplitude=(0.0, 0.0, 0.3),
                    frequency_hz=(0, 0, 0.25),
                    phase_rad=(0, 0, 0),
                )
            )
        ]
    )
    ws = Workspace(lower=(0.2, -0.5, 0.0), upper=(0.8, 0.5, 1.0))
    tracker = make_tracker(cam.intrinsics, ws)
    outs = run(tracker, cam, 120)
    tracked = [(t, o) for t, o in outs if o.state is TrackState.TRACKING]
    outside = [o for _, o in tracked if o.position[0] > 0.8]
    inside = [o for _, o in tracked if o.position[0] < 0.8]
    assert len(outside) > 10 and len(inside) > 10
    assert all(not o.valid and o.reason.startswith("outside workspace: x=") for o in outside)
    assert all(o.valid and o.reason == "" for o in inside)


def test_keeps_the_chosen_face_when_a_second_face_appears() -> None:
    target = SyntheticFace(LissajousPath(centre=(-0.15, 0.0, 0.9), amplitude=(0.03, 0.02, 0.03)))
    # a nearer (larger) face enters after 1 s: the tracker must stay on its target
    intruder = SyntheticFace(
        LissajousPath(centre=(0.2, 0.0, 0.7), amplitude=(0.02, 0.02, 0.0)), hidden=((0.0, 1.0),)
    )
    cam = SyntheticCamera(faces=[target, intruder])
    tracker = make_tracker(cam.intrinsics)
    outs = run(tracker, cam, 75)
    late = [(t, o) for t, o in outs if t > 1.2]
    assert all(o.valid for _, o in late)
    err = [np.linalg.norm(o.position - truth_goal(cam, t, 0)) for t, o in late]
    assert max(err) < 0.1
    # both faces are reported on full-detection frames
    assert any(len(o.detections) == 2 for _, o in late)


def test_starts_on_the_largest_face() -> None:
    far = SyntheticFace(LissajousPath(centre=(-0.2, 0.0, 1.3), amplitude=(0, 0, 0)))
    near = SyntheticFace(LissajousPath(centre=(0.15, 0.0, 0.8), amplitude=(0, 0, 0)))
    cam = SyntheticCamera(faces=[far, near])
    outs = run(make_tracker(cam.intrinsics), cam, 10)
    last = outs[-1][1]
    assert last.valid
    assert np.linalg.norm(last.position - truth_goal(cam, outs[-1][0], 1)) < 0.08


def test_frame_size_other_than_configured_rescales_intrinsics() -> None:
    cam = SyntheticCamera(Intrinsics.from_fov(960, 720, 60.0))
    tracker = make_tracker(Intrinsics.from_fov(640, 480, 60.0))
    tracker.set_image_size(960, 720)
    outs = run(tracker, cam, 20)
    t, o = outs[-1]
    assert o.valid and np.linalg.norm(o.position - truth_goal(cam, t)) < 0.08


@pytest.mark.parametrize("stamps", [[0, 0], [10, 5]])
def test_non_increasing_stamps_do_not_break_the_filter(stamps: list[int]) -> None:
    cam = SyntheticCamera()
    tracker = make_tracker(cam.intrinsics)
    frame = cam.render(0.0)
    for s in [*stamps, *stamps]:
        out = tracker.process(frame, s)
    assert out.stamp_ns > stamps[0]


STACK_TOML = Path(__file__).resolve().parents[2] / "configs" / "stack.toml"


def _stack_scene(n: int, still: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stack's tracker on the stack's synthetic face (0.5 m away, base y = camera depth),
    frames JPEG round-tripped as on the bus: frame times (n,), goals (n, 3), truth (n, 3)."""
    over = {"goal_tracker.synthetic.amplitude_m": [0.0, 0.0, 0.0]} if still else {}
    sec = load_config(TrackerConfig, STACK_TOML, env={}, overrides=over).goal_tracker
    cam, geo, tracker = build_synthetic_camera(sec), build_geometry(sec), build_tracker(sec)
    t = np.arange(n) / sec.synthetic.fps
    est, truth = np.full((n, 3), np.nan), np.empty((n, 3))
    for k, tk in enumerate(t):
        _, buf = cv2.imencode(".jpg", cam.render(tk), [cv2.IMWRITE_JPEG_QUALITY, sec.camera.jpeg_quality])
        out = tracker.process(cv2.imdecode(buf, cv2.IMREAD_COLOR), round(tk * 1e9))
        truth[k] = geo.camera_to_base.apply(cam.truth(tk)[0].position_cam + np.asarray(sec.face.offset_m))
        if out.valid:
            est[k] = out.position
    return t, est, truth


def test_still_face_goal_is_steady_in_depth() -> None:
    # Stated: after 5 s the goal of a still face 0.5 m away has a 1-sigma <= 1.5 mm on every axis
    # (measured 0.4 / 1.2 / 0.3 mm; the former filter: 6.7 mm along depth = base y) and its second
    # difference (the acceleration an arm following it must make) p99 < 4 m/s^2 (measured 2.3;
    # was 22).
    t, est, _ = _stack_scene(300, still=True)
    e = est[t >= 5.0]
    assert not np.isnan(e).any()
    assert np.all(np.std(e, axis=0) <= 0.0015), np.std(e, axis=0)
    acc = np.abs(np.diff(e, 2, axis=0)) * 30.0**2
    assert np.all(np.percentile(acc, 99, axis=0) < 4.0)


def test_moving_face_follows_the_stack_path() -> None:
    # Stated: on the stack's path (±3 cm at 0.04-0.07 Hz) the goal's RMS error after 5 s is
    # < 8 mm per axis (measured 2.6 / 6.1 / 0.6 mm, the depth part mostly the Haar size bias),
    # its acceleration p99 < 4 m/s^2 (measured 3.1; was 26), and it lags the truth by < 0.25 s
    # on the image axes.
    t, est, truth = _stack_scene(450, still=False)
    keep = t >= 5.0
    e, tr, tk = est[keep], truth[keep], t[keep]
    assert not np.isnan(e).any()
    rms = np.sqrt(np.mean((e - tr) ** 2, axis=0))
    assert np.all(rms < 0.008), rms
    acc = np.abs(np.diff(e, 2, axis=0)) * 30.0**2
    assert np.all(np.percentile(acc, 99, axis=0) < 4.0)
    for axis in (0, 2):  # base x, z: the image axes (amplitude 3 and 2 cm)
        assert abs(best_lag_s(tk, e[:, axis], tr[:, axis])) < 0.25
