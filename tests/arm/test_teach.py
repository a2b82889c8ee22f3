"""Teach mode: minimum-jerk paths with tremor, MCAP recording, end-effector extraction, and the
committed demonstrations under data/demos/."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.arm.demos import build_demos, load_demos
from services.arm.teach import (
    RecordedPath,
    TeachConfig,
    Tremor,
    ViaPointPath,
    load_path_file,
    teach,
    write_teach_mcap,
)
from services.bus.log import read_log, read_metadata
from services.bus.messages import ArmState, FrameTransforms
from services.robot.model import RobotModel
from services.robot.recordings import TEACH_METADATA, ee_trajectory
from services.tasks.feeding import load_feeding

from .conftest import ROOT

DEMOS = load_demos()
FEEDING_SEQUENCE = load_feeding().task.sequence

DEMO_DIR = ROOT / "data" / "demos"


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def test_single_leg_is_minimum_jerk() -> None:
    p0, p1 = np.array([0.4, 0.0, 0.4]), np.array([0.5, 0.2, 0.1])
    path = ViaPointPath(np.array([p0, p1]), np.array([2.0]))
    t = np.linspace(0, 2.0, 101)
    x, v, a = path.sample(t)
    s = t / 2.0
    shape = 10 * s**3 - 15 * s**4 + 6 * s**5
    np.testing.assert_allclose(x, p0 + np.outer(shape, p1 - p0), atol=1e-12)
    np.testing.assert_allclose(v[[0, -1]], 0.0, atol=1e-12)
    np.testing.assert_allclose(a[[0, -1]], 0.0, atol=1e-9)
    # Velocity/acceleration are the derivatives of the position.
    np.testing.assert_allclose(np.gradient(x, t, axis=0)[5:-5], v[5:-5], atol=2e-3)


def test_via_points_and_velocities_are_met() -> None:
    P = np.array([[0.45, -0.35, 0.15], [0.45, -0.10, 0.04], [0.45, 0.10, 0.04]])
    V = np.array([[0, 0, 0], [0, 0.05, 0], [0, 0.5, 0]], dtype=float)
    path = ViaPointPath(P, np.array([2.0, 0.7]), V)
    x, v, _ = path.sample(np.array([0.0, 2.0, 2.7]))
    np.testing.assert_allclose(x, P, atol=1e-12)
    np.testing.assert_allclose(v, V, atol=1e-12)
    with pytest.raises(ValueError):
        ViaPointPath(P, np.array([1.0]))
    with pytest.raises(ValueError):
        ViaPointPath(P, np.array([1.0, -1.0]))


def test_tremor_is_seeded_band_limited_and_tapered() -> None:
    t = np.arange(0, 4.0, 0.002)
    tr = Tremor(amplitude_m=2e-4, drift_m=0.0, seed=7)
    a, b = tr.signal(t), tr.signal(t)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, Tremor(amplitude_m=2e-4, drift_m=0.0, seed=8).signal(t))
    np.testing.assert_allclose(a[[0, -1]], 0.0, atol=1e-15)
    mid = a[200:-200]
    rms = np.sqrt(np.mean(mid**2, axis=0))
    assert np.all((rms > 1e-4) & (rms < 4e-4))
    spec = np.abs(np.fft.rfft(mid[:, 0])) ** 2
    f = np.fft.rfftfreq(mid.shape[0], 0.002)
    in_band = spec[(f >= 7) & (f <= 13)].sum()
    assert in_band / spec.sum() > 0.95


def test_teach_record_and_extract(robot: RobotModel, tmp_path: Path) -> None:
    path = ViaPointPath(np.array([[0.40, 0.0, 0.40], [0.50, 0.10, 0.25]]), np.array([1.0]))
    snaps = teach(robot, path, TeachConfig(rest_before_s=0.1, rest_after_s=0.2))
    out = write_teach_mcap(
        tmp_path / "d.mcap", robot, snaps, metadata={"task": "t1"}, transforms_rate_hz=10.0
    )
    states = [m for _, m, _ in read_log(out, "psm/arm/state")]
    tfs = [m for _, m, _ in read_log(out, "psm/arm/transforms")]
    assert len(states) == len(snaps) and all(isinstance(m, ArmState) for m in states)
    assert len(tfs) == len(snaps) // 50 + 1 and isinstance(tfs[0], FrameTransforms)
    assert {tf.child_frame_id for tf in tfs[0].transforms} >= {"panda_link7", "panda_hand_tcp"}
    meta = read_metadata(out)[TEACH_METADATA]
    assert meta["task"] == "t1" and meta["ee_frame"] == "panda_hand_tcp"
    assert float(meta["rate_hz"]) == pytest.approx(500.0)
    t, X = ee_trajectory(out)
    np.testing.assert_allclose(np.diff(t), 0.002, atol=1e-12)
    # FK from joints equals the published EE pose; the arm follows the guided path.
    P = np.array([[s.ee_position.x, s.ee_position.y, s.ee_position.z] for s in states])
    np.testing.assert_allclose(X, P, atol=1e-12)
    xd, _, _ = path.sample(t - 0.1)
    assert np.max(np.abs(X - xd)) < 3e-3
    np.testing.assert_allclose(X[-1], [0.50, 0.10, 0.25], atol=5e-4)


def test_extract_rejects_non_arm_files(tmp_path: Path) -> None:
    from services.bus.recorder import McapSink

    sink = McapSink(tmp_path / "empty.mcap")
    sink.close()
    with pytest.raises(ValueError, match="no ArmState"):
        ee_trajectory(tmp_path / "empty.mcap")


def test_path_files(tmp_path: Path) -> None:
    spec = {"points": [[0.4, 0, 0.4], [0.5, 0.1, 0.3]], "durations": [1.5]}
    (tmp_path / "p.json").write_text(json.dumps(spec))
    p = load_path_file(tmp_path / "p.json")
    assert isinstance(p, ViaPointPath) and p.duration == 1.5
    t = np.linspace(0, 1, 50)
    X = np.column_stack([0.4 + 0.1 * t, 0.1 * t**2, 0.4 - 0.1 * t])
    np.savetxt(tmp_path / "p.csv", np.column_stack([t, X]), delimiter=",", header="t,x,y,z")
    rp = load_path_file(tmp_path / "p.csv")
    assert isinstance(rp, RecordedPath)
    x, v, _ = rp.sample(np.array([0.5]))
    np.testing.assert_allclose(x[0], [0.45, 0.025, 0.35], atol=1e-6)
    np.testing.assert_allclose(v[0], [0.1, 0.1, -0.1], atol=1e-3)
    (tmp_path / "p.txt").write_text("x")
    with pytest.raises(ValueError, match="unsupported"):
        load_path_file(tmp_path / "p.txt")


def test_teach_cli(tmp_path: Path) -> None:
    spec = {"points": [[0.4, 0, 0.4], [0.45, 0.05, 0.35]], "durations": [0.6]}
    (tmp_path / "p.json").write_text(json.dumps(spec))
    out = tmp_path / "cli.mcap"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.arm",
            "teach",
            "--path",
            str(tmp_path / "p.json"),
            "-o",
            str(out),
            "--seed",
            "3",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    t, X = ee_trajectory(out)
    np.testing.assert_allclose(X[-1], [0.45, 0.05, 0.35], atol=5e-4)
    assert t[-1] == pytest.approx(0.3 + 0.6 + 0.5, abs=0.003)


@pytest.mark.parametrize("name", list(DEMOS))
def test_committed_demos(name: str) -> None:
    path = DEMO_DIR / f"{name}.mcap"
    assert path.stat().st_size < 512 * 1024
    spec = DEMOS[name]
    t, X = ee_trajectory(path)
    np.testing.assert_allclose(np.diff(t), 0.002, atol=1e-9)  # 500 Hz like the paper
    np.testing.assert_allclose(X[0], spec.points[0], atol=1e-3)
    np.testing.assert_allclose(X[-1], spec.goal, atol=1e-3)
    assert read_metadata(path)[TEACH_METADATA]["task"] == name


def test_feeding_sequence_is_continuous() -> None:
    assert set(FEEDING_SEQUENCE) <= set(DEMOS)
    for a, b in itertools.pairwise(FEEDING_SEQUENCE):
        assert DEMOS[a].goal == DEMOS[b].points[0]


def test_demos_follow_the_scene() -> None:
    """Via-points are relative to the scene: moving the bowl moves the demos that use it."""
    scene = load_feeding().scene
    moved = build_demos(scene.model_copy(update={"bowl": (0.60, 0.10, 0.12)}))
    assert moved["reach_bowl"].goal == (0.60, 0.10, 0.12)
    assert moved["scoop"].points[0] == (0.60, 0.10, 0.12)
    assert moved["scoop"].goal == moved["reach_person"].points[0] == (0.66, 0.16, 0.18)
    assert moved["grasp_spoon"] == DEMOS["grasp_spoon"]
    assert DEMOS["grasp_spoon"].goal == scene.spoon and DEMOS["reach_person"].goal == scene.person


def test_cylinder_strike_profile() -> None:
    t, X = ee_trajectory(DEMO_DIR / "cylinder_strike.mcap")
    vy = np.gradient(X[:, 1], t)
    contact = np.argmin(np.abs(X[:, 1] - (-0.10)))
    assert 0.02 < vy[contact] < 0.08  # touches the cylinder slowly
    assert X[contact, 2] == pytest.approx(0.04, abs=2e-3)
    peak = int(np.argmax(vy))
    assert vy[peak] == pytest.approx(0.5, abs=0.04)  # then ~0.5 m/s along y
    assert X[peak, 1] == pytest.approx(0.10, abs=0.02)


def test_demos_regenerate_byte_identical(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import make_demos
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    (fresh,) = make_demos.generate(tmp_path, ["scoop"])
    assert fresh.read_bytes() == (DEMO_DIR / "scoop.mcap").read_bytes()


def test_demo_learns_a_psm() -> None:
    from psm import PhaseSpaceModel

    t, X = ee_trajectory(DEMO_DIR / "reach_bowl.mcap")
    model = PhaseSpaceModel.fit(t, X)
    np.testing.assert_allclose(model.goal, DEMOS["reach_bowl"].goal, atol=2e-3)
