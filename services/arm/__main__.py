"""``python -m services.arm {arm,teach} ...``: the arm's sub-commands without the full ``psm``
command line (same flags as ``psm arm`` / ``psm teach``)."""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run ``arm`` or ``teach``; returns the exit code."""
    from services.arm.cli import register
    from services.cli import module_main

    return module_main(register, "python -m services.arm", argv)

if __name__ == "__main__":
    sys.exit(main())
