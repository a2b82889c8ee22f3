"""The recorder's lean MCAP writer produces files the reference readers fully understand."""

from __future__ import annotations

import io
from pathlib import Path

from mcap.reader import NonSeekingReader, SeekingReader
from mcap.writer import CompressionType, Writer

from services.bus.mcap_writer import FastMcapWriter


def _messages() -> list[tuple[int, int, bytes]]:
    # (channel index, log time, data): interleaved channels, times not monotonic per file
    out = []
    for i in range(3000):
        out.append((i % 3, 1_000 + (i * 7919) % 5000 + i * 10, f"msg{i}".encode() * (i % 5 + 1)))
    return out


def _write(writer, msgs) -> None:  # type: ignore[no-untyped-def]
    writer.start(profile="", library="test")
    sid = writer.register_schema(name="s", encoding="protobuf", data=b"\x01\x02")
    chans = [writer.register_channel(topic=f"t/{k}", message_encoding="protobuf",
                                     schema_id=sid if k else 0, metadata={"k": str(k)})
             for k in range(3)]
    writer.add_metadata("meta", {"a": "b"})
    for k, t, data in msgs:
        writer.add_message(chans[k], t, data, t + 1, 7)
    writer.finish()


def _read_all(buf: bytes, **kw):  # type: ignore[no-untyped-def]
    r = SeekingReader(io.BytesIO(buf), validate_crcs=True)
    return [(c.topic, m.log_time, m.publish_time, m.data, m.sequence)
            for _, c, m in r.iter_messages(**kw)]


def test_same_content_as_reference_writer(tmp_path: Path) -> None:
    msgs = _messages()
    fast_buf, ref_buf = io.BytesIO(), io.BytesIO()
    for comp, ref_comp in (("zstd", CompressionType.ZSTD), ("", CompressionType.NONE)):
        fast_buf, ref_buf = io.BytesIO(), io.BytesIO()
        _write(FastMcapWriter(fast_buf, chunk_size=4096, compression=comp), msgs)
        _write(Writer(ref_buf, chunk_size=4096, compression=ref_comp), msgs)
        fast, ref = fast_buf.getvalue(), ref_buf.getvalue()
        for kw in ({}, {"log_time_order": False}, {"reverse": True},
                   {"topics": ["t/1"]}, {"starting_at": 20_000, "ending_before": 25_000}):
            assert _read_all(fast, **kw) == _read_all(ref, **kw), kw
        fs = SeekingReader(io.BytesIO(fast)).get_summary()
        rs = SeekingReader(io.BytesIO(ref)).get_summary()
        assert fs is not None and rs is not None
        assert fs.statistics.message_count == rs.statistics.message_count == len(msgs)
        assert fs.statistics.channel_message_counts == rs.statistics.channel_message_counts
        assert fs.statistics.message_start_time == rs.statistics.message_start_time
        assert fs.statistics.message_end_time == rs.statistics.message_end_time
        assert {c.topic for c in fs.channels.values()} == {"t/0", "t/1", "t/2"}
        assert len(fs.chunk_indexes) > 5
        assert [m.name for m in SeekingReader(io.BytesIO(fast)).iter_metadata()] == ["meta"]
        n = sum(1 for _ in NonSeekingReader(io.BytesIO(fast), validate_crcs=True)
                .iter_messages(log_time_order=False))
        assert n == len(msgs)


class _Disk(io.BytesIO):
    """A stream that refuses a write once ``budget`` bytes are used (a disk filling up)."""

    def __init__(self, budget: int) -> None:
        super().__init__()
        self.budget = budget

    def write(self, data) -> int:  # type: ignore[no-untyped-def, override]
        if self.tell() + len(data) > self.budget:
            raise OSError(28, "No space left on device")
        return super().write(data)


def test_a_failed_write_leaves_the_writer_able_to_end_the_file_validly() -> None:
    disk = _Disk(1 << 30)
    w = FastMcapWriter(disk, chunk_size=4096, compression="")
    w.start(profile="", library="test")
    cid = w.register_channel(topic="t", message_encoding="x", schema_id=0, metadata={})
    for i in range(2000):
        w.add_message(cid, i, b"m" * 50, i, i)
    w.flush()
    whole = w.message_count
    # The disk fills during the next chunk: the position stays at the last whole chunk.
    disk.budget = disk.tell() + 100
    try:
        for i in range(2000, 4000):
            w.add_message(cid, i, b"m" * 50, i, i)
        raise AssertionError("the chunk write did not fail")
    except OSError:
        pass
    assert w.position == disk.tell()  # the refused chunk is not counted as written
    dropped = w.abort_chunk()
    assert w.message_count == whole and dropped > 0
    # Even the end fails at first (too little room), then succeeds from the same place.
    disk.budget = w.position + 40
    try:
        w.finish()
        raise AssertionError("finish did not fail")
    except OSError:
        pass
    end = w.rewind()
    disk.truncate(end)
    disk.seek(end)
    disk.budget = 1 << 30
    w.finish()
    r = SeekingReader(io.BytesIO(disk.getvalue()), validate_crcs=True)
    assert r.get_summary().statistics.message_count == whole  # type: ignore[union-attr]
    assert [m.sequence for _s, _c, m in r.iter_messages()] == list(range(whole))
