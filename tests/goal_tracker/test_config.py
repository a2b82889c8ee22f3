"""Configuration: defaults, file/env overrides, one-line errors naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from services.bus.config import ConfigError, load_config
from services.goal_tracker.config import TrackerConfig, build_synthetic_camera, build_tracker


def test_defaults_build_a_working_tracker() -> None:
    cfg = load_config(TrackerConfig, env={})
    sec = cfg.goal_tracker
    assert sec.camera.source == "synthetic" and sec.goal_name == "person"
    tracker = build_tracker(sec)
    cam = build_synthetic_camera(sec)
    for k in range(5):
        out = tracker.process(cam.render(k / 30), k * 33_333_333)
    assert out.valid, out.reason  # the default synthetic path lies inside the default workspace


def test_file_env_and_override_layers(tmp_path) -> None:
    path = tmp_path / "t.toml"
    path.write_text(
        'prefix = "cell1"\n[goal_tracker]\ngoal_name = "face"\n'
        '[goal_tracker.camera]\nsource = "device"\ndevice = 2\n'
        "[goal_tracker.mount]\ntranslation_m = [0.0, 0.1, 0.6]\n"
    )
    cfg = load_config(
        TrackerConfig,
        path,
        env={"PSM_GOAL_TRACKER__FILTER__LOST_TIMEOUT_S": "1.5"},
        overrides={"goal_tracker.camera.device": "3"},
    )
    sec = cfg.goal_tracker
    assert cfg.prefix == "cell1" and sec.goal_name == "face"
    assert sec.camera.device == 3 and sec.filter.lost_timeout_s == 1.5
    np.testing.assert_allclose(build_tracker(sec).geometry.camera_to_base.translation, [0.0, 0.1, 0.6])


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"goal_tracker.camera.source": "webcam"}, "goal_tracker.camera.source"),
        ({"goal_tracker.camera.source": "file"}, "goal_tracker.camera.uri"),
        ({"goal_tracker.detector.kind": "yunet"}, "goal_tracker.detector.model_path"),
        ({"goal_tracker.mount.rpy_deg": "1,2"}, "goal_tracker.mount.rpy_deg"),
        ({"goal_tracker.workspace.lower_m": "1,0,0"}, "goal_tracker.workspace.lower_m"),
        ({"goal_tracker.filter.gate_probability": "1.0"}, "goal_tracker.filter.gate_probability"),
        ({"goal_tracker.camera.fx": "-5"}, "goal_tracker.camera.fx"),
        ({"goal_tracker.goal_name": "a/b"}, "goal_tracker.goal_name"),
        ({"goal_tracker.synthetic.centre_m": "0,0,0.05"}, "goal_tracker.synthetic.centre_m"),
        ({"goal_tracker.filter.pixel_sigma": "1,1,0"}, "goal_tracker.filter.pixel_sigma"),
    ],
)
def test_bad_values_are_one_line_errors_naming_the_field(overrides: dict, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(TrackerConfig, overrides=overrides, env={})
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"config error: {field}"), text


def test_unknown_field_in_file(tmp_path) -> None:
    path = tmp_path / "t.toml"
    path.write_text("[goal_tracker.camera]\nfps = 30\n")
    with pytest.raises(ConfigError, match=r"goal_tracker\.camera\.fps: unknown field"):
        load_config(TrackerConfig, path, env={})


def test_hidden_windows_parse(tmp_path) -> None:
    path = tmp_path / "t.toml"
    path.write_text("[goal_tracker.synthetic]\nhidden_s = [[1.0, 2.0], [4.0, 4.5]]\n")
    cfg = load_config(TrackerConfig, path, env={})
    cam = build_synthetic_camera(cfg.goal_tracker)
    assert not cam.truth(1.5)[0].visible and cam.truth(3.0)[0].visible
