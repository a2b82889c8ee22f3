"""``psm export FILE.mcap --topic KEY --csv OUT.csv | --npz OUT.npz``: one recorded topic as a
table, for pandas, NumPy and MATLAB users.

Every message is decoded with the protobuf schema stored in the file (mcap-protobuf-support's
decoder factory), so any protobuf channel can be exported, also one recorded by another version
of the project. Each message becomes one row:

* ``log_time_ns`` (receive time), ``publish_time_ns`` (the message's own stamp, see the schema)
  and ``t_s``: the log time in seconds since the recording's start (its first message on any
  topic; the start ``psm info`` prints), so tables exported from one file share a time axis;
* every scalar field, nested fields as dotted names (``pose.position.x``), repeated fields of
  one length in every exported message as indexed columns (``q.0`` ... ``q.6``; repeated
  messages too: ``transforms.0.translation.x``). An unset sub-message gives its fields' default
  values (protobuf's reading of it).

Left out (and listed, see :attr:`ExportTable.left_out`): ``bytes`` fields (e.g. image data),
map fields, repeated fields whose length varies between the exported messages or that are
empty in all of them, and columns that are not in every message.

A truncated or corrupt recording is exported up to its last readable record
(:attr:`ExportTable.problem` says how far).
"""

from __future__ import annotations

import csv
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf.descriptor import FieldDescriptor

__all__ = ["TIME_COLUMNS", "ExportTable", "export_topic", "write_csv", "write_npz"]

#: The columns every export starts with: receive time [ns], the message's stamp [ns], and the
#: receive time relative to the recording's first message [s].
TIME_COLUMNS: tuple[str, ...] = ("log_time_ns", "publish_time_ns", "t_s")


@dataclass(frozen=True)
class ExportTable:
    """One topic as columns.

    ``columns`` maps column name to a 1-D array of length ``rows`` (time columns first, then
    the fields in schema order); dtypes follow the protobuf field types (double → float64,
    float → float32, int32/enum → int32, int64 → int64, uint32 → uint32, uint64 → uint64,
    bool → bool, string → unicode). ``left_out`` maps a field path (``*`` for any index, e.g.
    ``boxes.*.label``) to why it is not a column; ``problem`` is ``""`` or how far a damaged
    file could be read; ``skipped`` counts messages that did not decode.
    """

    topic: str
    schema: str
    columns: dict[str, np.ndarray]
    left_out: dict[str, str]
    problem: str
    skipped: int

    @property
    def rows(self) -> int:
        """Number of rows (messages exported)."""
        return len(self.columns[TIME_COLUMNS[0]])


def _dtype_of(field: Any) -> np.dtype:
    """The NumPy dtype of a scalar protobuf field."""
    F = FieldDescriptor
    return np.dtype({
        F.CPPTYPE_DOUBLE: np.float64, F.CPPTYPE_FLOAT: np.float32, F.CPPTYPE_INT32: np.int32,
        F.CPPTYPE_INT64: np.int64, F.CPPTYPE_UINT32: np.uint32, F.CPPTYPE_UINT64: np.uint64,
        F.CPPTYPE_BOOL: np.bool_, F.CPPTYPE_ENUM: np.int32, F.CPPTYPE_STRING: np.str_,
    }[field.cpp_type])


class _Flattener:
    """Turns decoded messages into rows of ``(column, value, field)`` and remembers the
    lengths of repeated fields and the fields that cannot be columns."""

    def __init__(self) -> None:
        self.lengths: dict[str, set[int]] = {}  # repeated field path ('*' indices) -> lengths
        self.unsupported: dict[str, str] = {}  # field path -> reason

    def row(self, msg: Any) -> list[tuple[str, Any, Any]]:
        out: list[tuple[str, Any, Any]] = []
        self._walk(msg, "", "", out)
        return out

    def _walk(self, msg: Any, prefix: str, pattern: str, out: list[tuple[str, Any, Any]]) -> None:
        F = FieldDescriptor
        for field in msg.DESCRIPTOR.fields:
            name, pat = prefix + field.name, pattern + field.name
            if field.type == F.TYPE_BYTES:
                self.unsupported[pat] = "bytes"
                continue
            if field.message_type is not None and field.message_type.GetOptions().map_entry:
                self.unsupported[pat] = "map"
                continue
            value = getattr(msg, field.name)
            if field.is_repeated:
                self.lengths.setdefault(pat, set()).add(len(value))
                for i, item in enumerate(value):
                    if field.type == F.TYPE_MESSAGE:
                        self._walk(item, f"{name}.{i}.", f"{pat}.*.", out)
                    else:
                        out.append((f"{name}.{i}", item, field))
            elif field.type == F.TYPE_MESSAGE:
                self._walk(value, name + ".", pat + ".", out)
            else:
                out.append((name, value, field))


