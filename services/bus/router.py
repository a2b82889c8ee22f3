"""``psm serve router``: a Zenoh router process (python ``zenoh`` in router mode).

The local stack and docker compose share one topology: one router, every service connects to
it as a peer or client (``--connect tcp/<router>:7447``, env ``PSM_ZENOH_CONNECT``). The router
is itself a bus service: it holds a liveliness token and publishes its ServiceStatus.
An access-control or other advanced zenoh setting goes in a JSON5 file given as
``zenoh.config_file`` (``--set zenoh.config_file=configs/zenoh-router.json5``).

Example::

    psm serve router --listen tcp/0.0.0.0:7447 --no-multicast
"""

from __future__ import annotations

import dataclasses

from services.bus.config import ServiceConfig

__all__ = ["DEFAULT_ROUTER_LISTEN", "router_config", "run_router"]

#: Where the router listens when no ``listen`` endpoint is configured.
DEFAULT_ROUTER_LISTEN = "tcp/0.0.0.0:7447"


def router_config(cfg: ServiceConfig) -> ServiceConfig:
    """``cfg`` with ``zenoh.mode = router`` and a default listen endpoint."""
    z = dataclasses.replace(
        cfg.zenoh, mode="router", listen=list(cfg.zenoh.listen) or [DEFAULT_ROUTER_LISTEN]
    )
    return dataclasses.replace(cfg, zenoh=z)


def run_router(cfg: ServiceConfig) -> int:
    """Run the router until SIGINT/SIGTERM; returns the exit code."""
    from services.bus.runtime import Service

    cfg = router_config(cfg)
    svc = Service("router", cfg)
    svc.log.info("router listening", extra={"listen": cfg.zenoh.listen,
                                            "connect": cfg.zenoh.connect})
    svc.run()
    return 0
