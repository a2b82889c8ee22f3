"""Read a recording (MCAP written by ``psm record``) as typed bus messages.

Example::

    from services.bus.log import read_log
    from services.bus.messages import ArmState

    for topic, msg, stamp_ns in read_log("out/run.mcap", topics=["psm/arm/state"]):
        assert isinstance(msg, ArmState)

Files are read front to back with mcap's stream reader, in recorded (receive) order, checking
every chunk's CRC, so a file whose writer was killed is read up to its last complete chunk
(``strict=False``, the default, stops there with a warning; ``strict=True`` raises
:class:`LogReadError` saying how much was readable). A file that is not MCAP at all (empty, wrong
magic) always raises :class:`LogReadError`. :func:`scan_log` reads a file once and reports its
keys, message count and completeness. Key-expression wildcards (``psm/goals/*``, ``psm/**``)
are accepted in ``topics``.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import Message

from services.bus.messages import ENCODING_PREFIX, MessageDecodeError, decode

__all__ = [
    "LogReadError",
    "LogScan",
    "RecordPass",
    "RecordedSample",
    "read_log",
    "read_metadata",
    "read_samples",
    "scan_log",
    "topic_matcher",
]

_log = logging.getLogger("psm.log")


class LogReadError(ValueError):
    """A recording cannot be read (not MCAP, truncated in strict mode, undecodable message)."""


@dataclass(frozen=True, slots=True)
class RecordedSample:
    """One recorded sample, undecoded.

    ``log_time_ns`` is the receive time, ``publish_time_ns`` the message's own stamp (UNIX or
    sim-time ns, see the schema), ``encoding`` the Zenoh encoding string.
    """

    topic: str
    encoding: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int


def topic_matcher(topics: Iterable[str] | str | None) -> Callable[[str], bool] | None:
    """A predicate that is true for keys matching any of the key expressions ``topics``
    (``None``: no filter)."""
    if topics is None:
        return None
    if isinstance(topics, str):
        topics = [topics]
    from services.bus.messages import validate_key_expr

    exprs = [validate_key_expr(t) for t in topics]
    if not any(ch in t for t in exprs for ch in "*$"):
        wanted = set(exprs)
        return wanted.__contains__
    import zenoh

    kes = [zenoh.KeyExpr(t) for t in exprs]
    cache: dict[str, bool] = {}

    def match(topic: str) -> bool:
        hit = cache.get(topic)
        if hit is None:
            hit = cache[topic] = any(ke.intersects(topic) for ke in kes)
        return hit

    return match


def _encoding_of(channel: object, schema: object | None) -> str:
    enc = getattr(channel, "metadata", {}).get("zenoh_encoding")
    if enc:
        return str(enc)
    if schema is not None and getattr(channel, "message_encoding", "") == "protobuf":
        return ENCODING_PREFIX + schema.name  # type: ignore[attr-defined]
    return str(getattr(channel, "message_encoding", ""))


class RecordPass:
    """One front-to-back pass over an MCAP file that stops at the first incomplete or corrupt
    record and says why.

    ``records()`` yields every record in file order (``mcap.records`` objects: header, schemas,
    channels, messages, metadata, attachments, then the summary's records; the records inside
    each chunk after checking the chunk's CRC). A file that is not MCAP at all (empty, wrong
    magic) raises :class:`LogReadError` at once; for a truncated or corrupt one the iteration
    ends early and :attr:`problem` says how much was readable (:attr:`truncated`: it ran into
    the end of the file; else :attr:`reason` says what was corrupt).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.size = 0  # file size, bytes
        self.readable_bytes = 0  # offset just past the last complete record, bytes
        self.messages = 0  # message records yielded
        self.complete = False  # footer and closing magic read
        self.truncated = False  # stopped at the end of the file (not at a corrupt record)
        self.reason = ""  # why a corrupt file stopped (e.g. a CRC mismatch); "" if truncated
        self.problem = ""  # one line when the pass stopped early

    def records(self) -> Iterator[object]:
        from mcap.exceptions import EndOfFile, InvalidMagic
        from mcap.records import Chunk, Message
        from mcap.stream_reader import StreamReader, breakup_chunk

        with self.path.open("rb") as fh:
            self.size = os.fstat(fh.fileno()).st_size
            if self.size == 0:
                raise LogReadError(f"{self.path}: empty file, not an MCAP recording")
            records = StreamReader(fh, emit_chunks=True).records
            while True:
                try:
                    record = next(records)
                    inner = breakup_chunk(record, validate_crc=True) if isinstance(
                        record, Chunk) else (record,)
                except StopIteration:
                    self.complete = True
                    self.readable_bytes = self.size
                    return
                except InvalidMagic:
                    if self.readable_bytes == 0:
                        raise LogReadError(
                            f"{self.path}: not an MCAP file (no MCAP magic at the start)"
                        ) from None
                    self._stop(fh.tell(), "the closing magic is wrong")
                    return
                except Exception as exc:  # any failure to parse the bytes (zstd, CRC, ...)
                    at_end = isinstance(exc, EndOfFile | struct.error) or fh.tell() >= self.size
                    self._stop(fh.tell(), "" if at_end else f"{type(exc).__name__}: {exc}")
                    return
                self.readable_bytes = fh.tell()
                for r in inner:
                    if isinstance(r, Message):
                        self.messages += 1
                    yield r

    def _stop(self, pos: int, reason: str) -> None:
        """Record why the pass stopped: truncated when it ran into the end of the file."""
        readable = (f"{self.messages} messages readable in the first {self.readable_bytes} of "
                    f"{self.size} bytes")
        if not reason and pos >= self.size:
            self.truncated = True
            self.problem = f"truncated recording (no footer): {readable}"
        else:
            self.reason = " ".join(reason.split())[:200] or "unreadable record"
            self.problem = (f"corrupt recording at byte {self.readable_bytes} ({self.reason}): "
                            f"{readable}")


