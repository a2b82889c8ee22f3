"""The config files shipped in configs/ load and validate with every service's config class."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.arm.config import ArmConfig
from services.bus.config import ServiceConfig, load_config
from services.bus.echo import EchoConfig
from services.bus.recorder import RecorderConfig
from services.bus.replayer import ReplayerConfig
from services.bus.router import RouterConfig
from services.goal_tracker.config import TrackerConfig
from services.stack import load_stack

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize(
    "cls", [ServiceConfig, ArmConfig, TrackerConfig, RecorderConfig, ReplayerConfig, EchoConfig]
)
def test_the_stack_file_is_valid_for_every_service(cls: type) -> None:
    cfg = load_config(cls, CONFIGS / "stack.toml", env={})
    # Peers that find each other through the router and link directly, on loopback only.
    assert cfg.zenoh.mode == "peer"
    assert cfg.zenoh.connect == ["tcp/127.0.0.1:7447"]
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:0"]
    assert cfg.zenoh.multicast is False


def test_the_router_listens_where_the_clients_connect() -> None:
    cfg = load_config(RouterConfig, CONFIGS / "stack.toml", env={})
    assert cfg.session_config().mode == "router"
    assert cfg.session_config().listen == ["tcp/127.0.0.1:7447"]
    assert load_config(ServiceConfig, CONFIGS / "stack.toml", env={}).zenoh.connect == cfg.router.listen


def test_the_default_stack_validates_every_process() -> None:
    stack = load_stack(CONFIGS / "stack.toml", env={})
    names = [p.name for p in stack.processes]
    assert names == ["router", "recorder", "arm", "camera", "goal_tracker", "obstacle_monitor", "planner"]
    assert stack.configs["camera"].goal_tracker.synthetic.clock == "arm"  # type: ignore[attr-defined]
