"""The ``psm`` command line: one entry point, one sub-command per capability.

Each module listed in :data:`COMMAND_MODULES` exposes ``register(subparsers)`` which adds its
sub-commands with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code. Modules keep
heavy imports (zenoh, pinocchio, OpenCV) inside their functions so ``psm --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence

from psm.errors import PSMError

#: Modules that contribute sub-commands, in the order they appear in ``psm --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "services.learn_cli",
    "services.stack_cli",
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


def dispatch(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` with ``parser`` and run the chosen sub-command: a user error (bad file,
    config or shape) is one line on stderr and exit code 2, never a traceback. A process started
    by the supervisor is bound to it first (it ends when the supervisor dies)."""
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
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (PSMError, CLIError, OSError, ValueError) as exc:
        print(f"{parser.prog} {args.command}: error: {_error_text(exc)}", file=sys.stderr)
        return 2


def _error_text(exc: BaseException) -> str:
    """One line for the user: an OS error as ``FILE: reason`` (not ``[Errno 2] ...``)."""
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror.lower()}"
    return str(exc)


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
    sys.exit(main())
