"""``psm info`` and ``psm export`` on real MCAP files: the committed fixture and demonstration,
files written with the recorder's own writer, and damaged copies (cut, corrupt, not MCAP)."""

from __future__ import annotations

import csv
import io
import json
import re
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from services.bus.export import export_topic
from services.bus.info import recording_info, utc_iso
from services.bus.log import RecordPass, read_log, read_metadata, read_samples
from services.bus.mcap_writer import FastMcapWriter
from services.bus.messages import (
    ArmState,
    FaceBox,
    FaceDetections,
    Keys,
    encode,
    file_descriptor_set,
)
from services.cli import main

from .fixture_data import PATH as FIXTURE
from .fixture_data import T0_NS
from .helpers import one_error_line, run_psm

KEYS = Keys("psm")
DEMO = Path(__file__).resolve().parents[2] / "data" / "demos" / "reach_person.mcap"


def _psm(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """Run ``psm ARGS`` in this process: exit code, stdout, stderr."""
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def _cut(tmp_path: Path, fraction: float) -> Path:
    """The fixture cut after ``fraction`` of its bytes (a recorder killed mid-file)."""
    data = FIXTURE.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    return cut


def _write_faces(path: Path, lengths: list[int]) -> list[FaceDetections]:
    """A recording of FaceDetections with ``lengths[i]`` boxes in message ``i``, written as the
    recorder writes (FastMcapWriter, the schema's FileDescriptorSet), 10 ms apart."""
    msgs = [FaceDetections(stamp_ns=i, seq=i, camera_id="cam0", image_width=640,
                           target_index=-1 if n == 0 else 0,
                           boxes=[FaceBox(x_px=10.0 * i + j, y_px=0.5, w_px=3.0, h_px=4.0,
                                          confidence=0.25 * j) for j in range(n)])
            for i, n in enumerate(lengths)]
    with path.open("wb") as fh:
        w = FastMcapWriter(fh, chunk_size=512)
        w.start(library="test")
        name = FaceDetections.DESCRIPTOR.full_name
        sid = w.register_schema(name=name, encoding="protobuf", data=file_descriptor_set(name))
        ch = w.register_channel(topic=KEYS.vision_faces.key, message_encoding="protobuf",
                                schema_id=sid, metadata={})
        for i, m in enumerate(msgs):
            t = 1_000_000_000 + i * 10_000_000
            w.add_message(ch, t, encode(m)[0], t - 5, i)
        w.finish()
    return msgs


# -- psm info ---------------------------------------------------------------------------------

def test_info_of_the_fixture_matches_what_is_recorded(capsys: pytest.CaptureFixture[str]) -> None:
    samples = list(read_samples(FIXTURE))
    counts = Counter(s.topic for s in samples)
    code, out, err = _psm(capsys, "info", "--json", str(FIXTURE))
    assert code == 0 and err == ""
    info = json.loads(out)
    assert info["complete"] and info["status"] == "complete"
    assert info["size_bytes"] == info["readable_bytes"] == FIXTURE.stat().st_size
    assert info["messages"] == len(samples) == 87
    start, end = min(s.log_time_ns for s in samples), max(s.log_time_ns for s in samples)
    assert (info["start_ns"], info["end_ns"]) == (start, end) == (T0_NS, T0_NS + 401_000_000)
    assert info["start_utc"] == "2023-11-14T22:13:20.000000000Z"
    assert info["end_utc"] == "2023-11-14T22:13:20.401000000Z"
    assert info["duration_s"] == pytest.approx(0.401)
    by_topic = {c["topic"]: c for c in info["channels"]}
    assert {t: c["messages"] for t, c in by_topic.items()} == dict(counts)
    state = by_topic[KEYS.arm_state.key]
    assert (state["schema"], state["message_encoding"]) == ("psm.ArmState", "protobuf")
    assert state["rate_hz"] == pytest.approx(100.0)  # 40 states 10 ms apart
    size = sum(len(s.payload) for s in samples if s.topic == KEYS.arm_state.key)
    assert state["payload_bytes"] == size
    assert state["bandwidth_bps"] == pytest.approx(100.0 * size / 40)
    assert by_topic[KEYS.obstacles.key]["rate_hz"] is None  # a single message has no rate
    assert info["metadata"] == read_metadata(FIXTURE)
    assert info["attachments"] == []


def test_info_table_for_people(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _psm(capsys, "info", str(DEMO))
    assert code == 0 and err == ""
    lines = out.splitlines()
    size = DEMO.stat().st_size
    assert lines[:3] == [f"file:      {DEMO}", f"size:      {size / 1000:.1f} kB ({size} bytes)",
                         "state:     complete"]
    assert "messages:  1838" in lines and "duration:  3.600 s" in lines
    assert f"end:       {utc_iso(3_600_000_000)} (3600000000 ns)" in lines
    state_row = next(ln for ln in lines if KEYS.arm_state.key in ln)
    assert "psm.ArmState" in state_row and "1801" in state_row and "500.0" in state_row
    assert "  psm.teach (13 keys)" in lines and "    task:        reach_person" in lines


def test_info_lists_attachments_and_schemaless_channels(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "att.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="x", library="ref")
        ch = w.register_channel(topic="raw/bytes", message_encoding="zenoh/bytes", schema_id=0)
        for i in range(3):
            w.add_message(ch, log_time=i * 500_000_000, data=b"abcd", publish_time=0)
        w.add_attachment(create_time=1, log_time=2, name="calib.yaml", media_type="text/yaml",
                         data=b"k: v\n")
        w.add_metadata("run", {"operator": "a"})
        w.finish()
    info = recording_info(path)
    assert info.complete and (info.profile, info.library) == ("x", "ref")
    [c] = info.channels
    assert (c.topic, c.schema, c.message_encoding, c.messages) == ("raw/bytes", "", "zenoh/bytes", 3)
    assert c.rate_hz == pytest.approx(2.0) and c.bandwidth_bps == pytest.approx(8.0)
    [a] = info.attachments
    assert (a.name, a.media_type, a.size_bytes, a.log_time_ns) == ("calib.yaml", "text/yaml", 5, 2)
    assert info.metadata == {"run": {"operator": "a"}}
    with pytest.raises(ValueError, match=r"message encoding 'zenoh/bytes' .*protobuf only"):
        export_topic(path, "raw/bytes")


def test_info_of_a_truncated_file_describes_the_readable_part(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    cut = _cut(tmp_path, 0.25)
    readable = list(read_samples(cut, quiet=True))
    assert 0 < len(readable) < 87
    reader = RecordPass(cut)
    for _ in reader.records():
        pass
    assert reader.truncated and 0 < reader.readable_bytes < cut.stat().st_size
    span = (max(s.log_time_ns for s in readable) - min(s.log_time_ns for s in readable)) / 1e9
    status = (f"truncated: no summary; readable up to byte {reader.readable_bytes} of "
              f"{cut.stat().st_size} ({len(readable)} messages in {span:.3f} s)")
    code, out, err = _psm(capsys, "info", str(cut))
    assert code == 0
    assert err == f"psm info: warning: {cut}: {status}\n"
    assert f"state:     {status}" in out.splitlines()
    code, out, err = _psm(capsys, "info", "--json", str(cut))
    info = json.loads(out)
    assert code == 0 and not info["complete"] and info["status"] == status
    assert info["messages"] == len(readable)
    assert {c["topic"]: c["messages"] for c in info["channels"] if c["messages"]} == dict(
        Counter(s.topic for s in readable))
    # cut inside the summary: every message is readable, the file is still not complete
    info = recording_info(_cut(tmp_path, 0.9))
    assert not info.complete and info.truncated and info.messages == 87


def test_info_of_a_corrupt_chunk_stops_there(tmp_path: Path) -> None:
    data = bytearray(FIXTURE.read_bytes())
    data[len(data) // 3] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    info = recording_info(bad)
    assert not info.complete and not info.truncated
    assert 0 < info.messages < 87
    assert info.status().startswith(f"corrupt at byte {info.readable_bytes} (CRCValidationError")


def test_info_errors_are_one_line(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"this is not an mcap file\n" * 10)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    head = tmp_path / "head.mcap"
    head.write_bytes(FIXTURE.read_bytes()[:600])  # header, no complete chunk
    for path, expect in ((garbage, "not an MCAP file (no MCAP magic at the start)"),
                         (empty, "empty file, not an MCAP recording"),
                         (head, "nothing readable: truncated: no summary; readable up to byte "),
                         (tmp_path / "missing.mcap", "no such file or directory")):
        msg = one_error_line(run_psm("info", str(path)), "psm info")
        assert msg.startswith(f"{path}: {expect}"), msg


# -- psm export -------------------------------------------------------------------------------

def test_csv_of_arm_state_matches_the_decoded_messages(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "state.csv"
    code, stdout, err = _psm(capsys, "export", str(FIXTURE), "--topic", KEYS.arm_state.key,
                             "--csv", str(out))
    assert code == 0
    with out.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert stdout == f"wrote {out}: 40 rows x {len(rows[0])} columns ({KEYS.arm_state.key}, " \
                     "psm.ArmState)\n"
    # the fixture's states have no joint names and no accelerations: said, not silently dropped
    assert err == ("psm export: left out: joint_names (empty in every message); "
                   "ddq (empty in every message)\n")
    samples = [s for s in read_samples(FIXTURE) if s.topic == KEYS.arm_state.key]
    msgs = [m for _, m, _ in read_log(FIXTURE, KEYS.arm_state.key)]
    assert len(rows) == len(samples) == len(msgs) == 40
    assert list(rows[0])[:6] == ["log_time_ns", "publish_time_ns", "t_s", "stamp_ns", "tick",
                                 "sim_time_ns"]
    for row, s, m in zip(rows, samples, msgs, strict=True):
        assert isinstance(m, ArmState)
        assert int(row["log_time_ns"]) == s.log_time_ns
        assert int(row["publish_time_ns"]) == s.publish_time_ns == m.stamp_ns
        assert float(row["t_s"]) == (s.log_time_ns - T0_NS) / 1e9  # the file's first message
        assert int(row["tick"]) == m.tick
        assert [float(row[f"q.{i}"]) for i in range(7)] == list(m.q)  # exact round trip
        assert [float(row[f"dq.{i}"]) for i in range(7)] == list(m.dq)
        assert [float(row[f"ee_position.{a}"]) for a in "xyz"] == [
            m.ee_position.x, m.ee_position.y, m.ee_position.z]
        assert row["ee_orientation.w"] == "1.0" and row["frame_id"] == m.frame_id == "base"
        assert row["braking"] == "0" and float(row["dt_s"]) == m.dt_s
    assert "q.7" not in rows[0]


def test_npz_round_trip_and_dtypes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, out_csv = tmp_path / "state.npz", tmp_path / "state.csv"
    code, _, _ = _psm(capsys, "export", str(DEMO), "--topic", KEYS.arm_state.key,
                      "--npz", str(out), "--csv", str(out_csv))
    assert code == 0
    table = export_topic(DEMO, KEYS.arm_state.key)
    with np.load(out, allow_pickle=False) as npz:
        assert list(npz.files) == list(table.columns)
        for name, col in table.columns.items():
            assert npz[name].dtype == col.dtype and np.array_equal(npz[name], col), name
        assert npz["q.0"].dtype == np.float64 and npz["tick"].dtype == np.uint64
        assert npz["braking"].dtype == np.bool_ and npz["joint_names.6"][0] == "panda_joint7"
        q = np.stack([npz[f"q.{i}"] for i in range(7)], axis=1)
    msgs = [m for _, m, _ in read_log(DEMO, KEYS.arm_state.key)]
    assert np.array_equal(q, np.array([list(m.q) for m in msgs]))
    # the CSV holds the same numbers
    with out_csv.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert np.array_equal(np.array([[float(r[f"q.{i}"]) for i in range(7)] for r in rows]), q)


def test_repeated_messages_fixed_and_variable_length(tmp_path: Path) -> None:
    fixed = tmp_path / "fixed.mcap"
    msgs = _write_faces(fixed, [2, 2, 2])
    table = export_topic(fixed, KEYS.vision_faces.key)
    assert table.left_out == {}
    assert table.columns["boxes.1.x_px"].tolist() == [m.boxes[1].x_px for m in msgs]
    assert table.columns["boxes.0.confidence"].tolist() == [0.0, 0.0, 0.0]
    assert table.columns["image_width"].dtype == np.uint32
    assert table.columns["target_index"].dtype == np.int32
    assert table.columns["publish_time_ns"].tolist() == [
        t - 5 for t in table.columns["log_time_ns"].tolist()]
    varying = tmp_path / "varying.mcap"
    _write_faces(varying, [0, 1, 2, 1])
    table = export_topic(varying, KEYS.vision_faces.key)
    assert table.left_out == {"boxes": "variable length (0 to 2)"}
    assert not any(c.startswith("boxes") for c in table.columns)
    assert table.columns["target_index"].tolist() == [-1, 0, 0, 0]
    # a window where the length does not vary: the boxes are columns again
    table = export_topic(varying, KEYS.vision_faces.key, start_s=0.005, end_s=0.015)
    assert table.rows == 1 and table.columns["boxes.0.x_px"].tolist() == [10.0]
    assert table.columns["t_s"].tolist() == [0.01]


def test_image_bytes_are_left_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "img.csv"
    code, _, err = _psm(capsys, "export", str(FIXTURE), "--topic",
                        KEYS.camera_image("cam0").key, "--csv", str(out))
    assert code == 0 and err == "psm export: left out: data (bytes)\n"
    header = out.read_text().splitlines()[0].split(",")
    assert header == ["log_time_ns", "publish_time_ns", "t_s", "timestamp.seconds",
                      "timestamp.nanos", "frame_id", "format"]


def test_fields_and_time_window(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    table = export_topic(DEMO, KEYS.arm_state.key, fields=["q", "ee_position.z"],
                         start_s=1.0, end_s=2.0)
    assert list(table.columns) == ["log_time_ns", "publish_time_ns", "t_s",
                                   *(f"q.{i}" for i in range(7)), "ee_position.z"]
    t = table.columns["t_s"]
    assert table.rows == 501 and t[0] == 1.0 and t[-1] == 2.0  # 500 Hz, both ends included
    state = re.escape(KEYS.arm_state.key)
    with pytest.raises(ValueError, match=rf"no field 'foo' in {state} \(psm.ArmState\); "
                                         r"fields: stamp_ns, tick, sim_time_ns, joint_names, q,"):
        export_topic(DEMO, KEYS.arm_state.key, fields=["q", "foo"])
    with pytest.raises(ValueError, match=r"field 'data' of \S+ cannot be a column: bytes"):
        export_topic(FIXTURE, KEYS.camera_image("cam0").key, fields=["data"])
    with pytest.raises(ValueError, match=f"no messages on {state} between 9 s and the end"):
        export_topic(DEMO, KEYS.arm_state.key, start_s=9.0)
    with pytest.raises(ValueError, match="--end 1 s is before --start 2 s"):
        export_topic(DEMO, KEYS.arm_state.key, start_s=2.0, end_s=1.0)


def test_export_of_a_truncated_file_exports_the_readable_part(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    cut = _cut(tmp_path, 0.25)
    readable = [s for s in read_samples(cut, quiet=True) if s.topic == KEYS.arm_state.key]
    out = tmp_path / "s.npz"
    code, _, err = _psm(capsys, "export", str(cut), "--topic", KEYS.arm_state.key,
                        "--npz", str(out))
    assert code == 0
    assert err.splitlines()[0].startswith(f"psm export: warning: {cut}: truncated recording")
    with np.load(out) as npz:
        assert npz["log_time_ns"].tolist() == [s.log_time_ns for s in readable]


def test_export_errors_are_one_line(tmp_path: Path) -> None:
    out = tmp_path / "x.csv"
    nope = KEYS.goal("nope").key
    msg = one_error_line(run_psm("export", str(DEMO), "--topic", nope, "--csv", str(out)),
                         "psm export")
    assert msg == (f"{DEMO}: no topic '{nope}'; topics: {KEYS.arm_state.key}, "
                   f"{KEYS.arm_transforms.key}")
    msg = one_error_line(run_psm("export", str(DEMO), "--topic", KEYS.arm_state.key),
                         "psm export")
    assert msg == "nothing to write: give --csv OUT.csv and/or --npz OUT.npz"
    copy = tmp_path / "demo.mcap"
    copy.write_bytes(DEMO.read_bytes())
    msg = one_error_line(run_psm("export", str(copy), "--topic", KEYS.arm_state.key,
                                 "--csv", str(copy)), "psm export")
    assert msg == f"{copy}: is the input recording; choose another output file"
    assert copy.read_bytes() == DEMO.read_bytes()
    assert not out.exists() and not list(tmp_path.glob(".*.tmp"))


def test_csv_is_readable_by_numpy_as_numbers(tmp_path: Path) -> None:
    """A CSV of numeric fields loads as one float matrix (what MATLAB's readmatrix does)."""
    out = tmp_path / "q.csv"
    assert main(["export", str(DEMO), "--topic", KEYS.arm_state.key, "--fields", "q",
                 "--csv", str(out)]) == 0
    text = out.read_text()
    m = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1)
    cols = export_topic(DEMO, KEYS.arm_state.key, fields=["q"]).columns
    assert m.shape == (1801, 10)
    assert np.array_equal(m[:, 3:], np.stack([cols[f"q.{i}"] for i in range(7)], axis=1))
    assert np.array_equal(m[:, 2], cols["t_s"])


def test_csv_to_stdout_and_through_a_link(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _psm(capsys, "export", str(DEMO), "--topic", KEYS.arm_state.key,
                          "--fields", "tick", "--end", "0.004", "--csv", "-")
    assert code == 0
    assert out == ("log_time_ns,publish_time_ns,t_s,tick\n0,0,0.0,0\n2000000,2000000,0.002,1\n"
                   "4000000,4000000,0.004,2\n")
    assert err == "wrote -: 3 rows x 4 columns (psm/arm/state, psm.ArmState)\n".replace(
        "psm/arm/state", KEYS.arm_state.key)
    target, link = tmp_path / "target.csv", tmp_path / "link.csv"
    target.write_text("old\n")
    link.symlink_to(target)
    assert main(["export", str(DEMO), "--topic", KEYS.arm_state.key, "--fields", "tick",
                 "--end", "0.004", "--csv", str(link)]) == 0
    assert link.is_symlink() and target.read_text() == out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.csv", "target.csv"]


def test_a_closed_pipe_ends_quietly() -> None:
    """``psm info FILE | head -1``: the reader goes away; no traceback. The JSON output ends with
    the SIGPIPE exit code (the dispatcher), the table with rich's own quiet exit (code 1)."""
    import os
    import subprocess
    import sys

    from .helpers import ROOT

    env = {k: v for k, v in os.environ.items() if not k.startswith("PSM_")}
    env["PYTHONPATH"] = str(ROOT)
    for args, code in ((["--json"], 141), ([], 1)):
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "info", *args, str(DEMO)],
                                cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None and proc.stderr is not None
        proc.stdout.close()  # before the command writes anything
        err = proc.stderr.read().decode()
        assert (proc.wait(timeout=60), err) == (code, ""), args
