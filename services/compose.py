"""``psm compose``: the docker compose files of a stack file, generated so the two cannot drift.

The stack file (``configs/stack.toml``) is the one description of the dataflow; the compose
files under ``docker/`` are derived from it and committed, and a test checks that they are
what ``psm compose`` writes today (``psm compose --check``). One image runs every process
(``docker/Dockerfile``); each container runs ``psm <command> --config /app/configs/<stack>``
and reads its own tables, exactly as under ``psm up``. What differs in a container is given
as environment variables (the stack file's override layer):

- every client connects to the router container (``PSM_ZENOH__CONNECT=tcp/router:7447``); the
  router listens on all interfaces of its network and publishes its port on the host
  (``PSM_ROUTER_BIND``, default ``127.0.0.1``; ``0.0.0.0`` for a camera on another machine);
- the recorder writes to ``/data`` (a host directory, ``PSM_DATA_DIR``, default
  ``out/compose``);
- access control is always on: every process authenticates as its role (its process name) with
  its own password (a docker secret from ``psm secrets docker/secrets``), and the router
  enforces the roles of ``services/bus/acl.py`` (docs/security.md).

``needs`` become ``depends_on`` with ``condition: service_healthy``; the healthcheck asks the
service's own status: the health file its status loop rewrites while it runs and is connected
to the router (``health_file``); the stack file's ``restart`` / ``max_restarts`` become the
restart policy (the planner ``on-failure``: a failed task exits 1 and the restarted planner
resumes it; a task done exits 0 and stays down); ``cpus`` / ``memory_mb`` become the
container limits.

Files written (relative to the output directory, ``docker/``):

- ``compose.yaml``: the whole stack on one host;
- ``compose.camera-device.yaml``: override: the camera container streams ``/dev/video0``;
- ``compose.camera-url.yaml``: override: the camera container streams ``PSM_CAMERA_URL``;
- ``compose.remote-camera.yaml``: override for the arm's host when the camera and the goal
  tracker run elsewhere: they are not started here;
- ``compose.camera-host.yaml``: a project of its own for the camera's host: the camera and the
  goal tracker, which share only the router's endpoint (``PSM_ROUTER_HOST``) with the rest;
- ``compose.realtime.yaml``: override: the processes with ``rt_priority`` (the control loop) run
  at ``SCHED_FIFO`` as they do under ``psm up``: the image's ``python-rt`` (the interpreter with
  the file capability ``CAP_SYS_NICE``) in a container granted ``SYS_NICE``, with a share of the
  engine's real-time budget (``cpu_rt_runtime``; the engine needs ``dockerd --cpu-rt-runtime``
  on kernels with real-time group scheduling, docs/deployment.md#real-time-scheduling);
- ``compose.lockstep.yaml``: override: every process on the stack's ``lockstep`` clock (the arm
  advances a tick only once the command for the previous state is in): a deterministic run that
  takes as long as the machine needs, never missing a deadline, as ``psm up --clock lockstep``
  (the compose tests use it, docs/deployment.md#lockstep).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from services.bus.config import ConfigError, env_var_name
from services.stack import DEFAULT_STACK, ProcessSpec, Stack, load_stack, routed_client_env

__all__ = ["COMPOSE_DIR", "compose_files", "register", "write_compose"]

ROOT = Path(__file__).resolve().parents[1]
#: Where the compose files live; the build context is its parent (the project).
COMPOSE_DIR = ROOT / "docker"
#: The project's directory inside the image.
APP_DIR = "/app"
IMAGE = "psm-dataflow:${PSM_IMAGE_TAG:-local}"
ROUTER_PORT = 7447
#: zenoh's log filter inside every container, passed from the host's environment
#: (``RUST_LOG=zenoh_transport=debug docker compose up``; unset: errors only).
RUST_LOG = "RUST_LOG"
#: The container user (the image's ``psm`` user unless PSM_UID/PSM_GID say otherwise).
USER = "${PSM_UID:-10001}:${PSM_GID:-10001}"
#: Every service rewrites this file at each status period while it runs and is connected to
#: the router (``health_file``, set by the image); healthy = rewritten within the last 6 s. A
#: check costs a ``find``, not a Python start (a bus query per check loaded 2 cores).
HEALTH_FILE = "/tmp/psm-health"
HEALTH_TEST = f'test -n "$(find {HEALTH_FILE} -mmin -0.1 2>/dev/null)"'
#: Healthcheck timing [s]: a check every HEALTH_INTERVAL_S, unhealthy after HEALTH_RETRIES.
HEALTH_INTERVAL_S = 5
HEALTH_TIMEOUT_S = 5
HEALTH_RETRIES = 5
#: cgroup CPU weight of the control loop's containers (the default is 1024).
CONTROL_CPU_SHARES = 4096
#: The interpreter with CAP_SYS_NICE in the image (docker/Dockerfile) and the console script
#: it runs in compose.realtime.yaml.
RT_PYTHON = "/opt/psm/bin/python-rt"
PSM_SCRIPT = "/opt/psm/bin/psm"
#: compose.realtime.yaml: the real-time containers share this fraction of the engine's
#: real-time runtime per period (each gets an equal part; the kernel refuses more than the
#: engine has, and a group over its budget is throttled until the period ends).
RT_PERIOD_US = 1_000_000
RT_SHARE = 0.9

#: Where the secrets of ``psm secrets`` are (relative to docker/ unless absolute).
SECRETS_DIR = "${PSM_SECRETS_DIR:-./secrets}"
#: Processes that belong to the camera's host in a two-host deployment.
CAMERA_PROCESSES = ("camera", "goal_tracker")


def _is_camera(p: ProcessSpec) -> bool:
    return tuple(p.command[:2]) in (("camera", "synth"), ("camera", "stream"))


def _is_router(p: ProcessSpec) -> bool:
    return tuple(p.command[:2]) == ("serve", "router")


def _restart_policy(p: ProcessSpec) -> str:
    """The process's restart policy in compose's words (``on-failure:N`` bounds the retries as
    ``max_restarts`` bounds them under ``psm up``)."""
    return f"on-failure:{p.max_restarts}" if p.restart == "on-failure" else p.restart


def _duration(seconds: float) -> str:
    return f"{seconds:g}s"


def _stack_in_image(stack: Stack) -> str:
    """The stack file's path inside the image (it must be under ``configs/``)."""
    path = stack.path.resolve()
    configs = ROOT / "configs"
    try:
        rel = path.relative_to(configs)
    except ValueError:
        raise ConfigError(
            "stack", f"{stack.path} is not under {configs} (mounted into the containers)"
        ) from None
    return f"{APP_DIR}/configs/{rel.as_posix()}"


