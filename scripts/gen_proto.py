"""Regenerate the Python code for the bus schemas (``services/bus/proto/*.proto``).

Usage::

    .venv/bin/python scripts/gen_proto.py            # write services/bus/proto_gen/
    .venv/bin/python scripts/gen_proto.py --check    # exit 1 if the committed code is stale

Uses the ``protoc`` bundled with ``grpcio-tools`` so the output depends only on the pinned
Python packages. ``tests/bus/test_proto_gen.py`` fails when the committed code is stale.
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROTO_DIR = ROOT / "services" / "bus" / "proto"
OUT_DIR = ROOT / "services" / "bus" / "proto_gen"
INIT_TEXT = '"""Generated protobuf code: do not edit, run ``scripts/gen_proto.py``."""\n'


def generate(out_dir: Path) -> list[Path]:
    """Run protoc on every ``.proto`` in :data:`PROTO_DIR`, writing ``*_pb2.py``/``.pyi`` to
    ``out_dir``; returns the written files (sorted)."""
    from grpc_tools import protoc

    out_dir.mkdir(parents=True, exist_ok=True)
    protos = sorted(p.name for p in PROTO_DIR.glob("*.proto"))
    if not protos:
        raise SystemExit(f"no .proto files in {PROTO_DIR}")
    args = [
        "protoc",
        f"-I{PROTO_DIR}",
        f"--python_out={out_dir}",
        f"--pyi_out={out_dir}",
        *protos,
    ]
    rc = protoc.main(args)
    if rc != 0:
        raise SystemExit(f"protoc failed with exit code {rc}")
    (out_dir / "__init__.py").write_text(INIT_TEXT)
    return sorted(p for p in out_dir.iterdir() if p.is_file() and p.suffix in (".py", ".pyi"))


def stale_files(committed: Path = OUT_DIR) -> list[str]:
    """Generate into a temporary directory and list the files that differ from ``committed``
    (missing, extra or changed); empty when the committed code is up to date."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp))
        names = {p.name for p in fresh}
        have = {
            p.name for p in committed.iterdir() if p.is_file() and p.suffix in (".py", ".pyi")
        } if committed.is_dir() else set()
        diff = sorted(names ^ have)
        for name in sorted(names & have):
            if not filecmp.cmp(Path(tmp) / name, committed / name, shallow=False):
                diff.append(name)
        return diff


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check, do not write")
    args = parser.parse_args(argv)
    if args.check:
        diff = stale_files()
        if diff:
            print("stale generated code: " + ", ".join(diff) + " (run scripts/gen_proto.py)")
            return 1
        print("generated code is up to date")
        return 0
    for path in generate(OUT_DIR):
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
