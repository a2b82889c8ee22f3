"""``python -m services.arm {arm,teach} ...``: the arm's sub-commands without the full ``psm``
command line (same flags as ``psm arm`` / ``psm teach``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run ``arm`` or ``teach``; returns the exit code."""
    from services.arm.cli import register
    from services.cli import CLIError

    parser = argparse.ArgumentParser(prog="python -m services.arm")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    register(sub)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, FileNotFoundError, CLIError) as exc:
        print(f"{parser.prog} {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