class _Builder:
    """Builds the compose services of one stack."""

    def __init__(self, stack: Stack) -> None:
        self.stack = stack
        self.stack_file = _stack_in_image(stack)
        # A deployment publishes the router's port: access control is always on (the local
        # `psm up` on loopback has it as an option, [stack] access_control).
        self.acl = True
        self.router = next((p for p in stack.processes if _is_router(p)), None)
        if self.router is None:
            raise ConfigError("stack.processes", "a compose deployment needs a router process")
        self.names = {p.name for p in stack.processes}

    # --- pieces -------------------------------------------------------------------------
    def environment(self, p: ProcessSpec, connect: str) -> dict[str, str]:
        env: dict[str, str] = {}
        if _is_router(p):
            env[env_var_name("router.listen")] = f"tcp/0.0.0.0:{ROUTER_PORT}"
            if self.acl:
                env[env_var_name("router.access_control")] = "true"
                env[env_var_name("router.users_file")] = "/run/secrets/psm_users"
        else:
            env[env_var_name("zenoh.connect")] = connect
        if p.command[:1] == ["record"]:
            cfg = self.stack.configs[p.name]
            output = Path(cfg.recorder.output).name  # type: ignore[attr-defined]
            env[env_var_name("recorder.output")] = f"/data/{output}"
        if self.acl and not _is_router(p):
            env.update(routed_client_env())
            env[env_var_name("zenoh.user")] = p.name
            env[env_var_name("zenoh.password_file")] = f"/run/secrets/psm_{p.name}"
        env[RUST_LOG] = "${RUST_LOG:-}"  # zenoh's own log filter, from the host (empty: errors)
        return env

    def healthcheck(self) -> dict[str, Any]:
        return {
            "test": ["CMD-SHELL", HEALTH_TEST.replace("$", "$$")],  # compose interpolates $
            "interval": _duration(HEALTH_INTERVAL_S),
            "timeout": _duration(HEALTH_TIMEOUT_S),
            "retries": HEALTH_RETRIES,
            "start_period": _duration(self.stack.config.stack.startup_timeout_s),
        }

    def service(self, p: ProcessSpec, *, connect: str, needs: list[str]) -> dict[str, Any]:
        svc: dict[str, Any] = {
            "image": IMAGE,
            "build": {"context": "..", "dockerfile": "docker/Dockerfile",
                      "args": {"BASE_IMAGE": "${PSM_BASE_IMAGE:-python:3.11-slim}"}},
            "command": ["psm", *p.command, "--config", self.stack_file],
            "user": USER,
            "init": True,
            "environment": self.environment(p, connect),
            "volumes": ["../configs:/app/configs:ro"],
            "healthcheck": self.healthcheck(),
            "restart": _restart_policy(p),
            "stop_grace_period": _duration(self.stack.config.stack.stop_timeout_s),
            "cpus": p.cpus,
            "mem_limit": f"{p.memory_mb}m",
        }
        if p.cpu_affinity:
            svc["cpuset"] = ",".join(str(c) for c in p.cpu_affinity)
        if self.realtime(p):
            # The control loop (arm -> router -> planner) wins the CPU under contention
            # (cgroup weight; SCHED_FIFO with compose.realtime.yaml).
            svc["cpu_shares"] = CONTROL_CPU_SHARES
        if needs:
            svc["depends_on"] = {n: {"condition": "service_healthy"} for n in needs}
        if _is_router(p):
            bind = "${PSM_ROUTER_BIND:-127.0.0.1}"
            svc["ports"] = [f"{bind}:${{PSM_ROUTER_PORT:-{ROUTER_PORT}}}:{ROUTER_PORT}"]
        if p.command[:1] == ["record"]:
            svc["volumes"].append("${PSM_DATA_DIR:-../out/compose}:/data")
        if p.command[:1] == ["plan"]:
            svc["volumes"].append("models:/app/out/models")
        if self.acl:
            svc["secrets"] = ["psm_users"] if _is_router(p) else [f"psm_{p.name}"]
        return svc

    def realtime_override(self) -> dict[str, Any]:
        """The control loop at SCHED_FIFO: ``python-rt``, ``SYS_NICE`` and real-time runtime."""
        rt = [p for p in self.stack.processes if self.realtime(p)]
        runtime_us = int(RT_PERIOD_US * RT_SHARE / max(len(rt), 1)) // 1000 * 1000
        services = {
            p.name: {
                "command": [RT_PYTHON, PSM_SCRIPT, *p.command, "--config", self.stack_file],
                "cap_add": ["SYS_NICE"],
                "cpu_rt_period": RT_PERIOD_US,
                "cpu_rt_runtime": runtime_us,
            }
            for p in rt
        }
        return {"services": services}

    def lockstep_override(self) -> dict[str, Any]:
        """Every process on the stack's lockstep clock (the stack file's ``clock``)."""
        env = {env_var_name("clock"): "lockstep"}
        return {"services": {p.name: {"environment": dict(env)} for p in self.stack.processes}}

    def realtime(self, p: ProcessSpec) -> bool:
        """The process asks for real-time scheduling (``rt_priority`` in one of its sections)."""
        cfg = self.stack.configs.get(p.name)
        sections = [getattr(cfg, name) for name in type(cfg).model_fields] if cfg is not None else []
        return any(getattr(sec, "rt_priority", 0) for sec in sections)

    def secrets(self, processes: list[ProcessSpec]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for p in processes:
            if _is_router(p):
                out["psm_users"] = {"file": f"{SECRETS_DIR}/users.txt"}
            else:
                out[f"psm_{p.name}"] = {"file": f"{SECRETS_DIR}/{p.name}.password"}
        return out

    # --- files --------------------------------------------------------------------------
    def main(self) -> dict[str, Any]:
        """Every process of the stack on one host."""
        assert self.router is not None
        connect = f"tcp/{self.router.name}:{ROUTER_PORT}"
        services = {
            p.name: self.service(p, connect=connect, needs=[n for n in p.needs if n in self.names])
            for p in self.stack.processes
        }
        doc: dict[str, Any] = {"services": services, "volumes": {"models": {}}}
        if self.acl:
            doc["secrets"] = self.secrets(self.stack.processes)
        return doc

    def camera_override(self, command: list[str], extra: dict[str, Any]) -> dict[str, Any]:
        """The camera container streams a real camera instead of the synthetic one."""
        cameras = [p for p in self.stack.processes if _is_camera(p)]
        if not cameras:
            return {"services": {}}
        p = cameras[0]
        svc: dict[str, Any] = {"command": ["psm", *command, "--config", self.stack_file], **extra}
        return {"services": {p.name: svc}}

    def remote_camera(self) -> dict[str, Any]:
        """Override for the arm's host: the camera's processes run on the camera's host."""
        return {"services": {p.name: {"profiles": ["local-camera"]}
                             for p in self.stack.processes if p.name in CAMERA_PROCESSES}}

    def camera_host(self) -> dict[str, Any]:
        """The camera's host: its processes, connected only to the router's endpoint."""
        connect = f"tcp/${{PSM_ROUTER_HOST:?set PSM_ROUTER_HOST to the arm host's address}}:" \
                  f"${{PSM_ROUTER_PORT:-{ROUTER_PORT}}}"
        processes = [p for p in self.stack.processes if p.name in CAMERA_PROCESSES]
        services = {}
        for p in processes:
            svc = self.service(p, connect=connect, needs=[n for n in p.needs if n in CAMERA_PROCESSES])
            svc["extra_hosts"] = ["host.docker.internal:host-gateway"]
            services[p.name] = svc
        doc: dict[str, Any] = {"services": services}
        if self.acl:
            doc["secrets"] = self.secrets(processes)
        return doc


def _yaml(doc: dict[str, Any], header: str) -> str:
    import yaml

    class Dumper(yaml.SafeDumper):
        def ignore_aliases(self, data: Any) -> bool:
            return True

    def scalar_list(dumper: yaml.SafeDumper, data: list[Any]) -> Any:
        """Commands and healthchecks on one line: ``[psm, arm, --config, ...]``."""
        flow = all(isinstance(v, str | int | float) for v in data)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)

    Dumper.add_representer(list, scalar_list)
    return header + yaml.dump(doc, Dumper=Dumper, sort_keys=False, default_flow_style=False, width=100)


