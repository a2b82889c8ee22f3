"""The ``save`` / ``compare`` command line shared by the fingerprint scripts
(``fit_fingerprints.py``, ``controller_fingerprints.py``): ``save REF.json`` writes every case's
digest, ``compare REF.json`` reports the cases whose digest differs (exit status 1 if any does,
or if the cases are not the same)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path


def save_or_compare(argv: Sequence[str], usage: str, digests: Callable[[], dict[str, str]]) -> int:
    """Run ``argv`` (``[mode, ref]``) against the digests by case name ``digests()`` returns;
    prints ``usage`` and returns 2 on a wrong command line."""
    if len(argv) != 2 or argv[0] not in ("save", "compare"):
        print(usage)
        return 2
    mode, ref = argv[0], Path(argv[1])
    got = digests()
    if mode == "save":
        ref.write_text(json.dumps(got, indent=0) + "\n")
        return 0
    want = json.loads(ref.read_text())
    differ = [name for name in want if got.get(name) != want[name]]
    print(f"{len(differ)} differ" + (": " + ", ".join(differ[:20]) if differ else ""))
    return 1 if differ or set(got) != set(want) else 0