def _pattern(column: str) -> str:
    """A column's field path with its indices as ``*`` (``boxes.2.x`` → ``boxes.*.x``)."""
    return ".".join("*" if part.isdigit() else part for part in column.split("."))


def _selected(fields: Sequence[str] | None) -> Callable[[str], bool]:
    """Whether a column is one of ``fields`` (a column name or a prefix at a dot: ``q``
    selects ``q.0`` ...; ``None``: all)."""
    if fields is None:
        return lambda column: True
    wanted = tuple(fields)
    return lambda column: any(column == f or column.startswith(f + ".") for f in wanted)


def _read_topic(path: Path, topic: str) -> tuple[list[Any], int | None, list[str], str]:
    """One pass over ``path``: the message records of ``topic`` with their channels'
    schemas and encodings, the recording's first log time [ns], every topic seen, and the
    pass's problem line."""
    from mcap.records import Channel, Message, Schema

    from services.bus.log import RecordPass

    reader = RecordPass(path)
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    wanted: set[int] = set()
    records: list[Any] = []
    start: int | None = None
    for record in reader.records():
        if isinstance(record, Message):
            if start is None or record.log_time < start:
                start = record.log_time
            if record.channel_id in wanted:
                records.append((record, channels[record.channel_id],
                                schemas.get(channels[record.channel_id].schema_id)))
        elif isinstance(record, Channel):
            if record.id not in channels:
                channels[record.id] = record
                if record.topic == topic:
                    wanted.add(record.id)
        elif isinstance(record, Schema):
            schemas.setdefault(record.id, record)
    topics = sorted({ch.topic for ch in channels.values()})
    return records, start, topics, reader.problem


def export_topic(
    path: str | Path,
    topic: str,
    *,
    fields: Sequence[str] | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
) -> ExportTable:
    """The messages of ``topic`` in ``path`` as columns (see the module docstring).

    Args:
        path: MCAP recording.
        topic: the recorded key, exactly (e.g. ``psm/arm/state``).
        fields: only these fields (a column name, or a field whose columns to take, e.g.
            ``q`` or ``pose.position``); the time columns are always there. Default all.
        start_s, end_s: only messages whose log time is in ``[start_s, end_s]`` seconds since
            the recording's first message.

    Raises:
        LogReadError: not MCAP, or nothing readable.
        ValueError: unknown topic (the message lists the recorded ones), a channel that is
            not protobuf, no message in the window, unknown or unexportable ``fields``.
    """
    from mcap.exceptions import McapError
    from mcap_protobuf.decoder import DecoderFactory

    path = Path(path)
    if start_s is not None and end_s is not None and end_s < start_s:
        raise ValueError(f"--end {end_s:g} s is before --start {start_s:g} s")
    records, t0, topics, problem = _read_topic(path, topic)
    if topic not in topics:
        listed = ", ".join(topics) if topics else "none"
        raise ValueError(f"{path}: no topic {topic!r}; topics: {listed}"
                         + (f" ({problem})" if problem else ""))
    if t0 is not None:
        lo = None if start_s is None else t0 + round(start_s * 1e9)
        hi = None if end_s is None else t0 + round(end_s * 1e9)
        records = [r for r in records if (lo is None or r[0].log_time >= lo)
                   and (hi is None or r[0].log_time <= hi)]
    if not records:
        window = "" if start_s is None and end_s is None else (
            f" between {start_s or 0:g} s and " + ("the end" if end_s is None else f"{end_s:g} s"))
        raise ValueError(f"{path}: no messages on {topic}{window}"
                         + (f" ({problem})" if problem else ""))

    factory = DecoderFactory()
    decoders: dict[int, Callable[[bytes], Any]] = {}
    flat = _Flattener()
    times: list[tuple[int, int]] = []
    values: dict[str, list[Any]] = {}
    column_field: dict[str, Any] = {}
    irregular: set[str] = set()
    skipped = 0
    schema_names: list[str] = []
    for record, channel, schema in records:
        decode = decoders.get(channel.id)
        if decode is None:
            try:
                decode = factory.decoder_for(channel.message_encoding, schema)
            except McapError as exc:
                raise ValueError(f"{path}: {topic}: cannot read its schema: {exc}") from None
            if decode is None:
                raise ValueError(
                    f"{path}: {topic} has message encoding {channel.message_encoding!r}"
                    + (f" (schema encoding {schema.encoding!r})" if schema else " (no schema)")
                    + "; psm export decodes protobuf only")
            decoders[channel.id] = decode
            if schema.name not in schema_names:
                schema_names.append(schema.name)
        try:
            row = flat.row(decode(record.data))
        except Exception:  # malformed payload: protobuf raises DecodeError (and others)
            skipped += 1
            continue
        n = len(times)
        for column, value, field in row:
            col = values.get(column)
            if col is None:
                col = values[column] = []
                column_field[column] = field
            if len(col) != n:  # absent from an earlier message
                irregular.add(column)
            col.append(value)
        times.append((record.log_time, record.publish_time))
    if not times:
        raise ValueError(f"{path}: none of the {skipped} messages on {topic} decode")
    rows = len(times)
    irregular.update(c for c, v in values.items() if len(v) != rows)

    left_out = dict(flat.unsupported)
    for pat, lengths in flat.lengths.items():
        if len(lengths) > 1:
            left_out[pat] = f"variable length ({min(lengths)} to {max(lengths)})"
        elif lengths == {0}:
            left_out[pat] = "empty in every message"
    for column in irregular:
        pat = _pattern(column)
        if not any(pat == p or pat.startswith(p + ".") for p in left_out):
            left_out[pat] = "not in every message"

    keep = _selected(fields)
    if fields is not None:
        for f in fields:
            if any(f == c or c.startswith(f + ".") for c in values if c not in irregular):
                continue
            pat = _pattern(f)
            why = next((r for p, r in left_out.items() if pat == p or pat.startswith(p + ".")),
                       None)
            if why is not None:
                raise ValueError(f"field {f!r} of {topic} cannot be a column: {why}")
            available = ", ".join(dict.fromkeys(c.split(".")[0] for c in values))
            raise ValueError(f"no field {f!r} in {topic} ({', '.join(schema_names)}); "
                             f"fields: {available}")
        left_out = {p: r for p, r in left_out.items()
                    if any(p == _pattern(f) or p.startswith(_pattern(f) + ".") for f in fields)}

    log_ns = np.array([t[0] for t in times], dtype=np.int64)
    columns: dict[str, np.ndarray] = {
        "log_time_ns": log_ns,
        "publish_time_ns": np.array([t[1] for t in times], dtype=np.int64),
        "t_s": (log_ns - (t0 if t0 is not None else 0)) / 1e9,
    }
    for column, col in values.items():
        if column not in irregular and keep(column):
            columns[column] = np.array(col, dtype=_dtype_of(column_field[column]))
    return ExportTable(topic, ", ".join(schema_names), columns, left_out, problem, skipped)


