"""The config files shipped in configs/ load and validate with every service's config class."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.arm.config import ArmConfig
from services.bus.config import ServiceConfig, load_config
from services.bus.echo import EchoConfig
from services.bus.recorder import RecorderConfig
from services.bus.replayer import ReplayerConfig
from services.goal_tracker.config import TrackerConfig

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize(
    "cls", [ServiceConfig, ArmConfig, TrackerConfig, RecorderConfig, ReplayerConfig, EchoConfig]
)
def test_local_config_is_valid_for_every_service(cls: type) -> None:
    cfg = load_config(cls, CONFIGS / "local.toml", env={})
    assert cfg.zenoh.mode == "client"
    assert cfg.zenoh.connect == ["tcp/127.0.0.1:7447"]
    assert cfg.zenoh.multicast is False


def test_router_config_listens_on_loopback() -> None:
    cfg = load_config(ServiceConfig, CONFIGS / "router.toml", env={})
    assert cfg.zenoh.mode == "router"
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7447"]
    local = load_config(ServiceConfig, CONFIGS / "local.toml", env={})
    assert local.zenoh.connect == cfg.zenoh.listen  # the clients reach this router
