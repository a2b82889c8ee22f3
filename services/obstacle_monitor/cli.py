"""``psm obstacles`` (the obstacle monitor) and ``psm obstacle add|move|remove|clear`` (change the
obstacle set of a running monitor)."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

__all__ = ["register"]


def register(subparsers: Any) -> None:
    """Add the ``obstacles`` and ``obstacle`` sub-commands."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "obstacles",
        help="run the obstacle monitor: collision predictions for every arm state",
        description="Obstacle monitor: keeps the obstacle set ([obstacle_monitor] of the config, "
        "changed at run time on <prefix>/obstacles/command), tests the segment from the end effector "
        "to the planner's goal against the inflated obstacles and computes the whole-arm clearance "
        "for every <prefix>/arm/state; publishes <prefix>/collision, <prefix>/obstacles and "
        "<prefix>/viz/scene.",
    )
    add_config_arguments(p)
    p.set_defaults(func=_run_monitor)

    p = subparsers.add_parser(
        "obstacle",
        help="add, move or remove an obstacle of a running monitor",
        description="Publish one ObstacleCommand on <prefix>/obstacles/command. Positions and sizes "
        "in m in the base frame; box size = edges, sphere size = diameter, cylinder size = diameter "
        "and height.",
    )
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, help_text in (
        ("add", "add a new obstacle"),
        ("move", "move an obstacle (new position, orientation, velocity)"),
        ("remove", "remove an obstacle"),
        ("clear", "remove every obstacle"),
    ):
        a = actions.add_parser(name, help=help_text, description=help_text)
        if name != "clear":
            a.add_argument("id", help="obstacle id")
        if name == "add":
            a.add_argument("--shape", choices=("box", "sphere", "cylinder"), required=True)
            a.add_argument("--size", type=float, nargs="+", required=True, metavar="M",
                           help="box: X Y Z edges; sphere: D; cylinder: D H")
        if name in ("add", "move"):
            a.add_argument("--position", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"))
            a.add_argument("--rpy", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                           metavar=("R", "P", "Y"), help="orientation, degrees (default 0 0 0)")
            a.add_argument("--velocity", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                           metavar=("VX", "VY", "VZ"), help="m/s (default at rest)")
        a.add_argument("--wait", type=float, default=3.0, metavar="S",
                       help="wait up to S seconds for the monitor to be subscribed (default 3)")
        add_config_arguments(a)
        a.set_defaults(func=_run_command)


def _run_monitor(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.obstacle_monitor.config import ObstacleMonitorConfig
    from services.obstacle_monitor.service import main

    return main(config_from_args(ObstacleMonitorConfig, args))


def _size_vector(shape: str, size: list[float]) -> tuple[float, float, float]:
    """The message's size vector of ``--size`` (a user error is a ValueError: one line, exit 2)."""
    want = {"box": 3, "sphere": 1, "cylinder": 2}[shape]
    if len(size) != want:
        raise ValueError(f"--size: a {shape} takes {want} value(s), got {len(size)}")
    if shape == "box":
        return size[0], size[1], size[2]
    if shape == "sphere":
        return size[0], size[0], size[0]
    return size[0], size[0], size[1]


def command_from_args(args: argparse.Namespace) -> Any:
    """The :class:`ObstacleCommand` the arguments describe."""
    from scipy.spatial.transform import Rotation

    from services.bus.messages import Obstacle, ObstacleCommand

    action = {"add": ObstacleCommand.ADD, "move": ObstacleCommand.MOVE,
              "remove": ObstacleCommand.REMOVE, "clear": ObstacleCommand.CLEAR}[args.action]
    cmd = ObstacleCommand(action=action, source="psm obstacle", id=getattr(args, "id", "") or "")
    if args.action in ("add", "move"):
        ob = cmd.obstacle
        ob.id = args.id
        ob.position.x, ob.position.y, ob.position.z = args.position
        q = Rotation.from_euler("xyz", args.rpy, degrees=True).as_quat()
        ob.orientation.x, ob.orientation.y, ob.orientation.z, ob.orientation.w = (float(c) for c in q)
        ob.velocity.x, ob.velocity.y, ob.velocity.z = args.velocity
        if args.action == "add":
            shapes = {"box": Obstacle.BOX, "sphere": Obstacle.SPHERE, "cylinder": Obstacle.CYLINDER}
            ob.shape = shapes[args.shape]
            ob.size.x, ob.size.y, ob.size.z = _size_vector(args.shape, args.size)
    return cmd


def _run_command(args: argparse.Namespace) -> int:
    import zenoh

    from services.bus.config import ServiceConfig, config_from_args
    from services.bus.messages import Keys, encode
    from services.bus.runtime import open_session

    cmd = command_from_args(args)
    cfg = config_from_args(ServiceConfig, args)
    key = Keys(cfg.prefix).obstacles_command.key
    payload, encoding = encode(cmd)
    session = open_session(cfg.zenoh)
    try:
        pub = session.declare_publisher(key, encoding=zenoh.Encoding(encoding),
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + max(0.0, args.wait)
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        if not pub.matching_status.matching:
            print(f"psm obstacle: warning: no obstacle monitor subscribed on {key}", file=sys.stderr)
        pub.put(payload)
        time.sleep(0.05)  # let the sample leave before the session closes
        pub.undeclare()
    finally:
        session.close()
    print(f"{args.action} {getattr(args, 'id', '') or 'all'} -> {key}")
    return 0
