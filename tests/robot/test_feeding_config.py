"""The feeding scene and task configuration (``configs/feeding.toml``): loads, is immutable, and
a bad value is one error line naming the field."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pydantic
import pytest

from services.tasks.feeding import (
    DEFAULT_FEEDING_CONFIG,
    FeedingConfigError,
    load_feeding,
    static_person_task,
)

ROOT = Path(__file__).resolve().parents[2]


def test_shipped_config_loads() -> None:
    cfg = load_feeding()
    assert DEFAULT_FEEDING_CONFIG == ROOT / "configs" / "feeding.toml"
    assert cfg.scene.frame_id == "base"
    assert cfg.scene.spoon == (0.50, -0.25, 0.06)
    assert cfg.task.sequence == ("grasp_spoon", "back_to_neutral", "reach_bowl", "scoop", "reach_person")
    with pytest.raises(pydantic.ValidationError):
        cfg.scene.bowl = (0.0, 0.0, 0.0)  # type: ignore[misc]


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "spoon = [0.50, -0.25, 0.06]",
            "spoon = [0.50, -0.25]",
            r"scene\.spoon: expected 3 finite numbers \(m\), got \[0\.5, -0\.25\]",
        ),
        ("bowl = [0.55, 0.20, 0.10]", 'bowl = [0.55, "x", 0.10]', r"scene\.bowl: expected 3 finite numbers"),
        ("bowl = [0.55, 0.20, 0.10]", "bowl = [0.55, nan, 0.10]", r"scene\.bowl: expected 3 finite numbers"),
        ("bowl = [0.55, 0.20, 0.10]", "bowl = [0.55, true, 0.10]", r"scene\.bowl: expected 3 finite numbers"),
        ("person = [0.35, 0.50, 0.45]", "persn = [0.35, 0.50, 0.45]", r"scene\.person: missing"),
        ('frame_id = "base"', 'frame_id = "base"\ntable = 1', r"scene\.table: unknown field"),
        ('goal = "spoon"', 'goal = "spon"', r"task\.steps\[0\]\.goal: 'spon' is not a scene position"),
        ('dwell_s = 0.2', "dwell_s = -1",
         r"task\.steps\[0\]\.dwell_s: Input should be greater than or equal to 0"),
        ("controller = { start_shift = true }", "controller = { start_shfit = true }",
         r"task\.steps\[0\]\.controller: .*unknown controller option 'start_shfit'"),
        ("controller = { start_shift = true }", "fit = { smoothin = 0.02 }",
         r"task\.steps\[0\]\.fit: .*unknown fit option 'smoothin'"),
        ('name = "back_to_neutral"', 'name = "grasp_spoon"', r"task\.steps\[1\]\.name: duplicate step name"),
        ('on_goal_lost = "hold"', 'on_goal_lost = "stop"',
         r"task\.on_goal_lost: Input should be 'hold' or 'neutral'"),
        ("live = true ", "live = \"maybe\" ", r"task\.steps\[4\]\.live: Input should be a valid boolean"),
        ("[task]", "[task", r"invalid TOML"),
    ],
)
def test_bad_value_names_the_field(tmp_path: Path, old: str, new: str, message: str) -> None:
    text = DEFAULT_FEEDING_CONFIG.read_text()
    assert old in text
    bad = tmp_path / "feeding.toml"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(FeedingConfigError, match=message) as err:
        load_feeding(bad)
    assert "\n" not in str(err.value) and str(err.value).startswith(str(bad))


def test_cli_reports_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "feeding.toml"
    bad.write_text(DEFAULT_FEEDING_CONFIG.read_text().replace("bowl = [0.55, 0.20, 0.10]", "bowl = [1, 2]"))
    proc = subprocess.run(
        [sys.executable, "-m", "services.cli", "teach", "--list", "--scene", str(bad)],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2
    expected = f"psm teach: error: {bad}: scene.bowl: expected 3 finite numbers (m), got [1, 2]"
    assert proc.stderr.strip() == expected


def test_the_static_person_task_has_the_same_steps_and_no_live_goal(tmp_path: Path) -> None:
    text = static_person_task(DEFAULT_FEEDING_CONFIG.read_text())
    path = tmp_path / "feeding.toml"
    path.write_text(text)
    static, shipped = load_feeding(path), load_feeding()
    assert static.task.sequence == shipped.task.sequence
    assert not any(s.live for s in static.task.steps) and any(s.live for s in shipped.task.steps)
    assert static.scene == shipped.scene
    with pytest.raises(ValueError):
        static_person_task(text)
