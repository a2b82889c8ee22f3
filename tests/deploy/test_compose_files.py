"""The compose files are the stack file's, and what they set is valid config (no engine needed)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from services.bus.acl import ROLE_NAMES
from services.bus.config import ConfigError
from services.compose import compose_files, write_compose
from services.stack import config_class, load_stack
from tests.deploy.conftest import COMPOSE_VERSIONS, DOCKER_DIR, ROOT, compose_commands

STACK = load_stack(ROOT / "configs" / "stack.toml")


def _doc(name: str) -> dict[str, Any]:
    return yaml.safe_load((DOCKER_DIR / name).read_text())  # type: ignore[no-any-return]


def test_the_committed_compose_files_are_generated_from_the_stack_file() -> None:
    stale = write_compose(STACK, DOCKER_DIR, check=True)
    assert not stale, f"docker/{stale} differ from `psm compose` (re-run it and commit)"


def test_every_process_is_a_service_with_its_needs_limits_and_command() -> None:
    services = _doc("compose.yaml")["services"]
    assert list(services) == [p.name for p in STACK.processes]
    for p in STACK.processes:
        svc = services[p.name]
        assert svc["command"][: len(p.command) + 1] == ["psm", *p.command]
        assert set(svc.get("depends_on", {})) == set(p.needs)
        assert all(v == {"condition": "service_healthy"} for v in svc.get("depends_on", {}).values())
        assert svc["cpus"] == p.cpus and svc["mem_limit"] == f"{p.memory_mb}m"
        assert svc["restart"] == (f"on-failure:{p.max_restarts}" if p.restart == "on-failure" else p.restart)
        assert svc["healthcheck"]["test"][0] == "CMD-SHELL"
        assert not str(svc["user"]).startswith("0")
        # Access control always: the router enforces the roles, every other process logs in
        # as its role with its own secret.
        if p.name == "router":
            assert svc["environment"]["PSM_ROUTER__ACCESS_CONTROL"] == "true"
        else:
            assert svc["environment"]["PSM_ZENOH__USER"] == p.name in ROLE_NAMES
            assert svc["secrets"] == [f"psm_{p.name}"]
            # ... as a client of the router, so that every message passes its rules (the stack
            # file's processes are peers, which would link to each other past it).
            assert STACK.configs[p.name].zenoh.mode == "peer"
            assert svc["environment"]["PSM_ZENOH__MODE"] == "client"
            assert svc["environment"]["PSM_ZENOH__LISTEN"] == "[]"


def test_the_environment_of_every_container_is_valid_config(tmp_path: Path) -> None:
    """Each container's environment on top of the stack file loads without error and sets
    what it means to (a misspelt variable would be silently ignored, so check the values).
    The secrets compose mounts under /run/secrets are files of a ``psm secrets`` directory."""
    from services.bus.credentials import write_secrets

    write_secrets(tmp_path)
    doc = _doc("compose.yaml")
    services = doc["services"]
    mounted = {name: Path(spec["file"].replace("${PSM_SECRETS_DIR:-./secrets}", str(tmp_path)))
               for name, spec in doc["secrets"].items()}
    for p in STACK.processes:
        env = {k: str(v) for k, v in services[p.name]["environment"].items()}
        assert env.pop("RUST_LOG") == "${RUST_LOG:-}"  # zenoh's log filter, from the host
        assert set(services[p.name]["secrets"]) <= set(mounted)
        for name in services[p.name]["secrets"]:
            env = {k: v.replace(f"/run/secrets/{name}", str(mounted[name])) for k, v in env.items()}
        cfg = config_class(p.command)
        from services.bus.config import load_config

        loaded = load_config(cfg, STACK.path, env=env).model_dump()
        for var, value in env.items():
            path = var.removeprefix("PSM_").lower().split("__")
            node: Any = loaded
            for part in path:
                assert part in node, f"{p.name}: {var} names no config field"
                node = node[part]
            if isinstance(node, list):
                ok = node == json.loads(value) if value.startswith("[") else value in node
            else:
                ok = str(node).lower() == value.lower()
            assert ok, (p.name, var, node)


def test_the_camera_host_shares_only_the_router_endpoint() -> None:
    cam = _doc("compose.camera-host.yaml")["services"]
    assert set(cam) == {"camera", "goal_tracker"}
    for svc in cam.values():
        assert "PSM_ROUTER_HOST" in svc["environment"]["PSM_ZENOH__CONNECT"]
        assert set(svc.get("depends_on", {})) <= {"camera", "goal_tracker"}
    remote = _doc("compose.remote-camera.yaml")["services"]
    assert {n: s["profiles"] for n, s in remote.items()} == {
        "camera": ["local-camera"], "goal_tracker": ["local-camera"]}


def test_the_camera_overrides_stream_a_real_camera() -> None:
    device = _doc("compose.camera-device.yaml")["services"]["camera"]
    assert device["command"][:3] == ["psm", "camera", "stream"]
    assert "/dev/video0:/dev/video0" in device["devices"]
    url = _doc("compose.camera-url.yaml")["services"]["camera"]
    assert "${PSM_CAMERA_URL" in " ".join(url["command"])


def test_a_cpu_affinity_becomes_the_containers_cpuset() -> None:
    stack = load_stack(ROOT / "configs" / "stack.toml")
    arm = next(p for p in stack.processes if p.name == "arm")
    arm.cpu_affinity = [1, 3]
    services = yaml.safe_load(compose_files(stack)["compose.yaml"])["services"]
    assert services["arm"]["cpuset"] == "1,3"
    assert all("cpuset" not in svc for name, svc in services.items() if name != "arm")


def test_a_stack_without_a_router_is_a_config_error() -> None:
    stack = load_stack(ROOT / "configs" / "stack.toml")
    stack.processes = [p for p in stack.processes if p.name != "router"]
    with pytest.raises(ConfigError, match="needs a router process"):
        compose_files(stack)


@pytest.mark.parametrize("compose", list(COMPOSE_VERSIONS))
@pytest.mark.parametrize("files", [
    ["compose.yaml"],
    ["compose.yaml", "compose.remote-camera.yaml"],
    ["compose.yaml", "compose.camera-device.yaml"],
    ["compose.yaml", "compose.camera-url.yaml"],
    ["compose.yaml", "compose.realtime.yaml"],
    ["compose.yaml", "compose.remote-camera.yaml", "compose.realtime.yaml"],
    ["compose.yaml", "compose.lockstep.yaml"],
    ["compose.yaml", "compose.remote-camera.yaml", "compose.lockstep.yaml"],
    ["compose.camera-host.yaml"],
])
def test_compose_accepts_the_files(files: list[str], compose: str) -> None:
    """``config -q`` of docker compose v2 and of docker-compose 1.29 accepts every combination
    of the files the docs give (without an engine)."""
    installed = compose_commands()
    if compose not in installed:
        if os.environ.get("PSM_REQUIRE_DOCKER") == "1":
            pytest.fail(f"PSM_REQUIRE_DOCKER=1 but compose {compose} is not installed")
        pytest.skip(f"compose {compose} not installed (docker/install-compose-v2.sh)")
    argv = list(installed[compose])
    for f in files:
        argv += ["-f", str(DOCKER_DIR / f)]
    env = {"PATH": "/usr/bin:/bin", "PSM_ROUTER_HOST": "arm-host", "PSM_CAMERA_URL": "rtsp://cam/1"}
    res = subprocess.run([*argv, "config", "-q"], capture_output=True, text=True, timeout=60, env=env,
                         cwd=DOCKER_DIR, check=False)
    assert res.returncode == 0, res.stderr


def test_the_image_and_the_compose_files_agree_on_the_health_file_and_user() -> None:
    from services.compose import HEALTH_FILE, USER

    dockerfile = (DOCKER_DIR / "Dockerfile").read_text()
    assert f"ENV PSM_HEALTH_FILE={HEALTH_FILE}" in dockerfile
    assert HEALTH_FILE in dockerfile.split("HEALTHCHECK", 1)[1]
    uid = USER.split(":-", 1)[1].split("}", 1)[0]
    assert f"USER {uid}:{uid}" in dockerfile


def test_the_realtime_override_runs_the_control_loop_at_sched_fifo_within_the_engines_budget() -> None:
    from services.compose import PSM_SCRIPT, RT_PERIOD_US, RT_PYTHON, RT_SHARE

    services = _doc("compose.realtime.yaml")["services"]
    main = _doc("compose.yaml")["services"]
    rt = [p.name for p in STACK.processes
          if any(getattr(getattr(STACK.configs[p.name], f), "rt_priority", 0)
                 for f in type(STACK.configs[p.name]).model_fields)]
    assert rt and list(services) == rt
    assert {"router", "arm", "planner", "obstacle_monitor"} <= set(rt)
    for name, svc in services.items():
        assert svc["command"][:2] == [RT_PYTHON, PSM_SCRIPT]
        assert svc["command"][2:] == main[name]["command"][1:], "the same psm command as compose.yaml"
        assert svc["cap_add"] == ["SYS_NICE"]
        assert svc["cpu_rt_period"] == RT_PERIOD_US
    assert sum(s["cpu_rt_runtime"] for s in services.values()) <= RT_SHARE * RT_PERIOD_US
    # The image makes python-rt: the venv's interpreter with CAP_SYS_NICE as a file capability.
    dockerfile = (DOCKER_DIR / "Dockerfile").read_text()
    assert f"setcap cap_sys_nice+ep {RT_PYTHON}" in dockerfile


def test_the_lockstep_override_puts_every_process_on_the_lockstep_clock(tmp_path: Path) -> None:
    """Each process of compose.lockstep.yaml loads its config with ``clock = lockstep``."""
    from services.bus.config import load_config

    services = _doc("compose.lockstep.yaml")["services"]
    assert list(services) == [p.name for p in STACK.processes]
    for p in STACK.processes:
        env = {k: str(v) for k, v in services[p.name]["environment"].items()}
        assert load_config(config_class(p.command), STACK.path, env=env).clock == "lockstep", p.name
