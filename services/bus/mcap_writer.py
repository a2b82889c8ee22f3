"""A lean MCAP writer for the recorder's hot path.

Writes the same file layout as ``mcap.writer.Writer`` (magic, header, chunked data section with
per-chunk message indexes, data end, summary with schemas, channels, statistics, chunk and
metadata indexes, summary offsets, footer) and reuses ``mcap.records`` to serialise every
record except messages. Messages are packed straight into the open chunk's ``bytearray`` with
one ``struct`` call, which makes ``add_message`` several times cheaper than the reference
writer (``benchmarks/bus.py`` measures the recorder end to end; the tests read every file back
with the reference ``mcap`` readers).

Every chunk is handed to the output stream with a single ``write`` call, so with a write-through
stream a killed process leaves only complete chunks (plus possibly one partial record at the
end, which non-seeking readers stop at).

A write that fails (a full disk) leaves the writer consistent: :attr:`FastMcapWriter.position`
is the end of the last record written whole, :meth:`FastMcapWriter.abort_chunk` drops the open
chunk (its messages leave the statistics), and :meth:`FastMcapWriter.finish` can then end the
file validly at that position once space is available again (the recorder keeps a reserve for
it); :meth:`FastMcapWriter.summary_size` bounds what the end of the file takes.
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict
from typing import Any

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

__all__ = ["MAGIC", "FastMcapWriter"]

MAGIC = b"\x89MCAP0\r\n"
_MSG = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log, publish
_MSG_FIXED = 2 + 4 + 8 + 8


class FastMcapWriter:
    """Chunked, indexed MCAP writer. ``compression`` is ``"zstd"``, ``"lz4"`` or ``""``."""

    def __init__(self, stream: Any, chunk_size: int = 256 * 1024, compression: str = "zstd"):
        self._out = stream
        self._pos = 0
        self.chunk_size = chunk_size
        if compression == "zstd":
            import zstandard

            self._compress = zstandard.ZstdCompressor(level=1).compress
        elif compression == "lz4":
            import lz4.frame

            self._compress = lz4.frame.compress
        elif compression in ("", "none"):
            compression = ""
            self._compress = None
        else:
            raise ValueError(f"unsupported compression {compression!r}")
        self.compression = compression
        self._buf = bytearray()
        self._index: dict[int, list[tuple[int, int]]] = {}
        self._chunk_start = 0
        self._chunk_end = 0
        self._chunk_msgs = 0
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: defaultdict[int, int] = defaultdict(int)
        self._n = 0
        self._t_start = 0
        self._t_end = 0
        self._metadata_count = 0
        # Bytes of the summary records known so far (schemas, channels, chunk and metadata
        # indexes): what finish() writes besides the fixed-size records.
        self._summary_records = 0
        self._data_end: int | None = None  # where finish() began (its data end record)

    # -- output ------------------------------------------------------------------------------
    def _write(self, data: bytes | bytearray) -> None:
        self._out.write(data)
        self._pos += len(data)

    def _write_records(self, *records: Any) -> int:
        rb = RecordBuilder()
        for r in records:
            r.write(rb)
        data = rb.end()
        offset = self._pos
        self._write(data)
        return offset

    @staticmethod
    def _serialise(record: Any) -> bytes:
        rb = RecordBuilder()
        record.write(rb)
        return rb.end()

    # -- API ---------------------------------------------------------------------------------
    def start(self, profile: str = "", library: str = "") -> None:
        """Write the magic and the header record."""
        self._write(MAGIC)
        self._write_records(Header(profile=profile, library=library))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Add a schema (written into the open chunk); returns its id (1, 2, ...)."""
        sid = len(self._schemas) + 1
        schema = Schema(id=sid, name=name, encoding=encoding, data=data)
        self._schemas[sid] = schema
        raw = self._serialise(schema)
        self._buf += raw
        self._summary_records += len(raw)
        return sid

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        """Add a channel (written into the open chunk); returns its id (1, 2, ...)."""
        cid = len(self._channels) + 1
        channel = Channel(id=cid, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata=dict(metadata))
        self._channels[cid] = channel
        raw = self._serialise(channel)
        self._buf += raw
        self._summary_records += len(raw)
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a metadata record (between chunks)."""
        record = Metadata(name=name, metadata=dict(data))
        raw = self._serialise(record)
        offset = self._pos
        self._write(raw)
        index = MetadataIndex(offset=offset, length=len(raw), name=name)
        self._metadata_indexes.append(index)
        self._summary_records += len(self._serialise(index))
        self._metadata_count += 1

    def add_message(
        self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0
    ) -> None:
        """Append one message to the open chunk (closing it when it reaches ``chunk_size``)."""
        buf = self._buf
        idx = self._index.get(channel_id)
        if idx is None:
            idx = self._index[channel_id] = []
        idx.append((log_time, len(buf)))
        buf += _MSG.pack(Opcode.MESSAGE, _MSG_FIXED + len(data), channel_id, sequence,
                         log_time, publish_time)
        buf += data
        if self._chunk_msgs == 0:
            self._chunk_start = self._chunk_end = log_time
        elif log_time < self._chunk_start:
            self._chunk_start = log_time
        elif log_time > self._chunk_end:
            self._chunk_end = log_time
        self._chunk_msgs += 1
        self._counts[channel_id] += 1
        if self._n == 0:
            self._t_start = self._t_end = log_time
        elif log_time < self._t_start:
            self._t_start = log_time
        elif log_time > self._t_end:
            self._t_end = log_time
        self._n += 1
        if len(buf) >= self.chunk_size:
            self._finish_chunk()

    def channel_message_counts(self) -> dict[int, int]:
        """Messages written per channel id."""
        return dict(self._counts)

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return self._n

    @property
    def position(self) -> int:
        """Bytes handed to the stream whole: the end of the last record written [bytes]."""
        return self._pos

    @property
    def pending_messages(self) -> int:
        """Messages in the open chunk (not yet handed to the stream)."""
        return self._chunk_msgs

    def summary_size(self) -> int:
        """An upper bound of the bytes :meth:`finish` writes when the open chunk is empty: data
        end, summary (schemas, channels, statistics, chunk and metadata indexes), summary
        offsets, footer and magic [bytes]."""
        statistics = 64 + 10 * len(self._channels)
        return self._summary_records + statistics + 13 + 5 * 29 + 29 + len(MAGIC) + 64

    def rewind(self) -> int:
        """After a failed :meth:`finish`: forget what it wrote, so that it can run again from the
        end of the data section; returns that position [bytes] (the stream must be cut there).
        Without a failed finish, the current :attr:`position`."""
        if self._data_end is not None:
            self._pos, self._data_end = self._data_end, None
        return self._pos

    def abort_chunk(self) -> int:
        """Drop the open chunk (its write failed, or it will not be written): its messages leave
        the counts and statistics; the schemas and channels it declared stay in the summary.
        Returns the number of messages dropped."""
        dropped = self._chunk_msgs
        for cid, records in self._index.items():
            self._counts[cid] -= len(records)
            if not self._counts[cid]:
                del self._counts[cid]
        self._n -= dropped
        if self._chunk_indexes:
            self._t_start = min(c.message_start_time for c in self._chunk_indexes)
            self._t_end = max(c.message_end_time for c in self._chunk_indexes)
        else:
            self._t_start = self._t_end = 0
        self._buf = bytearray()
        self._index = {}
        self._chunk_msgs = 0
        return dropped

    def _finish_chunk(self) -> None:
        if not self._buf:
            return
        if self._chunk_msgs == 0:
            # only schema/channel records: keep them for the next chunk
            return
        raw = bytes(self._buf)
        data = self._compress(raw) if self._compress is not None else raw
        chunk = Chunk(compression=self.compression, data=data,
                      message_start_time=self._chunk_start, message_end_time=self._chunk_end,
                      uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))
        chunk_bytes = self._serialise(chunk)
        rb = RecordBuilder()
        offsets: dict[int, int] = {}
        base = self._pos + len(chunk_bytes)
        for cid, records in self._index.items():
            offsets[cid] = base + rb.count
            MessageIndex(channel_id=cid, records=records).write(rb)
        index_bytes = rb.end()
        chunk_offset = self._pos
        # one write for chunk + its message indexes: all or nothing reaches the OS (a failed
        # write leaves the position, the index and the open chunk as they were)
        self._write(chunk_bytes + index_bytes)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=self._chunk_start, message_end_time=self._chunk_end,
            chunk_start_offset=chunk_offset, chunk_length=len(chunk_bytes),
            message_index_offsets=offsets, message_index_length=len(index_bytes),
            compression=self.compression, compressed_size=len(data),
            uncompressed_size=len(raw)))
        self._summary_records += len(self._serialise(self._chunk_indexes[-1]))
        self._buf = bytearray()
        self._index = {}
        self._chunk_msgs = 0

    def flush(self) -> None:
        """Close the open chunk (if it holds messages) and write it out."""
        self._finish_chunk()
        flush = getattr(self._out, "flush", None)
        if flush is not None:
            flush()

    def finish(self) -> None:
        """Close the last chunk and write data end, summary, summary offsets and footer."""
        self._finish_chunk()
        self._data_end = self._pos
        self._write_records(DataEnd(data_section_crc=0))
        summary_start = self._pos
        groups: list[tuple[int, list[Any]]] = [
            (Opcode.SCHEMA, list(self._schemas.values())),
            (Opcode.CHANNEL, list(self._channels.values())),
            (Opcode.STATISTICS, [Statistics(
                message_count=self._n, schema_count=len(self._schemas),
                channel_count=len(self._channels), attachment_count=0,
                metadata_count=self._metadata_count, chunk_count=len(self._chunk_indexes),
                message_start_time=self._t_start, message_end_time=self._t_end,
                channel_message_counts=dict(self._counts))]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        ]
        offsets = []
        for opcode, records in groups:
            if not records:
                continue
            start = self._pos
            self._write_records(*records)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=start,
                                         group_length=self._pos - start))
        summary_offset_start = self._pos
        if offsets:
            self._write_records(*offsets)
        rb = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start,
               summary_crc=0).write(rb)
        self._write(rb.end())
        self._write(MAGIC)
        flush = getattr(self._out, "flush", None)
        if flush is not None:
            flush()