def _cells(array: np.ndarray) -> Iterator[str]:
    """A column's values as CSV text: floats in their shortest round-trip form (float32 as
    float32), booleans as 0/1."""
    if array.dtype == np.float32:
        return (str(v) for v in array)  # numpy's shortest float32 repr
    if array.dtype.kind == "f":
        return (repr(v) for v in array.tolist())
    if array.dtype.kind == "b":
        return ("1" if v else "0" for v in array.tolist())
    return (str(v) for v in array.tolist())


def _write_file(out: Path, write: Callable[[Any], None], binary: bool) -> None:
    """Write ``out`` through a temporary file next to it, renamed over it on success (an
    interrupted export leaves no half-written file; a symbolic link's target is replaced). An
    existing path that is not a regular file (``/dev/stdout``, a FIFO) is written in place."""
    def open_(path: Path, mode: str) -> Any:
        return path.open(mode + "b") if binary else path.open(mode, newline="", encoding="utf-8")

    if out.exists() and not out.is_file():
        with open_(out, "w") as fh:
            write(fh)
        return
    target = out.resolve() if out.is_symlink() else out
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    try:
        with open_(tmp, "x") as fh:
            write(fh)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_csv(table: ExportTable, out: str | Path) -> None:
    """Write ``table`` as CSV: a header row of column names, one row per message (``out``
    ``-``: to stdout)."""
    def write(fh: Any) -> None:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(table.columns)
        w.writerows(zip(*(_cells(a) for a in table.columns.values()), strict=True))

    if str(out) == "-":
        write(sys.stdout)
        sys.stdout.flush()
        return
    _write_file(Path(out), write, binary=False)


def write_npz(table: ExportTable, out: str | Path) -> None:
    """Write ``table`` as an uncompressed NPZ: one ``.npy`` array per column, named as the
    column (``np.load(out)["q.0"]``; no pickled objects). Written as ``np.savez`` does, without
    its keyword arguments, so any column name works (``file`` too)."""
    import zipfile

    def write(fh: Any) -> None:
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, array in table.columns.items():
                with zf.open(name + ".npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, array, allow_pickle=False)

    _write_file(Path(out), write, binary=True)