def compose_files(stack: Stack) -> dict[str, str]:
    """The compose files of ``stack``: file name -> YAML text."""
    b = _Builder(stack)
    try:
        source = stack.path.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        source = stack.path.name
    head = f"# Generated by `psm compose` from {source}; do not edit: edit the stack file and re-run.\n"
    camera = [p for p in stack.processes if _is_camera(p)]
    device_cmd = ["camera", "stream", "--device", "0"]
    url_cmd = ["camera", "stream", "--source", "url", "--uri", "${PSM_CAMERA_URL:?set PSM_CAMERA_URL}"]
    files = {
        "compose.yaml": _yaml(
            b.main(), head + "# The whole stack on one host: docker compose -f docker/compose.yaml up\n"
        ),
        "compose.remote-camera.yaml": _yaml(
            b.remote_camera(),
            head + "# The arm's host when the camera and goal tracker run on another one "
            "(compose.camera-host.yaml):\n#   docker compose -f docker/compose.yaml "
            "-f docker/compose.remote-camera.yaml up\n",
        ),
        "compose.camera-host.yaml": _yaml(
            b.camera_host(),
            head + "# The camera's host: PSM_ROUTER_HOST=<arm host> docker compose -f "
            "docker/compose.camera-host.yaml up\n",
        ),
    }
    files["compose.realtime.yaml"] = _yaml(
        b.realtime_override(),
        head + "# The control loop at SCHED_FIFO (the engine: dockerd --cpu-rt-runtime=<us>, "
        "docs/deployment.md):\n#   docker compose -f docker/compose.yaml "
        "-f docker/compose.realtime.yaml up\n",
    )
    files["compose.lockstep.yaml"] = _yaml(
        b.lockstep_override(),
        head + "# Every process on the lockstep clock: deterministic, as fast as the machine allows "
        "(docs/deployment.md):\n#   docker compose -f docker/compose.yaml "
        "-f docker/compose.lockstep.yaml up\n",
    )
    if camera:
        files["compose.camera-device.yaml"] = _yaml(
            b.camera_override(device_cmd, {"devices": ["/dev/video0:/dev/video0"], "group_add": ["video"]}),
            head + "# A camera device instead of the synthetic camera:\n#   docker compose -f "
            "docker/compose.yaml -f docker/compose.camera-device.yaml up\n",
        )
        files["compose.camera-url.yaml"] = _yaml(
            b.camera_override(url_cmd, {}),
            head + "# A stream URL instead of the synthetic camera:\n#   PSM_CAMERA_URL=rtsp://... "
            "docker compose -f docker/compose.yaml -f docker/compose.camera-url.yaml up\n",
        )
    return files


