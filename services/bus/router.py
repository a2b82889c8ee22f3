"""``psm serve router``: a Zenoh router process (python ``zenoh`` in router mode).

The local stack and docker compose share one topology: one router, every service connects to
it as a client (``[zenoh] connect``, env ``PSM_ZENOH__CONNECT``). The router reads the shared
bus settings and its own ``[router]`` table (where it listens, which other routers it joins);
it is itself a bus service: it holds a liveliness token and publishes its ServiceStatus. An
access-control or other advanced zenoh setting goes in a JSON5 file given as
``zenoh.config_file``.

Example::

    psm serve router --listen tcp/127.0.0.1:7447 --no-multicast
"""

from __future__ import annotations

from pydantic import Field

from services.bus.config import EndpointList, Section, ServiceConfig, ZenohConfig

__all__ = ["RouterConfig", "RouterSection", "run_router"]


class RouterSection(Section):
    """The ``[router]`` table."""

    listen: EndpointList = Field(
        default_factory=lambda: ["tcp/0.0.0.0:7447"], min_length=1,
        description="endpoints the router listens on",
    )
    connect: EndpointList = Field(
        default_factory=list, description="other routers to join (a multi-router deployment)"
    )


class RouterConfig(ServiceConfig):
    """Config of ``psm serve router``: bus settings + ``[router]``."""

    router: RouterSection = Field(default_factory=RouterSection)

    def session_config(self) -> ZenohConfig:
        """The zenoh settings of the router's own session: router mode on ``router.listen``."""
        return self.zenoh.model_copy(
            update={"mode": "router", "listen": list(self.router.listen),
                    "connect": list(self.router.connect)}
        )


def run_router(cfg: RouterConfig) -> int:
    """Run the router until SIGINT/SIGTERM; returns the exit code."""
    from services.bus.runtime import Service, ServiceApp, run_service

    class Router(ServiceApp):
        name = "router"

        def zenoh_config(self) -> ZenohConfig:
            return cfg.session_config()

        def setup(self, svc: Service) -> None:
            svc.log.info("router listening", extra={"listen": cfg.router.listen,
                                                    "connect": cfg.router.connect})

    return run_service(Router(cfg))
