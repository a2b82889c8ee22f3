"""The stack file: one description of the whole dataflow (``configs/stack.toml``).

A stack file is a service config file that every process of the stack reads: the shared bus
settings at the top (``prefix``, ``clock``, ``[zenoh]``, logging), one table per service
(``[router]``, ``[arm]``, ``[goal_tracker]``, ``[recorder]``, ...) and a ``[stack]`` table that
says which processes run, in start order::

    prefix = "psm"
    clock = "realtime"
    [zenoh]
    mode = "peer"
    connect = ["tcp/127.0.0.1:7447"]
    listen = ["tcp/127.0.0.1:0"]
    multicast = false

    [[stack.processes]]
    name = "router"
    command = ["serve", "router"]
    [[stack.processes]]
    name = "arm"
    command = ["arm"]

    [router]
    listen = ["tcp/127.0.0.1:7447"]
    [arm]
    dt_s = 0.002

Each process is ``psm <command...> --config <stack file>``; it reads the shared keys and its own
tables and ignores the others'. :func:`load_stack` validates the whole file at once: the
``[stack]`` table, every process's own config (so a bad ``[arm]`` value is reported before
anything starts) and that every table belongs to some process.
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field

from services.bus.config import (
    ConfigError,
    Section,
    ServiceConfig,
    StrList,
    env_var_name,
    load_config,
    read_toml,
)
from services.viewer.config import ViewerSection

__all__ = [
    "COMMANDS",
    "DEFAULT_STACK",
    "ProcessSpec",
    "Stack",
    "StackConfig",
    "StackSection",
    "config_class",
    "load_stack",
    "real_camera_overrides",
    "use_camera",
]

#: The stack the README's demo runs when no stack file is given.
DEFAULT_STACK = Path(__file__).resolve().parents[1] / "configs" / "stack.toml"

#: The bus settings of every process but the router when the router enforces access control
#: (``[stack] access_control``, and every docker compose deployment): a client of the router that
#: listens on nothing, so that every message passes the router's rules. A peer would link to the
#: other peers directly, past them. Applied over the stack file and the environment; an explicit
#: ``--set zenoh.mode=peer`` is an error instead.
ROUTED_CLIENT: dict[str, Any] = {"zenoh.mode": "client", "zenoh.listen": []}


def routed_client_env() -> dict[str, str]:
    """:data:`ROUTED_CLIENT` as the environment variables of a process (``PSM_ZENOH__MODE``, ...)."""
    return {env_var_name(k): v if isinstance(v, str) else json.dumps(v) for k, v in ROUTED_CLIENT.items()}


@dataclass(frozen=True)
class Command:
    """A ``psm`` sub-command that can run in a stack: its config model (``module:Class``,
    imported when needed) and the name of the liveliness token it declares (``None``: the
    process's name)."""

    config: str
    service: str | None = None

    def config_class(self) -> type[ServiceConfig]:
        """The config model."""
        module, _, name = self.config.partition(":")
        return getattr(importlib.import_module(module), name)  # type: ignore[no-any-return]


#: The sub-commands a stack can run, by their words after ``psm``.
COMMANDS: dict[tuple[str, ...], Command] = {
    ("serve", "router"): Command("services.bus.router:RouterConfig", "router"),
    ("arm",): Command("services.arm.config:ArmConfig", "arm"),
    ("arm", "probe"): Command("services.bus.config:ServiceConfig", "probe"),
    ("camera", "synth"): Command("services.goal_tracker.config:TrackerConfig", "camera_synth"),
    ("camera", "stream"): Command("services.goal_tracker.config:TrackerConfig", "camera"),
    ("track",): Command("services.goal_tracker.config:TrackerConfig", "goal_tracker"),
    ("plan",): Command("services.planner.config:PlannerConfig", "planner"),
    ("obstacles",): Command("services.obstacle_monitor.config:ObstacleMonitorConfig", "obstacle_monitor"),
    ("record",): Command("services.bus.recorder:RecorderConfig", "recorder"),
    ("replay",): Command("services.bus.replayer:ReplayerConfig", "replayer"),
    ("echo",): Command("services.bus.echo:EchoConfig", "echo"),
    ("view",): Command("services.viewer.config:ViewerConfig", "viewer"),
}


def _command_of(argv: Sequence[str]) -> tuple[tuple[str, ...], Command]:
    """The longest registered command that ``argv`` starts with."""
    for n in (2, 1):
        words = tuple(argv[:n])
        if words in COMMANDS:
            return words, COMMANDS[words]
    known = ", ".join(" ".join(k) for k in COMMANDS)
    raise ValueError(f"{' '.join(argv)!r} is not a stack command (known: {known})")


def config_class(argv: Sequence[str]) -> type[ServiceConfig]:
    """The config model of the process ``psm <argv...>``."""
    return _command_of(argv)[1].config_class()


class ProcessSpec(Section):
    """One process of the stack (an entry of ``[[stack.processes]]``)."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_\-]+$", description="process name (logs, table)")
    command: StrList = Field(
        min_length=1, description="the psm sub-command and its own flags, e.g. ['track', '--source', 'topic']"
    )
    service: str = Field(
        "", description="liveliness name the process declares ('' = the command's, else the name)"
    )
    enabled: bool = Field(True, description="false: described but not started")
    ends_stack: bool = Field(
        False, description="when this process exits with code 0 the whole stack stops (e.g. the task is done)"
    )
    needs: StrList = Field(
        default_factory=list,
        description="processes (earlier in the list) that must be up before this one starts "
        "(docker compose: depends_on ... service_healthy)",
    )
    cpus: float = Field(1.0, gt=0.0, le=64.0, description="container CPU limit (docker compose) [cores]")
    cpu_affinity: list[Annotated[int, Field(ge=0, le=4095)]] = Field(
        default_factory=list,
        description="the CPUs (numbers) the process may run on, e.g. [1] to give the control loop a core "
        "of its own ([] = any; docker compose: cpuset)",
    )
    memory_mb: int = Field(
        1024, ge=64, le=1 << 20, description="container memory limit (docker compose) [MiB]"
    )
    restart: Literal["no", "on-failure", "always"] = Field(
        "no",
        description="restart the process when it exits: 'on-failure' after a non-zero exit code or a "
        "signal, 'always' after any exit (as docker compose's restart policies)",
    )
    max_restarts: int = Field(
        3, ge=0, le=1000, description="restarts allowed in one run; one more exit stops the stack"
    )
    required: bool = Field(
        True,
        description="false: the stack goes on without it when it exits and is not restarted (reported, and "
        "psm up's exit code is 1), e.g. the recorder: a lost recording does not stop the robot",
    )

    def check(self) -> None:
        """The command is one a stack can run; a process that ends the stack is not restarted
        after its clean exit."""
        try:
            _command_of(self.command)
        except ValueError as exc:
            raise ConfigError("command", str(exc)) from None
        if self.ends_stack and self.restart == "always":
            raise ConfigError("restart", "a process with ends_stack = true cannot restart 'always'")
        if len(set(self.cpu_affinity)) != len(self.cpu_affinity):
            raise ConfigError("cpu_affinity", f"lists a CPU twice: {self.cpu_affinity}")

    @property
    def is_router(self) -> bool:
        """Whether the process is a zenoh router (``psm serve router``)."""
        return tuple(self.command[:2]) == ("serve", "router")

    @property
    def service_name(self) -> str:
        """The liveliness token name the supervisor waits for."""
        return self.service or _command_of(self.command)[1].service or self.name


class StackSection(Section):
    """The ``[stack]`` table."""

    name: str = Field("local", min_length=1, description="name of the stack (logs, summary)")
    processes: list[ProcessSpec] = Field(min_length=1, description="processes, in start order")
    startup_timeout_s: float = Field(
        30.0, gt=0.0, le=600.0, description="wait this long for each process's liveliness token [s]"
    )
    stop_timeout_s: float = Field(
        10.0, gt=0.0, le=600.0, description="after SIGTERM, wait this long before SIGKILL [s]"
    )
    run_dir: str = Field("out/stack", description="process logs go to <run_dir>/<name>.log")
    access_control: bool = Field(
        False,
        description="run the bus with authentication and access control: psm up writes the "
        "credentials into <run_dir>/secrets, the router allows each process only what its "
        "role needs (the role is the process's name; docs/security.md)",
    )

    def check(self) -> None:
        """Process names are unique; a process needs only processes listed before it; with
        access control each process but the router is a role."""
        from services.bus.acl import ROLE_NAMES

        seen: set[str] = set()
        for i, p in enumerate(self.processes):
            if p.name in seen:
                raise ConfigError(f"processes[{i}].name", f"duplicate process name {p.name!r}")
            for need in p.needs:
                if need not in seen:
                    raise ConfigError(
                        f"processes[{i}].needs",
                        f"{need!r} is not a process listed before {p.name!r}",
                    )
            seen.add(p.name)
            if (self.access_control and p.enabled and not p.is_router
                    and p.name not in ROLE_NAMES):
                raise ConfigError(
                    f"processes[{i}].name",
                    f"{p.name!r} is no access-control role (roles: {', '.join(ROLE_NAMES)})",
                )


class StackConfig(ServiceConfig):
    """The supervisor's view of a stack file: the shared settings + ``[stack]``, and the
    ``[viewer]`` table (validated with the file: ``psm up --view`` adds the viewer process)."""

    stack: StackSection
    viewer: ViewerSection = Field(default_factory=ViewerSection)


def viewer_process(stack: StackConfig) -> ProcessSpec:
    """The process ``psm up --view`` adds: ``psm view``, not required (the stack goes on without
    it), never restarted, after the router."""
    routers = [p.name for p in stack.stack.processes if p.enabled and p.is_router]
    return ProcessSpec(name="viewer", command=["view"], needs=routers[:1], required=False,
                       cpus=0.5, memory_mb=256)


@dataclass
class Stack:
    """A validated stack file: the supervisor's config, the file, the processes to start and
    each one's config (the stack file as that process will read it)."""

    path: Path
    config: StackConfig
    processes: list[ProcessSpec]
    configs: dict[str, ServiceConfig]


def _overrides_for(cls: type[ServiceConfig], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """The overrides that address fields of ``cls`` (the others belong to other processes)."""
    return {k: v for k, v in overrides.items() if k.split(".", 1)[0] in cls.model_fields}


def load_stack(
    path: str | Path,
    *,
    overrides: Mapping[str, Any] | None = None,
    env: Mapping[str, str] | None = None,
    view: bool = False,
) -> Stack:
    """Load and validate a stack file (raises :class:`ConfigError` naming the process and the
    field). ``overrides`` (dotted path -> value) apply to every process that has the field.
    ``view``: add the live viewer (:func:`viewer_process`) right after the router, so it sees
    the stack from its first message."""
    path = Path(path)
    overrides = dict(overrides or {})
    config = load_config(StackConfig, path, overrides=_overrides_for(StackConfig, overrides), env=env)
    if view:
        _add_viewer(config)
    unknown_override = [
        k for k in overrides
        if not any(k.split(".", 1)[0] in cls.model_fields
                   for cls in [StackConfig, *(config_class(p.command) for p in config.stack.processes)])
    ]
    if unknown_override:
        raise ConfigError(unknown_override[0], "unknown field for every process of the stack")
    data = read_toml(path)
    processes = [p for p in config.stack.processes if p.enabled]
    configs: dict[str, ServiceConfig] = {}
    owned: set[str] = set(StackConfig.model_fields)
    for p in config.stack.processes:
        cls = config_class(p.command)
        owned |= set(cls.model_fields)
        if not p.enabled:
            continue
        try:
            own = _overrides_for(cls, overrides)
            if config.stack.access_control and not p.is_router:
                own = {**ROUTED_CLIENT, **own}
            configs[p.name] = load_config(cls, path, overrides=own, env=env)
        except ConfigError as exc:
            raise ConfigError(exc.path, f"{exc.reason} (process {p.name!r})") from None
    for key, value in data.items():
        if isinstance(value, dict) and key not in owned:
            raise ConfigError(key, "no process of the stack reads this table")
    if config.stack.access_control:
        for p in processes:
            if not p.is_router and configs[p.name].zenoh.mode != "client":
                raise ConfigError(
                    "zenoh.mode",
                    f"must be 'client' with stack.access_control (process {p.name!r}): a peer "
                    "links to other peers directly, past the router's access control",
                )
    return Stack(path, config, processes, configs)


def _add_viewer(config: StackConfig) -> None:
    """Insert :func:`viewer_process` after the stack's router (first if it has none)."""
    from pydantic import ValidationError

    from services.bus.config import config_error

    procs = list(config.stack.processes)
    if any(p.name == "viewer" or p.command[:1] == ["view"] for p in procs):
        raise ConfigError("stack.processes", "--view adds a process 'viewer' running 'psm view'; "
                          "the stack file already has one")
    at = next((i + 1 for i, p in enumerate(procs) if p.enabled and p.is_router), 0)
    procs.insert(at, viewer_process(config))
    try:
        config.stack = StackSection(**{**dict(config.stack), "processes": procs})
    except ValidationError as exc:
        err = config_error(exc)
        raise ConfigError(f"stack.{err.path}", err.reason) from None


def use_camera(stack: Stack) -> Stack:
    """Run the stack's goal trackers on their own camera (``[goal_tracker.camera]`` source set
    by the caller, e.g. ``psm up --camera 0``): the synthetic camera processes are not started
    and the trackers' ``--source`` flags are dropped so the configured source applies.
    Changes ``stack`` in place and returns it."""
    keep: list[ProcessSpec] = []
    for p in stack.processes:
        if tuple(p.command[:2]) == ("camera", "synth"):
            stack.configs.pop(p.name, None)
            continue
        if p.command[:1] == ["track"]:
            cmd = list(p.command)
            while "--source" in cmd:
                i = cmd.index("--source")
                del cmd[i : i + 2]
            p = p.model_copy(update={"command": cmd})
        keep.append(p)
    stack.processes = keep
    return stack


def real_camera_overrides(stack: Stack) -> dict[str, Any]:
    """The overrides a stack on a real camera (:func:`use_camera`) gives its processes besides
    the camera's source: a real camera's frames are not on the arm's clock, so a planner cannot
    wait for their goals (``planner.live_goal_sync`` off, where the stack has a planner)."""
    if any(hasattr(cfg, "planner") for cfg in stack.configs.values()):
        return {"planner.live_goal_sync": False}
    return {}
