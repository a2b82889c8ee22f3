"""The stack file: validated as a whole before anything starts, one error line naming the
process and the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.bus.config import ConfigError
from services.stack import load_stack

BASE = """
prefix = "psm"
[zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:7447"]
multicast = false
[[stack.processes]]
name = "router"
command = ["serve", "router"]
[[stack.processes]]
name = "arm"
command = ["arm"]
[router]
listen = ["tcp/127.0.0.1:7447"]
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "stack.toml"
    p.write_text(BASE + text)
    return p


def test_overrides_reach_every_process_that_has_the_field(tmp_path: Path) -> None:
    stack = load_stack(_write(tmp_path, "[arm]\ndt_s = 0.002\n"), overrides={"clock": "lockstep",
                                                                             "arm.dt_s": 0.001}, env={})
    assert stack.config.clock == "lockstep"
    assert all(c.clock == "lockstep" for c in stack.configs.values())
    assert stack.configs["arm"].arm.dt_s == 0.001  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("text", "overrides", "expected"),
    [
        ("[arm]\ndt_s = -1\n", {},
         "config error: arm.dt_s: Input should be greater than 0 (got -1) (process 'arm')"),
        ("[arm]\nstart_pose = 'nowhere'\n", {}, None),
        ("[amr]\ndt_s = 0.001\n", {}, "config error: amr: no process of the stack reads this table"),
        ("[[stack.processes]]\nname = 'arm'\ncommand = ['arm']\n", {},
         "config error: stack.processes[2].name: duplicate process name 'arm'"),
        ("[[stack.processes]]\nname = 'x'\ncommand = ['fly']\n", {},
         "config error: stack.processes[2].command: 'fly' is not a stack command"),
        ("[[stack.processes]]\nname = 'rec'\ncommand = ['record']\ncpu_affinity = [1, 1]\n", {},
         "config error: stack.processes[2].cpu_affinity: lists a CPU twice"),
        ("[[stack.processes]]\nname = 'rec'\ncommand = ['record']\ncpu_affinity = [-1]\n", {},
         "config error: stack.processes[2].cpu_affinity[0]: Input should be greater than or equal to 0"),
        ("", {"goal_tracker.goal_name": "x"},
         "config error: goal_tracker.goal_name: unknown field for every"),
    ],
)
def test_errors_name_the_process_and_field(
    tmp_path: Path, text: str, overrides: dict, expected: str | None
) -> None:
    path = _write(tmp_path, text)
    if expected is None:  # only the arm's robot model can check a pose: the arm checks it at start
        load_stack(path, overrides=overrides, env={})
        return
    with pytest.raises(ConfigError) as ei:
        load_stack(path, overrides=overrides, env={})
    assert str(ei.value).startswith(expected), str(ei.value)


def test_a_real_camera_replaces_the_synthetic_one(tmp_path: Path) -> None:
    from services.stack import DEFAULT_STACK, load_stack, use_camera

    stack = use_camera(load_stack(DEFAULT_STACK, overrides={"goal_tracker.camera.source": "device"}, env={}))
    names = [p.name for p in stack.processes]
    assert "camera" not in names and "goal_tracker" in names and "camera" not in stack.configs
    (tracker,) = [p for p in stack.processes if p.name == "goal_tracker"]
    assert tracker.command == ["track"]
    assert stack.configs["goal_tracker"].goal_tracker.camera.source == "device"  # type: ignore[attr-defined]
    # The planner cannot wait for a real camera's goals on the arm's clock.
    from services.stack import real_camera_overrides

    assert real_camera_overrides(stack) == {"planner.live_goal_sync": False}
    no_planner = tmp_path / "no_planner.toml"
    no_planner.write_text(BASE + "[[stack.processes]]\nname = 'goal_tracker'\ncommand = ['track']\n")
    assert real_camera_overrides(use_camera(load_stack(no_planner, env={}))) == {}