@dataclass(frozen=True)
class LogScan:
    """What a whole pass over a recording found (:func:`scan_log`).

    ``keys`` maps every recorded key to its Zenoh encoding (first-seen order); ``messages`` is
    the number of readable messages, ``readable_bytes`` / ``size_bytes`` how far the file
    could be read; ``problem`` is ``""`` for a complete file, else one line (truncated or
    corrupt, with the counts).
    """

    path: Path
    keys: dict[str, str]
    messages: int
    readable_bytes: int
    size_bytes: int
    problem: str

    @property
    def complete(self) -> bool:
        """True if the file was read to its footer."""
        return not self.problem


def read_samples(
    path: str | Path,
    topics: Iterable[str] | str | None = None,
    *,
    strict: bool = False,
    quiet: bool = False,
) -> Iterator[RecordedSample]:
    """Every recorded sample of ``path`` (optionally only ``topics``), in file order.

    A file that is not MCAP (empty, wrong magic) raises :class:`LogReadError`. A truncated or
    corrupt file yields every message up to the last complete chunk, then logs a warning
    (``strict=False``; none with ``quiet``, for callers that report it themselves) or raises
    :class:`LogReadError` naming how much was readable (``strict=True``).
    """
    from mcap.records import Channel, Message, Schema

    match = topic_matcher(topics)
    path = Path(path)
    reader = RecordPass(path)
    schemas: dict[int, object] = {}
    channels: dict[int, object] = {}
    encodings: dict[int, str] = {}
    for record in reader.records():
        if isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None or (match is not None and not match(channel.topic)):
                continue
            enc = encodings.get(record.channel_id)
            if enc is None:
                schema = schemas.get(channel.schema_id)
                enc = encodings[record.channel_id] = _encoding_of(channel, schema)
            yield RecordedSample(channel.topic, enc, record.data, record.log_time,
                                 record.publish_time, record.sequence)
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Schema):
            schemas[record.id] = record
    if reader.problem:
        if strict:
            raise LogReadError(f"{path}: {reader.problem}")
        if not quiet:
            _log.warning("%s: %s", path, reader.problem, extra={"path": str(path)})


def scan_log(path: str | Path) -> LogScan:
    """Read a whole recording once without decoding: its keys, message count and whether it
    is complete. Raises :class:`LogReadError` if the file is not MCAP at all."""
    from mcap.records import Channel, Message, Schema

    path = Path(path)
    reader = RecordPass(path)
    schemas: dict[int, object] = {}
    channels: dict[int, object] = {}
    keys: dict[str, str] = {}
    for record in reader.records():
        if isinstance(record, Message):
            ch = channels.get(record.channel_id)
            if ch is not None and ch.topic not in keys:
                keys[ch.topic] = _encoding_of(ch, schemas.get(ch.schema_id))
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Schema):
            schemas[record.id] = record
    return LogScan(path, keys, reader.messages, reader.readable_bytes, reader.size,
                   reader.problem)


def read_log(
    path: str | Path,
    topics: Iterable[str] | str | None = None,
    *,
    strict: bool = False,
    skip_undecodable: bool = True,
) -> Iterator[tuple[str, Message, int]]:
    """Yield ``(topic, message, stamp_ns)`` for every recorded bus message.

    ``message`` is the typed protobuf (decoded with :func:`services.bus.messages.decode`);
    ``stamp_ns`` is the message's own stamp (the MCAP ``publish_time``, 0 a valid stamp; the
    receive time only for a message that carried no stamp field). Samples that do not decode
    (garbage, unknown encodings) are skipped with a warning, or raise :class:`LogReadError`
    if ``skip_undecodable`` is false.
    """
    skipped = 0
    for s in read_samples(path, topics, strict=strict):
        try:
            msg = decode(s.payload, s.encoding)
        except MessageDecodeError as exc:
            if not skip_undecodable:
                raise LogReadError(f"{path}: {s.topic}: {exc}") from None
            skipped += 1
            continue
        yield s.topic, msg, s.publish_time_ns
    if skipped:
        _log.warning("skipped %d undecodable samples", skipped, extra={"path": str(path)})


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The metadata records of a recording, by name (e.g. ``psm.recorder``): those before a
    truncation of the file. Raises :class:`LogReadError` if the file is not MCAP."""
    from mcap.records import Metadata

    out: dict[str, dict[str, str]] = {}
    for record in RecordPass(Path(path)).records():
        if isinstance(record, Metadata):
            out[record.name] = dict(record.metadata)
    return out
