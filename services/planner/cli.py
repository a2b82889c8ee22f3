"""``psm plan``: the planner service (the task sequencer answering every arm state)."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["register"]


def register(subparsers: Any) -> None:
    """Add the ``plan`` sub-command."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "plan",
        help="run the planner: the task's PSMs answering every arm state",
        description="Planner: learns one PSM per step of the task (configs/feeding.toml by "
        "default; models cached by content hash), answers every <prefix>/arm/state with an "
        "<prefix>/arm/command, follows live goals from <prefix>/goals/*, publishes "
        "<prefix>/planner/status, <prefix>/task/events and <prefix>/gripper/command.",
    )
    add_config_arguments(p)
    p.add_argument("--task", metavar="FILE.toml", help="scene + task file (default configs/feeding.toml)")
    p.add_argument("--summary-file", metavar="FILE.json", help="write the task summary at exit")
    p.add_argument(
        "--exit-when-done", action="store_true", default=None, help="exit once the task is done or aborted"
    )
    p.set_defaults(func=_run_plan)


def _run_plan(args: argparse.Namespace) -> int:
    from services.bus.config import config_from_args
    from services.planner.config import PlannerConfig
    from services.planner.service import main

    extra = {
        "planner.task_file": args.task,
        "planner.summary_file": args.summary_file,
        "planner.exit_when_done": args.exit_when_done,
    }
    return main(config_from_args(PlannerConfig, args, extra))
