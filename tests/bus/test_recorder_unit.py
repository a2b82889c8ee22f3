"""MCAP sink, reader and replay helpers without a bus."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap_protobuf.decoder import DecoderFactory

from services.bus.log import LogReadError, read_log, read_metadata, read_samples, scan_log
from services.bus.messages import ArmState, Goal, Keys, encode
from services.bus.recorder import McapSink, RecorderError
from services.bus.replayer import remap_key

from .fixture_data import PATH as FIXTURE
from .fixture_data import fixture_samples

K = Keys()


def _write(path: Path, n: int, **kw) -> McapSink:  # type: ignore[no-untyped-def]
    sink = McapSink(path, metadata={"project_version": "t", "config": "{}"}, **kw)
    for i in range(n):
        payload, enc = encode(ArmState(stamp_ns=1000 + i, tick=i, q=[0.5] * 7))
        sink.write(K.arm_state.key, enc, payload, 10_000 + i)
    return sink


def test_channels_schemas_times(tmp_path: Path) -> None:
    p = tmp_path / "a.mcap"
    sink = _write(p, 100)
    g, genc = encode(Goal(stamp_ns=7, name="x"))
    sink.write(K.goal("x").key, genc, g, 20_000)
    sink.write("psm/raw", "text/plain", b"hello", 20_001)
    sink.close()
    with p.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 102
        topics = {c.topic: c for c in summary.channels.values()}
        assert topics["psm/arm/state"].message_encoding == "protobuf"
        assert summary.schemas[topics["psm/arm/state"].schema_id].name == "psm.ArmState"
        assert topics["psm/raw"].schema_id == 0
        assert topics["psm/raw"].metadata["zenoh_encoding"] == "text/plain"
        msgs = list(reader.iter_messages(topics=["psm/arm/state"]))
        assert [m.publish_time for _, _, m in msgs] == [1000 + i for i in range(100)]
        assert [m.log_time for _, _, m in msgs] == [10_000 + i for i in range(100)]
    typed = list(read_log(p))  # the raw text sample is skipped, the rest decode
    assert len(typed) == 101
    assert isinstance(typed[-1][1], Goal) and typed[-1][2] == 7
    assert read_metadata(p)["psm.recorder"]["project_version"] == "t"


def test_split_by_size(tmp_path: Path) -> None:
    sink = _write(tmp_path / "s.mcap", 3000, split_size_mb=0.05, chunk_size=8192,
                  compression="none")
    sink.close()
    assert len(sink.paths) >= 3
    assert [p.name for p in sink.paths[:2]] == ["s-0000.mcap", "s-0001.mcap"]
    total = 0
    for p in sink.paths:
        with p.open("rb") as fh:
            total += make_reader(fh).get_summary().statistics.message_count
    assert total == 3000


def test_split_by_duration(tmp_path: Path) -> None:
    sink = McapSink(tmp_path / "d.mcap", split_duration_s=1.0)
    payload, enc = encode(ArmState(stamp_ns=1))
    for i in range(50):  # 50 samples 100 ms apart -> 5 s -> 5 files
        sink.write(K.arm_state.key, enc, payload, i * 100_000_000)
    sink.close()
    assert len(sink.paths) == 5
    assert sum(len(list(read_samples(p))) for p in sink.paths) == 50


def test_unwritable_paths_fail_at_start(tmp_path: Path) -> None:
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    with pytest.raises(RecorderError, match="cannot create directory"):
        McapSink(not_a_dir / "x.mcap")


def test_read_only_directory_fails_at_start(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        # root ignores the mode bits: then use a directory nobody can create files in (procfs),
        # so the test runs, and can fail, in CI as well.
        target = ro if not os.access(ro, os.W_OK) else Path("/proc")
        with pytest.raises(RecorderError, match="cannot"):
            McapSink(target / "x.mcap")
    finally:
        ro.chmod(0o700)


def test_existing_file_and_disk_space_fail_at_start(tmp_path: Path) -> None:
    (tmp_path / "e.mcap").write_bytes(b"x")
    with pytest.raises(RecorderError, match="exists"):
        McapSink(tmp_path / "e.mcap")
    with pytest.raises(RecorderError, match="MB free"):
        McapSink(tmp_path / "f.mcap", min_free_mb=1e12)
    with pytest.raises(RecorderError, match="cannot"):
        McapSink(Path("/proc/psm-no-such-dir/x.mcap"))


def test_truncated_file_reads_up_to_last_chunk(tmp_path: Path) -> None:
    p = tmp_path / "t.mcap"
    sink = _write(p, 2000, chunk_size=4096)
    sink.close()
    data = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    got = [m.tick for _, m, _ in read_log(cut)]
    assert 0 < len(got) < 2000
    assert got == list(range(len(got)))  # a prefix, in order
    with pytest.raises(LogReadError, match="truncated"):
        list(read_log(cut, strict=True))
    with cut.open("rb") as fh:  # the plain mcap reader agrees up to the truncation
        n = 0
        try:
            for _ in NonSeekingReader(fh).iter_messages(log_time_order=False):
                n += 1
        except Exception:
            pass
        assert n == len(got)


def test_committed_fixture_matches_generator() -> None:
    got = [(s.topic, s.encoding, s.payload, s.log_time_ns) for s in read_samples(FIXTURE)]
    assert got == fixture_samples()


def test_read_log_topic_filter_with_wildcards() -> None:
    goals = list(read_log(FIXTURE, topics=["psm/goals/*"]))
    assert len(goals) == 4 and all(isinstance(m, Goal) for _, m, _ in goals)
    arm = list(read_log(FIXTURE, topics="psm/arm/**"))
    assert len(arm) == 80


def test_remap_key() -> None:
    assert remap_key("psm/arm/state", "psm=sim") == "sim/arm/state"
    assert remap_key("psmx/arm/state", "psm=sim") == "psmx/arm/state"
    assert remap_key("psm/arm/state", "psm=cell/2") == "cell/2/arm/state"
    assert remap_key("psm/arm/state", "") == "psm/arm/state"


def test_scan_log_reports_damage_and_refuses_non_mcap(tmp_path: Path) -> None:
    whole = scan_log(FIXTURE)
    assert whole.complete and whole.messages == len(fixture_samples())
    assert list(whole.keys) == list(dict.fromkeys(k for k, *_ in fixture_samples()))
    data = FIXTURE.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 4])
    sc = scan_log(cut)
    assert not sc.complete and 0 < sc.messages < whole.messages
    assert sc.problem == (f"truncated recording (no footer): {sc.messages} messages readable "
                          f"in the first {sc.readable_bytes} of {len(data) // 4} bytes")
    bad = bytearray(data)
    mid = len(data) // 3
    bad[mid:mid + 64] = bytes(64)  # zeros inside a chunk: its CRC or compression fails
    (tmp_path / "bad.mcap").write_bytes(bad)
    sc = scan_log(tmp_path / "bad.mcap")
    assert sc.problem.startswith("corrupt recording at byte ") and sc.messages < whole.messages
    with pytest.raises(LogReadError, match="corrupt recording"):
        list(read_samples(tmp_path / "bad.mcap", strict=True))
    (tmp_path / "g.mcap").write_bytes(b"GARBAGE!" * 20)
    (tmp_path / "e.mcap").write_bytes(b"")
    for name, match in (("g.mcap", "not an MCAP file"), ("e.mcap", "empty file")):
        for read in (scan_log, lambda p: list(read_samples(p)), read_metadata,
                     lambda p: list(read_log(p))):
            with pytest.raises(LogReadError, match=match):
                read(tmp_path / name)


def test_discard_removes_the_files_of_a_failed_start(tmp_path: Path) -> None:
    sink = _write(tmp_path / "x.mcap", 10, split_size_mb=1.0)
    assert [p.name for p in sink.paths] == ["x-0000.mcap"] and sink.paths[0].exists()
    sink.discard()
    assert list(tmp_path.iterdir()) == []
    sink.close()  # nothing left to finalise: no error
    McapSink(tmp_path / "x.mcap", split_size_mb=1.0).close()  # a retry needs no overwrite


def test_session_errors_name_the_endpoint() -> None:
    from services.bus.errors import session_error, zenoh_reason

    exc = RuntimeError("Unable to connect to any of [Single(tcp/127.0.0.1:7599)]!  at "
                       "/root/.cargo/git/x/zenoh/src/net/runtime/orchestrator.rs:447.")
    assert zenoh_reason(exc) == "Unable to connect to any of [Single(tcp/127.0.0.1:7599)]!"
    err = session_error(exc, "client", ["tcp/127.0.0.1:7599"], [])
    assert str(err).startswith("cannot connect to tcp/127.0.0.1:7599 (client mode): ")
    err = session_error(exc, "peer", ["tcp/127.0.0.1:7599"], [], zid="1ab")
    assert str(err).startswith("cannot connect to tcp/127.0.0.1:7599 (peer mode) as zenoh id 1ab: "
                               "a session with this id is already connected there")
    exc = RuntimeError("Can not create a new TCP listener bound to tcp/127.0.0.1:7601: "
                       "[127.0.0.1:7601: Address already in use (os error 98) at a/tcp.rs:61.] "
                       "at b/unicast.rs:338.")
    err = session_error(exc, "router", [], ["tcp/127.0.0.1:7601"])
    assert str(err) == "cannot listen on tcp/127.0.0.1:7601 (router mode): address already in use"
    exc = RuntimeError('Json5Err(Message { msg: "Endpoints must be of the form '
                       '<protocol>/<address>: foo at c/endpoint.rs:615.", location: None }) '
                       "at d/config.rs:86.")
    assert str(session_error(exc, "peer", ["foo"], [])) == (
        "cannot open a zenoh session (peer mode, connect foo): Endpoints must be of the form "
        "<protocol>/<address>: foo")


def test_validate_key_expr() -> None:
    from services.bus.messages import InvalidKeyError, validate_key_expr

    assert validate_key_expr("psm/**") == "psm/**"
    assert validate_key_expr("psm/goals/*") == "psm/goals/*"
    for bad in ("bad//key", "psm/", "", "psm/*x", "psm/a?b", "psm/**/**"):
        with pytest.raises(InvalidKeyError, match=r"invalid key expression "):
            validate_key_expr(bad)
    with pytest.raises(InvalidKeyError, match="'bad//key'"):
        list(read_samples(FIXTURE, topics=["bad//key"]))
