"""``psm info FILE.mcap``: what a recording holds — what ``mcap info`` and ``ros2 bag info``
give.

The file is read once, front to back, with the same pass as :func:`services.bus.log.read_samples`
(every chunk's CRC is checked), so the counts, rates and bandwidths are exact and a damaged
file is reported, not trusted: a truncated recording (a recorder killed with SIGKILL leaves no
summary and no footer) or one with a corrupt chunk is described up to the last record that could
be read, with one warning line saying how far that is. A file that is not MCAP at all, or one
with no readable message before its damage, raises :class:`services.bus.log.LogReadError`.

Example::

    from services.bus.info import recording_info

    info = recording_info("data/demos/reach_person.mcap")
    print(info.messages, info.duration_s, [c.topic for c in info.channels])
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

__all__ = [
    "AttachmentInfo",
    "ChannelInfo",
    "RecordingInfo",
    "info_json",
    "print_info",
    "recording_info",
    "utc_iso",
]


@dataclass(frozen=True, slots=True)
class ChannelInfo:
    """One MCAP channel (a recorded key) and what was read of it.

    Times are MCAP ``log_time`` (receive time), ns; ``payload_bytes`` is the sum of the message
    payloads (record framing not counted).
    """

    id: int
    topic: str
    schema: str  # schema name, e.g. ``psm.ArmState``; "" for a schemaless channel
    schema_encoding: str  # e.g. ``protobuf``; "" for a schemaless channel
    message_encoding: str  # e.g. ``protobuf``
    messages: int
    payload_bytes: int
    first_ns: int | None  # None without messages
    last_ns: int | None

    @property
    def rate_hz(self) -> float | None:
        """Mean rate, Hz: messages minus one over the span from the first to the last message
        (``None`` with fewer than two messages or a zero span)."""
        if self.messages < 2 or self.first_ns is None or self.last_ns is None:
            return None
        span_ns = self.last_ns - self.first_ns
        return (self.messages - 1) / (span_ns * 1e-9) if span_ns > 0 else None

    @property
    def bandwidth_bps(self) -> float | None:
        """Mean bandwidth, bytes/s: the mean rate times the mean payload size (``None`` when
        the rate is)."""
        rate = self.rate_hz
        return None if rate is None else rate * self.payload_bytes / self.messages


@dataclass(frozen=True, slots=True)
class AttachmentInfo:
    """One MCAP attachment record: its name, media type, size (bytes) and log time (ns)."""

    name: str
    media_type: str
    size_bytes: int
    log_time_ns: int


@dataclass(frozen=True)
class RecordingInfo:
    """Everything :func:`recording_info` read of one file.

    ``readable_bytes`` is the offset just past the last complete record (``size_bytes`` for a
    complete file); ``problem`` is ``""`` for a complete file, else why the read stopped
    (``truncated`` true: the file ends early; else ``reason`` names the corrupt record).
    """

    path: Path
    size_bytes: int
    readable_bytes: int
    truncated: bool
    reason: str
    problem: str
    profile: str
    library: str
    channels: tuple[ChannelInfo, ...]
    metadata: dict[str, dict[str, str]]
    attachments: tuple[AttachmentInfo, ...]

    @property
    def complete(self) -> bool:
        """True if the file was read to its footer and closing magic."""
        return not self.problem

    @property
    def messages(self) -> int:
        """Messages read (on known channels)."""
        return sum(c.messages for c in self.channels)

    @property
    def start_ns(self) -> int | None:
        """Earliest message log time, ns (``None`` without messages)."""
        firsts = [c.first_ns for c in self.channels if c.first_ns is not None]
        return min(firsts) if firsts else None

    @property
    def end_ns(self) -> int | None:
        """Latest message log time, ns (``None`` without messages)."""
        lasts = [c.last_ns for c in self.channels if c.last_ns is not None]
        return max(lasts) if lasts else None

    @property
    def duration_s(self) -> float:
        """From the first to the last message, s (0 without messages)."""
        start, end = self.start_ns, self.end_ns
        return 0.0 if start is None or end is None else (end - start) * 1e-9

    def status(self) -> str:
        """One line: ``complete``, or how far a damaged file could be read, e.g.
        ``truncated: no summary; readable up to byte N of M (K messages in T s)``."""
        if self.complete:
            return "complete"
        readable = (f"readable up to byte {self.readable_bytes} of {self.size_bytes} "
                    f"({self.messages} messages in {self.duration_s:.3f} s)")
        if self.truncated:
            return f"truncated: no summary; {readable}"
        return f"corrupt at byte {self.readable_bytes} ({self.reason}); {readable}"


def utc_iso(ns: int) -> str:
    """A UNIX time in ns as an ISO 8601 UTC date with ns, e.g.
    ``2023-11-14T22:13:20.000000000Z`` (a sim-time recording starting at 0 shows 1970)."""
    seconds, frac = divmod(ns, 1_000_000_000)
    return datetime.fromtimestamp(seconds, tz=UTC).strftime("%Y-%m-%dT%H:%M:%S") + f".{frac:09d}Z"


class _Counts:
    """Running totals of one channel while the file is read."""

    __slots__ = ("bytes", "first", "last", "n")

    def __init__(self) -> None:
        self.n = 0
        self.bytes = 0
        self.first: int | None = None
        self.last: int | None = None


def recording_info(path: str | Path) -> RecordingInfo:
    """Read ``path`` once and describe it (see the module docstring).

    Raises:
        LogReadError: the file is empty or not MCAP, or it is damaged before its first
            readable message (the message says how far it could be read).
        OSError: the file cannot be opened.
    """
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

    from services.bus.log import LogReadError, RecordPass

    path = Path(path)
    reader = RecordPass(path)
    header: Header | None = None
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    counts: dict[int, _Counts] = {}
    metadata: dict[str, dict[str, str]] = {}
    attachments: list[AttachmentInfo] = []
    for record in reader.records():
        if isinstance(record, Message):
            c = counts.get(record.channel_id)
            if c is None:
                c = counts[record.channel_id] = _Counts()
            c.n += 1
            c.bytes += len(record.data)
            t = record.log_time
            if c.first is None or t < c.first:
                c.first = t
            if c.last is None or t > c.last:
                c.last = t
        elif isinstance(record, Channel):
            channels.setdefault(record.id, record)
        elif isinstance(record, Schema):
            schemas.setdefault(record.id, record)
        elif isinstance(record, Metadata):
            metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Attachment):
            attachments.append(AttachmentInfo(record.name, record.media_type, len(record.data),
                                              record.log_time))
        elif isinstance(record, Header):
            header = record
    infos = []
    for cid, ch in channels.items():
        schema = schemas.get(ch.schema_id)
        c = counts.get(cid, _Counts())
        infos.append(ChannelInfo(
            cid, ch.topic, schema.name if schema else "", schema.encoding if schema else "",
            ch.message_encoding, c.n, c.bytes, c.first, c.last,
        ))
    info = RecordingInfo(
        path, reader.size, reader.readable_bytes, reader.truncated, reader.reason,
        reader.problem, header.profile if header else "", header.library if header else "",
        tuple(sorted(infos, key=lambda i: (i.topic, i.id))), metadata, tuple(attachments),
    )
    if not info.complete and info.messages == 0:
        raise LogReadError(f"{path}: nothing readable: {info.status()}")
    return info


def info_json(info: RecordingInfo) -> dict[str, Any]:
    """``info`` as plain JSON values (what ``psm info --json`` prints). Times are ns and ISO
    UTC strings, rates Hz, bandwidths bytes/s; ``null`` where undefined."""
    start, end = info.start_ns, info.end_ns
    return {
        "path": str(info.path),
        "size_bytes": info.size_bytes,
        "readable_bytes": info.readable_bytes,
        "complete": info.complete,
        "status": info.status(),
        "profile": info.profile,
        "library": info.library,
        "messages": info.messages,
        "start_ns": start,
        "end_ns": end,
        "start_utc": None if start is None else utc_iso(start),
        "end_utc": None if end is None else utc_iso(end),
        "duration_s": info.duration_s,
        "channels": [
            {"id": c.id, "topic": c.topic, "schema": c.schema,
             "schema_encoding": c.schema_encoding, "message_encoding": c.message_encoding,
             "messages": c.messages, "payload_bytes": c.payload_bytes,
             "first_ns": c.first_ns, "last_ns": c.last_ns, "rate_hz": c.rate_hz,
             "bandwidth_bps": c.bandwidth_bps}
            for c in info.channels
        ],
        "metadata": info.metadata,
        "attachments": [
            {"name": a.name, "media_type": a.media_type, "size_bytes": a.size_bytes,
             "log_time_ns": a.log_time_ns}
            for a in info.attachments
        ],
    }


#: Longest metadata value shown in the terminal (characters); ``--json`` prints them whole.
METADATA_VALUE_CHARS = 72


def _human_size(n_bytes: int) -> str:
    """A file size for people: ``512 B``, ``23.2 kB``, ``1.5 GB`` (1 kB = 1000 B)."""
    if n_bytes < 1000:
        return f"{n_bytes} B"
    size = n_bytes / 1000
    for unit in ("kB", "MB", "GB"):
        if round(size, 1) < 1000 or unit == "GB":
            break
        size /= 1000
    return f"{size:.1f} {unit}"


def print_info(info: RecordingInfo, console: Any) -> None:
    """Print ``info`` for people on a ``rich`` console: the file's lines, the channel table,
    the metadata records and the attachments."""
    from rich.table import Table

    from services.bus.introspect import human_bandwidth

    start, end = info.start_ns, info.end_ns
    lines = [
        ("file", str(info.path)),
        ("size", f"{_human_size(info.size_bytes)} ({info.size_bytes} bytes)"),
        ("state", info.status()),
        ("library", info.library or "-"),
        ("profile", info.profile or "-"),
        ("messages", str(info.messages)),
        ("duration", f"{info.duration_s:.3f} s"),
        ("start", "-" if start is None else f"{utc_iso(start)} ({start} ns)"),
        ("end", "-" if end is None else f"{utc_iso(end)} ({end} ns)"),
    ]
    width = max(len(name) for name, _ in lines) + 3
    for name, value in lines:
        console.print(f"{name + ':':<{width}}{value}", markup=False, highlight=False)

    console.print(f"channels: {len(info.channels)}", markup=False, highlight=False)
    t = Table()
    right = {"messages", "rate Hz", "bandwidth"}
    for col in ("topic", "schema", "encoding", "messages", "rate Hz", "bandwidth"):
        t.add_column(col, justify="right" if col in right else "left")
    for c in info.channels:
        rate, bw = c.rate_hz, c.bandwidth_bps
        t.add_row(c.topic, c.schema or "(schemaless)", c.message_encoding, str(c.messages),
                  "-" if rate is None else f"{rate:.1f}",
                  "-" if bw is None else human_bandwidth(bw))
    console.print(t)

    console.print(f"metadata: {len(info.metadata) or 'none'}", markup=False, highlight=False)
    for name, values in info.metadata.items():
        console.print(f"  {name} ({len(values)} keys)", markup=False, highlight=False)
        key_width = max((len(k) for k in values), default=0) + 2
        for k, v in values.items():
            shown = v if len(v) <= METADATA_VALUE_CHARS else v[:METADATA_VALUE_CHARS - 1] + "…"
            console.print(f"    {k + ':':<{key_width}}{shown}", markup=False, highlight=False)
    console.print(f"attachments: {len(info.attachments) or 'none'}", markup=False,
                  highlight=False)
    for a in info.attachments:
        console.print(f"  {a.name} ({a.media_type or 'no media type'}, {a.size_bytes} bytes, "
                      f"log time {a.log_time_ns} ns)", markup=False, highlight=False)


def run_info(path: str | Path, *, as_json: bool = False) -> int:
    """``psm info``: print what ``path`` holds (``as_json``: one JSON object on stdout).

    Exit code 0, also for a truncated or corrupt file with readable messages: the table is
    then of the readable part and one warning line on stderr says how far that is
    (``psm info: warning: FILE: truncated: ...``). Errors (not MCAP, nothing readable) are
    raised for the dispatcher.
    """
    import sys

    info = recording_info(path)
    if not info.complete:
        print(f"psm info: warning: {info.path}: {info.status()}", file=sys.stderr)
    if as_json:
        json.dump(info_json(info), sys.stdout, indent=2, allow_nan=False)
        sys.stdout.write("\n")
        return 0
    from services.bus.introspect import terminal_console

    print_info(info, terminal_console())
    return 0
