"""``psm serve router``: a Zenoh router process (python ``zenoh`` in router mode).

The local stack and docker compose share one topology: one router, every service connects to
it as a client (``[zenoh] connect``, env ``PSM_ZENOH__CONNECT``). The router reads the shared
bus settings and its own ``[router]`` table (where it listens, which other routers it joins,
who may log in and what each may do); it is itself a bus service: it holds a liveliness token
and publishes its ServiceStatus. Any other advanced zenoh setting (e.g. TLS) goes in a JSON5
file given as ``zenoh.config_file``.

Access control (docs/security.md): ``users_file`` is zenoh's user/password dictionary
(``user:password`` lines, written by ``psm secrets``): only those users can connect.
``access_control = true`` (which needs it) adds zenoh's access control, default deny, built
from the roles table of :mod:`services.bus.acl`: each user is a role (the stack's process
names and ``operator``) and may do exactly what that role needs. A denied message and a
refused login are WARNING lines of the router's log (:mod:`services.bus.acl_log`).

Example::

    psm serve router --listen tcp/127.0.0.1:7447 --no-multicast
    psm serve router --set router.access_control=true --set router.users_file=/run/secrets/users.txt
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field

from services.bus.config import ConfigError, EndpointList, Section, ServiceConfig, ZenohConfig

__all__ = ["RouterConfig", "RouterSection", "read_users_file", "run_router"]


def read_users_file(path: str) -> list[str]:
    """The users of a zenoh user/password dictionary (``user:password`` per line, blank lines
    ignored); raises :class:`ConfigError` naming ``users_file`` if it cannot be read or a line
    is not ``user:password``."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        reason = exc.strerror.lower() if exc.strerror else type(exc).__name__
        raise ConfigError("users_file", f"cannot read {path}: {reason}") from None
    except UnicodeDecodeError:
        raise ConfigError("users_file", f"{path} is not UTF-8 text") from None
    users = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise ConfigError("users_file", f"{path} line {n}: expected user:password")
        users.append(user)
    if not users:
        raise ConfigError("users_file", f"{path} has no user")
    return users


class RouterSection(Section):
    """The ``[router]`` table."""

    listen: EndpointList = Field(
        default_factory=lambda: ["tcp/0.0.0.0:7447"], min_length=1,
        description="endpoints the router listens on",
    )
    connect: EndpointList = Field(
        default_factory=list, description="other routers to join (a multi-router deployment)"
    )
    access_control: bool = Field(
        False,
        description="zenoh access control, default deny: each user of users_file may do what "
        "its role needs (services/bus/acl.py, docs/security.md); needs users_file",
    )
    users_file: str = Field(
        "",
        description="zenoh's user/password dictionary (user:password lines, psm secrets writes "
        "it): only these users may connect ('' = no authentication)",
    )
    rt_priority: int = Field(
        0, ge=0, le=99,
        description="SCHED_FIFO priority of the router process, 1-99 (0 = normal scheduling): it "
        "routes every message of the control loop (arm state -> monitor -> planner -> arm)",
    )
    log_denials: bool = Field(
        True,
        description="with users_file: every denied message and refused login is a WARNING line "
        "of the router's log (zenoh's access-control trace, filtered in the router: costs "
        "router CPU per routed message, benchmarks/results/acl.md)",
    )

    def check(self) -> None:
        """Access control needs the users file; the users file is readable and well-formed."""
        if self.access_control and not self.users_file:
            raise ConfigError("users_file", "is required with access_control = true")
        if self.users_file:
            read_users_file(self.users_file)


class RouterConfig(ServiceConfig):
    """Config of ``psm serve router``: bus settings + ``[router]``."""

    router: RouterSection = Field(default_factory=RouterSection)

    def session_config(self) -> ZenohConfig:
        """The zenoh settings of the router's own session: router mode on ``router.listen``."""
        return self.zenoh.model_copy(
            update={"mode": "router", "listen": list(self.router.listen),
                    "connect": list(self.router.connect)}
        )

    def session_extra(self) -> dict[str, Any]:
        """The router's zenoh settings beyond :class:`ZenohConfig`: the clock sampler's QoS, the
        users dictionary and the access-control configuration of the roles (zenoh config path ->
        JSON value)."""
        from services.bus.acl import acl_config
        from services.bus.messages import Keys, clock_sampler_qos

        # The arm's state goes droppable to the clock sampler when routed to it (clients).
        extra: dict[str, Any] = {"qos/network": clock_sampler_qos(Keys(self.prefix))}
        if self.router.users_file:
            extra["transport/auth/usrpwd/dictionary_file"] = str(
                Path(self.router.users_file).resolve()
            )
        if self.router.access_control:
            extra["access_control"] = acl_config(Keys(self.prefix))
        return extra


def run_router(cfg: RouterConfig) -> int:
    """Run the router until SIGINT/SIGTERM; returns the exit code."""
    from services.bus.acl import ROLE_NAMES
    from services.bus.acl_log import ZENOH_LOG_DIRECTIVES, AclLog
    from services.bus.runtime import Service, ServiceApp, init_zenoh_log, run_service, setup_logging
    from services.threads import set_realtime_priority

    # Before zenoh starts: its threads inherit the scheduling class.
    rt_problem = set_realtime_priority(cfg.router.rt_priority, cfg.clock)
    acl_log: AclLog | None = None
    if cfg.router.users_file and cfg.router.log_denials:
        # Before zenoh logs anything: its log goes through the filter (see acl_log).
        acl_log = AclLog(setup_logging("router", cfg.log_level, cfg.log_format))
        acl_log.start()
        init_zenoh_log(ZENOH_LOG_DIRECTIVES)

    class Router(ServiceApp):
        name = "router"

        def zenoh_config(self) -> ZenohConfig:
            return cfg.session_config()

        def zenoh_extra(self) -> dict[str, Any]:
            return cfg.session_extra()

        def setup(self, svc: Service) -> None:
            if rt_problem:
                svc.log.warning(f"{rt_problem}; running with normal scheduling")
            users = read_users_file(cfg.router.users_file) if cfg.router.users_file else []
            svc.log.info("router listening", extra={
                "listen": cfg.router.listen, "connect": cfg.router.connect,
                "authentication": bool(users), "access_control": cfg.router.access_control,
            })
            strangers = sorted(set(users) - set(ROLE_NAMES))
            if cfg.router.access_control and strangers:
                svc.log.warning(
                    "users without a role: everything they send is denied",
                    extra={"users": ",".join(strangers), "roles": ",".join(ROLE_NAMES)},
                )

        def teardown(self, svc: Service) -> None:
            if acl_log is not None:
                svc.log.info("access-control summary", extra={
                    "denials": sum(acl_log.denied.values()),
                    "logins_refused": acl_log.logins_refused,
                    "zenoh_log_lines": acl_log.lines,
                })

    try:
        return run_service(Router(cfg))
    finally:
        if acl_log is not None:
            acl_log.stop()
