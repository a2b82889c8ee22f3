"""``psm up`` (run a stack), ``psm status`` (services alive on a prefix) and ``psm topics``
(live keys with type, rate and bandwidth)."""

from __future__ import annotations

import argparse
import json
from typing import Any

__all__ = ["register"]


def _cmd_up(args: argparse.Namespace) -> int:
    from services.bus.config import ConfigError, env_var_name, parse_override, set_items
    from services.stack import DEFAULT_STACK, load_stack, real_camera_overrides, use_camera
    from services.supervisor import run_stack

    overrides: dict[str, Any] = dict(set_items(args.set))
    if args.clock:
        overrides["clock"] = args.clock
    if args.record:
        overrides["recorder.output"] = args.record
    if args.camera is not None:
        if args.camera.isdigit():
            overrides["goal_tracker.camera.source"] = "device"
            overrides["goal_tracker.camera.device"] = args.camera
        else:
            overrides["goal_tracker.camera.source"] = "url"
            overrides["goal_tracker.camera.uri"] = json.dumps(args.camera)
    parsed = {k: parse_override(v) for k, v in overrides.items()}
    stack = load_stack(args.stack or DEFAULT_STACK, overrides=parsed, view=args.view)
    if args.camera is not None:
        parsed.update(real_camera_overrides(use_camera(stack)))
    if args.record and not any(p.command[:1] == ["record"] for p in stack.processes):
        raise ConfigError("recorder.output", "--record needs a recorder process in the stack")
    # The processes read the overrides from their environment: a string as itself, anything
    # else as JSON (how pydantic-settings reads lists and tables from the environment).
    env = {env_var_name(k): v if isinstance(v, str) else json.dumps(v) for k, v in parsed.items()}
    if args.check:
        print(f"{stack.path}: valid; processes: {', '.join(p.name for p in stack.processes)}")
        return 0
    if args.view:
        v = stack.config.viewer
        print(f"live view: open ws://{v.host}:{v.port} in Foxglove (Open connection > Foxglove WebSocket)",
              flush=True)
    return run_stack(stack, duration_s=args.duration, env_overrides=env, live=args.live)


def _cmd_status(args: argparse.Namespace) -> int:
    from services.bus.config import ServiceConfig, config_from_args
    from services.bus.introspect import run_status

    return run_status(config_from_args(ServiceConfig, args), watch=args.watch, wait_s=args.wait,
                      services=args.service, quiet=args.quiet)


def _cmd_topics(args: argparse.Namespace) -> int:
    from services.bus.config import ServiceConfig, config_from_args
    from services.bus.introspect import run_topics

    return run_topics(config_from_args(ServiceConfig, args), window_s=args.window, watch=args.watch)


def register(subparsers: Any) -> None:
    """Add ``up``, ``status`` and ``topics``."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "up", help="run a stack: every process of a stack file, supervised",
        description="Start every process of the stack file (default configs/stack.toml) in "
        "order, wait for each one's liveliness token, show a live status table, and stop them "
        "in reverse order on Ctrl-C, SIGTERM or --duration, with a summary.",
    )
    p.add_argument("stack", nargs="?", metavar="STACK.toml", help="stack file (default configs/stack.toml)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (wall clock)")
    p.add_argument("--clock", choices=("lockstep", "realtime"), help="the stack's clock")
    p.add_argument("--record", metavar="FILE.mcap", help="the recorder writes to FILE.mcap")
    p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                   help="override a field for every process that has it, e.g. --set arm.dt_s=0.001")
    p.add_argument("--live", action=argparse.BooleanOptionalAction, default=None,
                   help="live status table (default: when stdout is a terminal)")
    p.add_argument("--check", action="store_true", help="validate the stack file and exit")
    p.add_argument("--camera", metavar="DEVICE|URL",
                   help="a real camera for the goal tracker: a device index (0) or a stream URL "
                   "(rtsp://...), instead of the synthetic camera")
    p.add_argument("--view", action="store_true",
                   help="also run the live viewer (psm view): the stack in Foxglove at "
                   "ws://HOST:PORT of [viewer] (default ws://127.0.0.1:8765)")
    p.set_defaults(func=_cmd_up)

    s = subparsers.add_parser(
        "status", help="services alive on a prefix and their status",
        description="List the services whose liveliness token is declared on the prefix, with "
        "their latest ServiceStatus (state, uptime, counters, last error).",
    )
    s.add_argument("--watch", action="store_true", help="refresh until Ctrl-C")
    s.add_argument("--wait", type=float, default=1.5, metavar="S",
                   help="how long to listen for status messages (default 1.5 s)")
    s.add_argument("--service", action="append", default=[], metavar="NAME",
                   help="exit 1 unless this service is alive (repeatable; a container healthcheck)")
    s.add_argument("-q", "--quiet", action="store_true",
                   help="no table: only the liveliness query (with --service: names the missing ones)")
    add_config_arguments(s)
    s.set_defaults(func=_cmd_status)

    t = subparsers.add_parser(
        "topics", help="live keys with type, rate and bandwidth",
        description="Listen to <prefix>/** for a window and list every key seen with its message "
        "type, rate (Hz) and bandwidth.",
    )
    t.add_argument("--window", type=float, default=2.0, metavar="S", help="listening window (default 2 s)")
    t.add_argument("--watch", action="store_true", help="refresh until Ctrl-C")
    add_config_arguments(t)
    t.set_defaults(func=_cmd_topics)
