"""Typed config: TOML < env < CLI, validation with one-line errors naming the field."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from services.bus.config import (
    ConfigError,
    ServiceConfig,
    add_config_arguments,
    config_from_args,
    env_var_name,
    load_config,
    spec,
)


@dataclass
class ArmSection:
    dt_s: float = spec(0.002, "control period, s", gt=0.0, le=0.1)
    clock: str = spec("realtime", "clock", choices=("realtime", "lockstep"))
    joints: int = spec(7, "joint count", ge=1)


@dataclass
class ArmConfig(ServiceConfig):
    arm: ArmSection = field(default_factory=ArmSection)


def test_defaults() -> None:
    cfg = load_config(ArmConfig, env={})
    assert cfg.prefix == "psm" and cfg.zenoh.mode == "peer" and cfg.zenoh.multicast
    assert cfg.arm.dt_s == 0.002


def test_file_env_cli_precedence(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text(
        'prefix = "filecell"\n[zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\n'
        '[arm]\ndt_s = 0.001\nclock = "lockstep"\n'
    )
    cfg = load_config(ArmConfig, f, env={})
    assert (cfg.prefix, cfg.zenoh.mode, cfg.arm.dt_s) == ("filecell", "client", 0.001)
    env = {"PSM_PREFIX": "envcell", "PSM_ZENOH_CONNECT": "tcp/a:1, tcp/b:2",
           "PSM_MULTICAST": "off", "PSM_ARM_DT_S": "0.004", "PSM_ZENOH_LISTEN": "tcp/0.0.0.0:1"}
    cfg = load_config(ArmConfig, f, env=env)
    assert cfg.prefix == "envcell"
    assert cfg.zenoh.connect == ["tcp/a:1", "tcp/b:2"]
    assert cfg.zenoh.listen == ["tcp/0.0.0.0:1"]
    assert cfg.zenoh.multicast is False
    assert cfg.arm.dt_s == 0.004
    assert cfg.arm.clock == "lockstep"  # from the file, untouched by env
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    args = parser.parse_args(["--config", str(f), "--prefix", "clicell", "--multicast",
                              "--set", "arm.dt_s=0.008", "--mode", "peer", "--low-latency"])
    cfg = config_from_args(ArmConfig, args, env=env)
    assert (cfg.prefix, cfg.zenoh.multicast, cfg.arm.dt_s, cfg.zenoh.mode, cfg.zenoh.low_latency) == (
        "clicell", True, 0.008, "peer", True)
    assert config_from_args(ArmConfig, parser.parse_args([]), env={}).zenoh.low_latency is False


def test_env_var_names() -> None:
    assert env_var_name("zenoh.mode") == "PSM_ZENOH_MODE"
    assert env_var_name("prefix") == "PSM_PREFIX"


@pytest.mark.parametrize(
    ("env", "overrides", "toml", "expected"),
    [
        ({"PSM_ZENOH_MODE": "x"}, {}, None,
         "config error: zenoh.mode: expected one of peer|client|router, got 'x'"),
        ({}, {"zenoh.mode": "x"}, None,
         "config error: zenoh.mode: expected one of peer|client|router, got 'x'"),
        ({}, {}, '[zenoh]\nmode = "x"\n',
         "config error: zenoh.mode: expected one of peer|client|router, got 'x'"),
        ({}, {}, "[zenoh]\nmulticast = 3\n",
         "config error: zenoh.multicast: expected a boolean (true/false), got 3"),
        ({}, {}, "[arm]\ndt_s = -1\n", "config error: arm.dt_s: expected a value > 0.0, got -1.0"),
        ({}, {}, '[arm]\ndt_s = "fast"\n', "config error: arm.dt_s: expected a number, got 'fast'"),
        ({}, {}, "[arm]\ncolour = 1\n", "config error: arm.colour: unknown field"),
        ({}, {}, 'arm = 3\n', "config error: arm: expected a table, got 3"),
        ({"PSM_ARM_JOINTS": "seven"}, {}, None,
         "config error: arm.joints (from $PSM_ARM_JOINTS): expected an integer, got 'seven'"),
        ({}, {"zenoh.connect": ["localhost"]}, None,
         "config error: zenoh.connect: expected endpoints like 'tcp/HOST:PORT', got 'localhost'"),
        ({}, {"prefix": "a/*"}, None, "config error: prefix: invalid prefix chunk '*'"),
        ({}, {"zenoh.mode": "client", "zenoh.multicast": False}, None,
         "config error: zenoh.connect: client mode with multicast off needs"),
        ({}, {"nope": 1}, None, "config error: nope: unknown field"),
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
    cfg = load_config(ServiceConfig, env={"PSM_SOMETHING_ELSE": "x", "HOME": "/"})
    assert cfg.prefix == "psm"