def write_compose(stack: Stack, out_dir: Path, *, check: bool = False) -> list[str]:
    """Write the compose files of ``stack`` into ``out_dir``; with ``check`` write nothing and
    return the names of the files that differ from what would be written."""
    stale = []
    if not check:
        out_dir.mkdir(parents=True, exist_ok=True)
    for name, text in compose_files(stack).items():
        path = out_dir / name
        old = path.read_text() if path.exists() else None
        if old != text:
            stale.append(name)
            if not check:
                path.write_text(text)
    return stale


def _cmd_compose(args: argparse.Namespace) -> int:
    stack = load_stack(args.stack or DEFAULT_STACK)
    out = Path(args.out) if args.out else COMPOSE_DIR
    stale = write_compose(stack, out, check=args.check)
    if args.check:
        if stale:
            print(f"out of date in {out}: {', '.join(stale)} (run `psm compose`)")
            return 1
        print(f"{out}: up to date with {stack.path}")
        return 0
    print(f"{out}: {'wrote ' + ', '.join(stale) if stale else 'up to date'}")
    return 0


def register(subparsers: Any) -> None:
    """Add ``compose``."""
    p = subparsers.add_parser(
        "compose", help="write the docker compose files of a stack file",
        description="Generate docker/compose*.yaml from the stack file (default "
        "configs/stack.toml): one container per process, the router's endpoint, healthchecks, "
        "restart policies and limits. --check exits 1 when the committed files differ.",
    )
    p.add_argument("stack", nargs="?", metavar="STACK.toml", help="stack file (default configs/stack.toml)")
    p.add_argument("--out", metavar="DIR", help="output directory (default docker/)")
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file is out of date")
    p.set_defaults(func=_cmd_compose)


def main(argv: list[str] | None = None) -> int:
    """``python -m services.compose``."""
    from services.cli import module_main

    return module_main(register, "python -m services.compose", argv)
