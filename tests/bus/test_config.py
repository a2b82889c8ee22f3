"""Typed config (pydantic-settings): TOML < env < CLI, one-line errors naming the field, and the
stack-file rule (a service ignores the tables of the other services)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
from pydantic import Field

from services.bus.config import (
    ConfigError,
    Section,
    ServiceConfig,
    Vec3,
    add_config_arguments,
    config_from_args,
    env_var_name,
    load_config,
    parse_override,
)


class ArmSection(Section):
    dt_s: float = Field(0.002, gt=0.0, le=0.1)
    joints: int = Field(7, ge=1)
    offset: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 1.0])

    def check(self) -> None:
        if self.joints == 13:
            raise ConfigError("joints", "unlucky")


class ArmConfig(ServiceConfig):
    arm: ArmSection = Field(default_factory=ArmSection)


def test_defaults() -> None:
    cfg = load_config(ArmConfig, env={})
    assert cfg.prefix == "psm" and cfg.zenoh.mode == "peer" and cfg.zenoh.multicast
    assert cfg.arm.dt_s == 0.002 and cfg.clock == "realtime"


def test_file_env_cli_precedence(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text(
        'prefix = "filecell"\nclock = "lockstep"\n[zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\n'
        "[arm]\ndt_s = 0.001\njoints = 6\n"
    )
    cfg = load_config(ArmConfig, f, env={})
    assert (cfg.prefix, cfg.zenoh.mode, cfg.arm.dt_s, cfg.clock) == ("filecell", "client", 0.001, "lockstep")
    env = {"PSM_PREFIX": "envcell", "PSM_ZENOH__CONNECT": "tcp/a:1, tcp/b:2",
           "PSM_ZENOH__MULTICAST": "off", "PSM_ARM__DT_S": "0.004", "PSM_ZENOH__LISTEN": '["tcp/0.0.0.0:1"]'}
    cfg = load_config(ArmConfig, f, env=env)
    assert cfg.prefix == "envcell"
    assert cfg.zenoh.connect == ["tcp/a:1", "tcp/b:2"]
    assert cfg.zenoh.listen == ["tcp/0.0.0.0:1"]
    assert cfg.zenoh.multicast is False
    assert cfg.zenoh.mode == "client"  # from the file: env merges per field, not per table
    assert cfg.arm.dt_s == 0.004
    assert cfg.arm.joints == 6
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    args = parser.parse_args(["--config", str(f), "--prefix", "clicell", "--multicast",
                              "--set", "arm.dt_s=0.008", "--mode", "peer", "--low-latency",
                              "--set", "arm.offset=[1, 2, 3]"])
    cfg = config_from_args(ArmConfig, args, env=env)
    assert (cfg.prefix, cfg.zenoh.multicast, cfg.arm.dt_s, cfg.zenoh.mode, cfg.zenoh.low_latency) == (
        "clicell", True, 0.008, "peer", True)
    assert cfg.arm.joints == 6 and cfg.arm.offset == [1.0, 2.0, 3.0]
    assert config_from_args(ArmConfig, parser.parse_args([]), env={}).zenoh.low_latency is False


def test_a_stack_file_section_of_another_service_is_ignored(tmp_path: Path) -> None:
    f = tmp_path / "stack.toml"
    f.write_text('[arm]\njoints = 5\n[goal_tracker]\nanything = 1\n[goal_tracker.camera]\nsource = "x"\n')
    assert load_config(ArmConfig, f, env={}).arm.joints == 5
    assert load_config(ServiceConfig, f, env={}).prefix == "psm"


def test_env_var_names() -> None:
    assert env_var_name("zenoh.mode") == "PSM_ZENOH__MODE"
    assert env_var_name("prefix") == "PSM_PREFIX"
    assert env_var_name("goal_tracker.camera.source") == "PSM_GOAL_TRACKER__CAMERA__SOURCE"


def test_override_values_parse_as_toml() -> None:
    assert parse_override("0.001") == 0.001
    assert parse_override("true") is True
    assert parse_override("[1, 2]") == [1, 2]
    assert parse_override("psm2") == "psm2"


@pytest.mark.parametrize(
    ("env", "overrides", "toml", "expected"),
    [
        ({"PSM_ZENOH__MODE": "x"}, {}, None,
         "config error: zenoh.mode (from $PSM_ZENOH__MODE): Input should be 'peer', 'client' or 'router'"),
        ({}, {"zenoh.mode": "x"}, None,
         "config error: zenoh.mode: Input should be 'peer', 'client' or 'router' (got 'x')"),
        ({}, {}, '[zenoh]\nmode = "x"\n',
         "config error: zenoh.mode: Input should be 'peer', 'client' or 'router' (got 'x')"),
        ({}, {}, "[zenoh]\nmulticast = 3\n", "config error: zenoh.multicast: Input should be a valid"),
        ({}, {}, "[arm]\ndt_s = -1\n", "config error: arm.dt_s: Input should be greater than 0 (got -1)"),
        ({}, {}, '[arm]\ndt_s = "fast"\n', "config error: arm.dt_s: Input should be a valid number"),
        ({}, {}, "[arm]\ncolour = 1\n", "config error: arm.colour: unknown field"),
        ({}, {}, "arm = 3\n", "config error: arm: Input should be a valid dictionary"),
        ({}, {}, "prefx = 'typo'\n", "config error: prefx: unknown field"),
        ({}, {}, "[arm]\njoints = 13\n", "config error: arm.joints: unlucky"),
        ({}, {}, "[arm]\noffset = [1, 2]\n", "config error: arm.offset: expected 3 numbers, got 2"),
        ({"PSM_ARM__JOINTS": "seven"}, {}, None,
         "config error: arm.joints (from $PSM_ARM__JOINTS): Input should be a valid integer"),
        ({}, {"zenoh.connect": ["localhost"]}, None,
         "config error: zenoh.connect: expected endpoints like 'tcp/HOST:PORT', got 'localhost'"),
        ({}, {"prefix": "a/*"}, None, "config error: prefix: invalid prefix chunk '*'"),
        ({}, {"zenoh.mode": "client", "zenoh.multicast": False}, None,
         "config error: zenoh.connect: client mode with multicast off needs"),
        ({}, {"nope": 1}, None, "config error: nope: unknown field"),
        ({}, {"arm.nope": 1}, None, "config error: arm.nope: unknown field"),
        ({}, {"clock": "fast"}, None, "config error: clock: Input should be 'realtime' or 'lockstep'"),
    ],
)
def test_errors_are_one_line_naming_the_field(env, overrides, toml, expected, tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = None
    if toml is not None:
        path = tmp_path / "c.toml"
        path.write_text(toml)
    with pytest.raises(ConfigError) as ei:
        load_config(ArmConfig, path, env=env, overrides=overrides)
    msg = str(ei.value)
    assert msg.startswith(expected), msg
    assert "\n" not in msg


def test_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(ServiceConfig, tmp_path / "missing.toml", env={})
    bad = tmp_path / "bad.toml"
    bad.write_text("prefix = [\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(ServiceConfig, bad, env={})


def test_env_ignores_unrelated_vars() -> None:
    cfg = load_config(ServiceConfig, env={"PSM_SOMETHING_ELSE": "x", "HOME": "/", "PSM_ARM__DT_S": "1"})
    assert cfg.prefix == "psm"


def test_no_default_is_written_twice() -> None:
    """The service sections are the parameter models they feed (subclasses), not copies."""
    from services.arm.config import ArmSection
    from services.arm.sim import ArmSimConfig
    from services.goal_tracker.config import DetectorSection, FilterSection
    from services.goal_tracker.detectors import HaarParams, PipelineParams, YuNetParams
    from services.goal_tracker.kalman import KalmanParams

    for section, params in ((ArmSection, ArmSimConfig), (FilterSection, KalmanParams),
                            (DetectorSection, PipelineParams), (DetectorSection, HaarParams),
                            (DetectorSection, YuNetParams)):
        assert issubclass(section, params)
        for name in params.model_fields:
            assert section.model_fields[name].default == params.model_fields[name].default
        own = set(section.__annotations__)
        twice = own & set(params.model_fields)
        assert not twice, f"{section.__name__} redefines {twice}"
