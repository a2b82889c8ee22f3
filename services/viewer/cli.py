"""``psm view``: the cell live in Foxglove (a Foxglove WebSocket server)."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["register"]


def register(subparsers: Any) -> None:
    """Add the ``view`` sub-command."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "view",
        help="watch a running stack live in Foxglove (WebSocket server)",
        description="Serve the cell's messages to the Foxglove app over a WebSocket "
        "(sub-protocol foxglove.sdk.v1; open ws://HOST:PORT in Foxglove). One channel per key, the "
        "payloads forwarded unchanged, fast streams throttled per [viewer] max_rate_hz; only "
        "streams a client subscribes to are forwarded.",
    )
    p.add_argument("--host", help="address to bind (default [viewer] host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="WebSocket port (default [viewer] port, 8765; 0: any free port)")
    add_config_arguments(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.viewer.config import ViewerConfig
    from services.viewer.service import main

    return main(config_from_args(ViewerConfig, args, {"viewer.host": args.host, "viewer.port": args.port}))
