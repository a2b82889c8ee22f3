"""Generated protobuf code must match what scripts/gen_proto.py produces now."""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _gen():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("gen_proto", ROOT / "scripts" / "gen_proto.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_generated_code_is_up_to_date() -> None:
    stale = _gen().stale_files()
    assert stale == [], f"stale generated code {stale}: run scripts/gen_proto.py"


def test_staleness_is_detected(tmp_path: Path) -> None:
    gen = _gen()
    copy = tmp_path / "proto_gen"
    shutil.copytree(gen.OUT_DIR, copy)
    assert gen.stale_files(copy) == []
    target = copy / "psm_pb2.py"
    target.write_text(target.read_text() + "\n# edited by hand\n")
    (copy / "psm_pb2.pyi").unlink()
    assert gen.stale_files(copy) == ["psm_pb2.pyi", "psm_pb2.py"]
