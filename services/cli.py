"""The ``psm`` command line: one entry point, one sub-command per capability.

Each module listed in :data:`COMMAND_MODULES` exposes ``register(subparsers)`` which adds its
sub-commands with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code. Modules keep
heavy imports (zenoh, pinocchio, OpenCV) inside their functions so ``psm --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from psm.errors import PSMError

#: Modules that contribute sub-commands, in the order they appear in ``psm --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "services.learn_cli",
    "services.bus.cli",
    "services.arm.cli",
    "services.goal_tracker.cli",
)


class CLIError(Exception):
    """A user error at the command line: printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    """Build the ``psm`` argument parser with every registered sub-command."""
    parser = argparse.ArgumentParser(
        prog="psm",
        description="Phase Space Model: learn a motion from one demonstration and run it "
        "over Eclipse Zenoh, recorded to MCAP.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``psm`` command line; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from importlib.metadata import version

        print(version("psm-dataflow"))
        return 0
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (PSMError, CLIError, OSError, ValueError) as exc:
        # The edge: a user error is one clear line, not a traceback.
        print(f"psm {args.command}: error: {exc}", file=sys.stderr)
        return 2

if __name__ == "__main__":
    sys.exit(main())
