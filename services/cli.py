"""The ``psm`` command line: one entry point, one sub-command per capability.

Each module listed in :data:`COMMAND_MODULES` exposes ``register(subparsers)`` which adds its
sub-commands with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code. Modules keep
heavy imports (zenoh, pinocchio, OpenCV) inside their functions so ``psm --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence

from psm.errors import PSMError
from services.bus.errors import BusError

#: Modules that contribute sub-commands, in the order they appear in ``psm --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "services.learn_cli",
    "services.stack_cli",
    "services.bus.cli",
    "services.arm.cli",
    "services.goal_tracker.cli",
    "services.planner.cli",
    "services.obstacle_monitor.cli",
    "services.viewer.cli",
    "services.compose",
    "experiments.cli",
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


def dispatch(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` with ``parser`` and run the chosen sub-command.

    This is the one place where errors become output: a user error (bad file, config, shape,
    key expression; a bus that cannot be reached) is one line on stderr,
    ``<command path>: error: <message>`` (e.g. ``psm serve router: error: ...``), and exit
    code 2, never a traceback. Sub-commands raise and do not print their own errors.
    A process started by the supervisor is bound to it first (it ends when the supervisor dies).
    """
    from services.supervisor import bind_to_supervisor

    bind_to_supervisor()
    args = parser.parse_args(argv)
    if getattr(args, "version", False):
        from importlib.metadata import version

        print(version("psm-dataflow"))
        return 0
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here (below), not at interpreter exit
        return code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader of stdout went away (``psm info FILE | head``): end quietly, as a command
        # killed by SIGPIPE would, with the rest of the output sent nowhere.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + 13
    except (PSMError, CLIError, BusError, OSError, ValueError) as exc:
        print(f"{command_path(parser, args)}: error: {_error_text(exc)}", file=sys.stderr)
        return 2


def command_path(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str:
    """The program and sub-command names as typed, e.g. ``psm serve router`` or
    ``psm camera synth``: follows the chosen sub-parser at every level."""
    prog = parser.prog
    current: argparse.ArgumentParser | None = parser
    while current is not None:
        action = next(
            (a for a in current._actions if isinstance(a, argparse._SubParsersAction)), None
        )
        chosen = getattr(args, action.dest, None) if action is not None else None
        if action is None or chosen is None or chosen not in action.choices:
            break
        current = action.choices[chosen]
        prog = current.prog
    return prog


def _error_text(exc: BaseException) -> str:
    """One line for the user: an OS error as ``FILE: reason`` (not ``[Errno 2] ...``); a
    config error without its ``config error:`` prefix (the line already says ``error:``)."""
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror.lower()}"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text.removeprefix("config error: ")


def module_main(
    register: Callable[[argparse._SubParsersAction], None], prog: str,
    argv: Sequence[str] | None = None,
) -> int:
    """Run one module's sub-commands on their own (``python -m services.<module> ...``)."""
    parser = argparse.ArgumentParser(prog=prog)
    register(parser.add_subparsers(dest="command", metavar="COMMAND", required=True))
    return dispatch(parser, argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``psm`` command line; returns the process exit code."""
    return dispatch(build_parser(), argv)

if __name__ == "__main__":
    # Run the imported module's main, not this __main__ copy: sub-commands import
    # services.cli (CLIError), and a second copy of the class would not be caught here.
    sys.exit(importlib.import_module("services.cli").main())
