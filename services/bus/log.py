"""Read a recording (MCAP written by ``psm record``) as typed bus messages.

Example::

    from services.bus.log import read_log
    from services.bus.messages import ArmState

    for topic, msg, stamp_ns in read_log("out/run.mcap", topics=["psm/arm/state"]):
        assert isinstance(msg, ArmState)

Files are read front to back with mcap's non-seeking reader, in recorded (receive) order, so a
file whose writer was killed is read up to its last complete chunk (``strict=False``, the
default, stops quietly there; ``strict=True`` raises :class:`LogReadError`). Key-expression
wildcards (``psm/goals/*``, ``psm/**``) are accepted in ``topics``.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import Message

from services.bus.messages import ENCODING_PREFIX, MessageDecodeError, decode

__all__ = ["LogReadError", "RecordedSample", "read_log", "read_metadata", "read_samples"]

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


def _topic_matcher(topics: Iterable[str] | str | None):  # type: ignore[no-untyped-def]
    if topics is None:
        return None
    if isinstance(topics, str):
        topics = [topics]
    exprs = list(topics)
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


def read_samples(
    path: str | Path,
    topics: Iterable[str] | str | None = None,
    *,
    strict: bool = False,
) -> Iterator[RecordedSample]:
    """Every recorded sample of ``path`` (optionally only ``topics``), in file order."""
    from mcap.exceptions import EndOfFile, McapError
    from mcap.reader import NonSeekingReader

    match = _topic_matcher(topics)
    path = Path(path)
    with path.open("rb") as fh:
        reader = NonSeekingReader(fh)
        encodings: dict[int, str] = {}
        try:
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if match is not None and not match(channel.topic):
                    continue
                enc = encodings.get(channel.id)
                if enc is None:
                    enc = encodings[channel.id] = _encoding_of(channel, schema)
                yield RecordedSample(
                    channel.topic,
                    enc,
                    message.data,
                    message.log_time,
                    message.publish_time,
                    message.sequence,
                )
        except (EndOfFile, struct.error):
            if strict:
                raise LogReadError(f"{path}: truncated recording (no footer)") from None
            _log.warning("truncated recording, read up to the last complete chunk",
                         extra={"path": str(path)})
        except (McapError, ValueError) as exc:
            if strict:
                raise LogReadError(f"{path}: not a readable MCAP file: {exc}") from None
            _log.warning("unreadable tail of recording: %s", exc, extra={"path": str(path)})


def read_log(
    path: str | Path,
    topics: Iterable[str] | str | None = None,
    *,
    strict: bool = False,
    skip_undecodable: bool = True,
) -> Iterator[tuple[str, Message, int]]:
    """Yield ``(topic, message, stamp_ns)`` for every recorded bus message.

    ``message`` is the typed protobuf (decoded with :func:`services.bus.messages.decode`);
    ``stamp_ns`` is the message's own stamp (the MCAP ``publish_time``; the receive time if the
    message had none). Samples that do not decode (garbage, unknown encodings) are skipped
    with a warning, or raise :class:`LogReadError` if ``skip_undecodable`` is false.
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
    """The metadata records of a recording, by name (e.g. ``psm.recorder``)."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Metadata
    from mcap.stream_reader import StreamReader

    out: dict[str, dict[str, str]] = {}
    with Path(path).open("rb") as fh:
        try:
            for record in StreamReader(fh).records:
                if isinstance(record, Metadata):
                    out[record.name] = dict(record.metadata)
        except EndOfFile:
            pass
    return out
