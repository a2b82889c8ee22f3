"""``psm record``: write every bus sample, bytes unchanged, to MCAP.

* Subscribes ``<prefix>/**`` (or the configured key expressions), with late-joiner history so
  latched goals/obstacle sets published before the recorder started are captured too.
* One MCAP channel per (key expression, encoding); the channel's schema is the protobuf
  ``FileDescriptorSet`` of the type named by the sample's encoding
  (``application/protobuf;psm.ArmState`` -> schema ``psm.ArmState``), so Foxglove and the
  ``mcap`` CLI decode the file without the project. Samples of unknown encodings are recorded
  schemaless (``message_encoding`` = the Zenoh encoding). The exact Zenoh encoding string is kept
  in the channel metadata (``zenoh_encoding``) for the replayer.
* ``log_time`` = receive time (UNIX ns, see below), always; ``publish_time`` = the message's own
  stamp on every channel (:func:`~services.bus.messages.stamp_ns_of`: ``stamp_ns``, or the
  Foxglove ``timestamp``), 0 included (sim time 0 in lockstep); only a message that carries no
  stamp (unknown encoding, absent Foxglove timestamp) gets the receive time;
  ``sequence`` = per-channel count.
* zstd chunks of ``chunk_size`` bytes written straight to the OS (no user-space buffering), and a
  chunk is closed at least every ``flush_interval_s``: after SIGKILL the file stays readable up
  to the last complete chunk with a non-seeking reader. SIGINT/SIGTERM finalise the file
  (summary, statistics, chunk and message indexes).
* A metadata record ``psm.recorder`` holds the config snapshot and the project version.
* ``split_size_mb`` / ``split_duration_s`` start a new file (``<stem>-0000.mcap``, ...).
* An unwritable path or too little free disk space raises :class:`RecorderError` at start.
* A full disk later (or any failed write) stops the recording, not the recorder: the space kept
  in a reserve file next to the recording (``.<name>.reserve``, at least
  :data:`SUMMARY_RESERVE_MIN` bytes and twice what the end of the file needs, grown as chunks
  accumulate) is released, the file is cut back to its last complete chunk and ends validly
  (summary, indexes, footer), one error line says so, and the service stays up, DEGRADED with
  that reason, counting what it no longer writes; its exit code is 1.

Samples reach the writer thread through a bounded zenoh channel (``"channel"`` delivery of
:class:`services.bus.runtime.Subscription`): Zenoh's receive thread runs no Python, and when the
writer falls behind, zenoh applies back-pressure instead of dropping. ``log_time`` is taken when
the writer thread takes the sample off that channel (= arrival time unless it is behind).

Example::

    psm record -o out/run.mcap --connect tcp/127.0.0.1:7447 --no-multicast
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import Field

from services.bus.config import Section, ServiceConfig, StrList, config_to_dict
from services.bus.errors import BusError
from services.bus.messages import (
    ENCODING_PREFIX,
    MESSAGE_TYPES,
    Keys,
    file_descriptor_set,
    stamp_ns_of,
    validate_key_expr,
)
from services.bus.runtime import Service, ServiceApp, run_service

__all__ = [
    "SUMMARY_RESERVE_MIN",
    "McapSink",
    "RecorderConfig",
    "RecorderError",
    "RecorderSection",
    "run_recorder",
]

#: The smallest reserve kept for the end of a recording [bytes] (a few hundred chunk indexes).
SUMMARY_RESERVE_MIN = 64 * 1024


class RecorderError(BusError):
    """The recorder cannot write its output (unwritable path, disk full, ...)."""


class RecorderSection(Section):
    """``[recorder]`` section."""

    output: str = Field("", description="output .mcap path (default out/recording-<UTC time>.mcap)")
    key_exprs: StrList = Field(
        default_factory=list,
        description="key expressions to record (default <prefix>/**)",
    )
    chunk_size: int = Field(256 * 1024, ge=1024, le=1 << 30, description="MCAP chunk size, bytes")
    compression: Literal['zstd', 'lz4', 'none'] = Field("zstd", description="chunk compression")
    flush_interval_s: float = Field(
        1.0, gt=0.0,
        description="close the open chunk at least this often, s (bounds loss on SIGKILL)",
    )
    split_size_mb: float = Field(0.0, ge=0.0, description="start a new file after this many MB (0 = never)")
    split_duration_s: float = Field(
        0.0, ge=0.0,
        description="start a new file after this many seconds (0 = never)",
    )
    min_free_mb: float = Field(64.0, ge=0.0, description="refuse to start with less free disk space, MB")
    history: bool = Field(True, description="fetch late-joiner history (latched goals, obstacles) at start")
    queue_size: int = Field(
        100_000, ge=1,
        description="samples buffered between Zenoh and the writer; when full, zenoh applies "
        "back-pressure (nothing is dropped)",
    )
    overwrite: bool = Field(False, description="overwrite an existing output file")


class RecorderConfig(ServiceConfig):
    """Recorder service configuration."""

    recorder: RecorderSection = Field(default_factory=RecorderSection)


class _UnbufferedFile:
    """Write-through file object for :class:`mcap.writer.Writer`: every ``write`` reaches the
    OS at once (the writer writes one whole chunk per call), so a killed process leaves every
    complete chunk on disk."""

    def __init__(self, path: Path, overwrite: bool) -> None:
        self._f = open(path, "wb" if overwrite else "xb", buffering=0)  # noqa: SIM115
        self.size = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        total = len(view)
        while view:
            n = self._f.write(view)
            if n is None or n <= 0:
                raise OSError(errno.EIO, "short write")
            view = view[n:]
        self.size += total
        return total

    def tell(self) -> int:
        return self.size

    def flush(self) -> None:
        """Nothing is buffered in user space."""

    def truncate(self, size: int) -> None:
        """Cut the file to ``size`` bytes (drops what a failed write left of a record)."""
        os.ftruncate(self._f.fileno(), size)
        self._f.seek(size)  # the next write goes at the new end, not where the failed one stopped
        self.size = size

    def close(self) -> None:
        self._f.close()


class _Reserve:
    """Disk space held for the end of a recording: a file of ``size`` allocated bytes
    (``posix_fallocate``: really allocated, not sparse) that is deleted to make room for the
    summary when the disk is full."""

    def __init__(self, path: Path, size: int) -> None:
        self.path = path
        path.unlink(missing_ok=True)  # a reserve left by a killed recorder
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        self.size = 0
        try:
            self.ensure(size)
        except OSError:
            self.release()
            raise

    def ensure(self, size: int) -> None:
        """Hold at least ``size`` bytes (OSError, e.g. ENOSPC, if the disk cannot give them)."""
        if size > self.size:
            os.posix_fallocate(self._fd, 0, size)
            self.size = size

    def release(self) -> None:
        """Give the space back (idempotent)."""
        if self._fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = -1
            self.path.unlink(missing_ok=True)


def _check_writable(path: Path, min_free_mb: float, overwrite: bool) -> None:
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecorderError(f"cannot create directory {parent}: {exc.strerror}") from None
    if path.exists() and not overwrite:
        raise RecorderError(f"{path} exists (use --overwrite or another --output)")
    if not os.access(parent, os.W_OK):
        raise RecorderError(f"cannot write to {parent}: permission denied")
    free_mb = shutil.disk_usage(parent).free / 1e6
    if free_mb < min_free_mb:
        raise RecorderError(
            f"only {free_mb:.1f} MB free in {parent} (need {min_free_mb:.0f} MB, "
            "see recorder.min_free_mb)"
        )


class McapSink:
    """Thread-safe MCAP writer with per-(key, encoding) channels, periodic chunk flushing,
    size/duration splitting and a valid end when a write fails (:attr:`failure`, see the
    module docstring): :meth:`write` and :meth:`flush` then raise :class:`RecorderError` with
    that one line, now and on every later call."""

    def __init__(
        self,
        path: str | Path,
        *,
        chunk_size: int = 256 * 1024,
        compression: str = "zstd",
        split_size_mb: float = 0.0,
        split_duration_s: float = 0.0,
        min_free_mb: float = 0.0,
        overwrite: bool = False,
        metadata: dict[str, str] | None = None,
        library: str = "psm-dataflow recorder",
    ) -> None:
        self.base = Path(path)
        self.chunk_size = chunk_size
        self.compression = compression
        self.split_bytes = int(split_size_mb * 1e6)
        self.split_ns = int(split_duration_s * 1e9)
        self.overwrite = overwrite
        self.metadata = dict(metadata or {})
        self.library = library
        self.min_free_mb = min_free_mb
        self.paths: list[Path] = []
        self.message_count = 0
        self.file_message_count = 0
        self._closed_counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._writer: Any = None
        self._file: _UnbufferedFile | None = None
        self._channels: dict[tuple[str, str], int] = {}
        self._schemas: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self._topics: dict[int, str] = {}
        self._file_start_ns = 0
        self._unflushed = 0
        self._closed = False
        self._reserve: _Reserve | None = None
        #: Why the recording stopped before :meth:`close` (one line; "" while it runs).
        self.failure = ""
        self._open_next()

    def _next_path(self) -> Path:
        if not (self.split_bytes or self.split_ns):
            return self.base
        return self.base.with_name(f"{self.base.stem}-{len(self.paths):04d}{self.base.suffix}")

    def _open_next(self) -> None:
        from services.bus.mcap_writer import FastMcapWriter

        path = self._next_path()
        _check_writable(path, self.min_free_mb, self.overwrite)
        try:
            self._file = _UnbufferedFile(path, self.overwrite)
        except FileExistsError:
            raise RecorderError(f"{path} exists (use --overwrite)") from None
        except OSError as exc:
            raise RecorderError(f"cannot write recording to {path}: {exc.strerror}") from None
        try:
            self._writer = FastMcapWriter(
                self._file, chunk_size=self.chunk_size, compression=self.compression
            )
            self._writer.start(profile="", library=self.library)
            meta_record = dict(self.metadata)
            meta_record["file_index"] = str(len(self.paths))
            meta_record["created_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            self._writer.add_metadata("psm.recorder", meta_record)
            self._reserve = _Reserve(
                path.with_name(f".{path.name}.reserve"),
                max(SUMMARY_RESERVE_MIN, 2 * self._writer.summary_size()),
            )
        except OSError as exc:
            # Nothing of this file is usable yet: no file rather than a stub.
            self._file.close()
            self._file = None
            path.unlink(missing_ok=True)
            raise RecorderError(f"cannot write recording to {path}: {exc.strerror}") from None
        self.paths.append(path)
        self._channels.clear()
        self._schemas.clear()
        self._seq.clear()
        self._topics.clear()
        self._file_start_ns = 0
        self.file_message_count = 0

    def _channel(self, key: str, encoding: str) -> int:
        w = self._writer
        schema_id = 0
        name = encoding[len(ENCODING_PREFIX) :] if encoding.startswith(ENCODING_PREFIX) else ""
        if name in MESSAGE_TYPES:
            schema_id = self._schemas.get(name, 0)
            if not schema_id:
                schema_id = w.register_schema(
                    name=name, encoding="protobuf", data=file_descriptor_set(name)
                )
                self._schemas[name] = schema_id
            msg_encoding = "protobuf"
        elif encoding.startswith("application/json"):
            msg_encoding = "json"
        else:
            msg_encoding = encoding or "zenoh/bytes"
        ch = w.register_channel(
            topic=key,
            message_encoding=msg_encoding,
            schema_id=schema_id,
            metadata={"zenoh_encoding": encoding},
        )
        self._channels[(key, encoding)] = ch
        self._seq[ch] = 0
        self._topics[ch] = key
        return ch

    def write(self, key: str, encoding: str, payload: bytes, recv_ns: int) -> None:
        """Append one sample (``recv_ns`` = receive time, UNIX ns, the MCAP ``log_time``; the
        ``publish_time`` is the message's own stamp, see the module docstring)."""
        with self._lock:
            if self._closed:
                raise RecorderError(self.failure or "recording already finalised")
            try:
                if self._file_start_ns == 0:
                    self._file_start_ns = recv_ns
                elif (self.split_ns and recv_ns - self._file_start_ns >= self.split_ns) or (
                    self.split_bytes and self._file is not None
                    and self._file.size >= self.split_bytes
                ):
                    self._finish_file()
                    self._open_next()
                    self._file_start_ns = recv_ns
                ch = self._channels.get((key, encoding))
                if ch is None:
                    ch = self._channel(key, encoding)
                seq = self._seq[ch] + 1
                self._seq[ch] = seq
                stamp = stamp_ns_of(payload, encoding)
                self.message_count += 1
                self._unflushed += 1
                self._writer.add_message(
                    ch, recv_ns, payload, recv_ns if stamp is None else stamp, seq & 0xFFFFFFFF
                )
                self._keep_reserve()
            except (OSError, RecorderError) as exc:
                self._stop_writing(exc)
                raise RecorderError(self.failure) from None

    def _keep_reserve(self) -> None:
        """Grow the reserve when the end of the file needs more than half of it (OSError when
        the disk cannot give it: the disk is full)."""
        need = 2 * self._writer.summary_size()
        if self._reserve is not None and need > self._reserve.size:
            self._reserve.ensure(max(2 * self._reserve.size, need))

    def _stop_writing(self, exc: BaseException) -> None:
        """A write failed (under the lock): drop the open chunk, cut the file back to its last
        complete record, release the reserve and end the file there; set :attr:`failure`."""
        self._closed = True
        path = self.paths[-1] if self.paths else self.base
        if self._file is None or self._writer is None or not self.paths:  # a split's next file failed
            self.failure = f"recording stopped: {exc}"
            return
        w, f = self._writer, self._file
        lost = w.abort_chunk()
        self.message_count -= lost
        good = w.rewind()  # the end of the last whole chunk (also when finish() itself failed)
        if self._reserve is not None:
            self._reserve.release()
            self._reserve = None
        end = "finalised (summary, indexes, footer) after its last complete chunk"
        try:
            f.truncate(good)
            self._finish_file()
        except OSError:
            good = w.rewind()
            with contextlib.suppress(OSError):
                f.truncate(good)
                f.close()
            self._file = None
            end = "not finalised, readable up to its last complete chunk"
        errno_ = getattr(exc, "errno", None)
        what = "disk full" if errno_ in (errno.ENOSPC, errno.EDQUOT) else "write failed"
        reason = getattr(exc, "strerror", None) or str(exc)
        self.failure = (
            f"{what} ({reason}): stopped recording to {path} after {self.message_count} messages "
            f"({good / 1e6:.2f} MB); the file is {end}; {lost} messages of the open chunk were "
            "not written"
        )

    def discard(self) -> None:
        """Close without finalising and delete every file this sink wrote (a recorder that
        failed to start leaves nothing behind that would block a retry). Idempotent."""
        with self._lock:
            self._closed = True
            if self._reserve is not None:
                self._reserve.release()
                self._reserve = None
            if self._file is not None:
                with contextlib.suppress(OSError):
                    self._file.close()
                self._file = None
            for path in self.paths:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()

    def flush(self) -> None:
        """Close the open chunk (if it holds messages) and hand it to the OS."""
        with self._lock:
            if self._closed:
                if self.failure:
                    raise RecorderError(self.failure)
                return
            if not self._unflushed:
                return
            try:
                self._writer.flush()
                self._keep_reserve()
            except OSError as exc:
                self._stop_writing(exc)
                raise RecorderError(self.failure) from None
            self._unflushed = 0

    @property
    def channel_counts(self) -> dict[str, int]:
        """Messages written per key, all files so far."""
        out = dict(self._closed_counts)
        if self._writer is not None and not self._closed:
            for ch, n in self._writer.channel_message_counts().items():
                key = self._topics[ch]
                out[key] = out.get(key, 0) + n
        return out

    def _finish_file(self) -> None:
        """End the current file (summary, indexes, footer), release its reserve, close it."""
        if self._reserve is not None:
            self._reserve.release()  # the space the summary may need
            self._reserve = None
        self._writer.finish()
        for ch, n in self._writer.channel_message_counts().items():
            key = self._topics[ch]
            self._closed_counts[key] = self._closed_counts.get(key, 0) + n
        assert self._file is not None
        self._file.close()
        self._file = None

    def close(self) -> None:
        """Finalise the current file (summary, indexes, footer) and close it. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._finish_file()
            except OSError as exc:
                self._stop_writing(exc)
                raise RecorderError(self.failure) from None


def default_output_path() -> Path:
    """``out/recording-<UTC time>.mcap``."""
    return Path("out") / time.strftime("recording-%Y%m%dT%H%M%SZ.mcap", time.gmtime())


def _subscriptions(
    keys: Any, key_exprs: list[str], history: bool, on_sample: Callable[[Any], None]
) -> list[tuple[str, Callable[[Any], None], int]]:
    """The subscriptions that record ``key_exprs``: ``(key_expr, handler, history)``.

    Live traffic: one plain subscriber per key expression, so everything is written in arrival
    order by one writer thread. Late-joiner history: with ``history``, each latched selector
    (goals, obstacles, scene) that intersects a recorded key expression gets an advanced
    subscriber whose handler writes only samples published *before* the recorder started
    (Zenoh HLC timestamp), skipping any the live path already wrote. One advanced subscriber
    per latched selector, never one on ``<prefix>/**``: zenoh's advanced subscriber drops
    samples that arrive out of timestamp order from one session, which happens whenever
    express/real-time samples overtake others.
    """
    import hashlib
    from collections import OrderedDict

    import zenoh

    kes = [zenoh.KeyExpr(k) for k in key_exprs]
    latched = [
        zenoh.KeyExpr(t.key) for t in keys.latched_selectors()
        if history and any(k.intersects(t.key) for k in kes)
    ]
    subs: list[tuple[str, Callable[[Any], None], int]] = [(str(k), on_sample, 0) for k in kes]
    if not latched:
        return subs
    start_ns = time.time_ns()
    # Digests of the latched samples each path wrote (the last 10,000): the history path skips
    # what the live path wrote; the live path skips, once, a sample the history path wrote. A
    # sample published twice with the same bytes is recorded twice.
    by_live: OrderedDict[bytes, None] = OrderedDict()
    by_history: OrderedDict[bytes, None] = OrderedDict()
    lock = threading.Lock()
    cache: dict[str, bool] = {}

    def digest(raw: Any) -> bytes:
        return hashlib.blake2b(raw.key.encode() + b"\0" + raw.payload, digest_size=16).digest()

    def remember(seen: OrderedDict[bytes, None], d: bytes) -> None:
        seen[d] = None
        if len(seen) > 10_000:
            seen.popitem(last=False)

    def is_latched(key: str) -> bool:
        hit = cache.get(key)
        if hit is None:
            hit = cache[key] = any(e.intersects(key) for e in latched)
        return hit

    def live(raw: Any) -> None:
        if is_latched(raw.key):
            d = digest(raw)
            with lock:
                if d in by_history:
                    del by_history[d]
                    return
                remember(by_live, d)
        on_sample(raw)

    def hist(raw: Any) -> None:
        if not (raw.ts_ns and raw.ts_ns < start_ns and any(k.intersects(raw.key) for k in kes)):
            return
        d = digest(raw)
        with lock:
            if d in by_live or d in by_history:
                return
            remember(by_history, d)
        on_sample(raw)

    subs = [(str(k), live, 0) for k in kes]
    subs += [(str(lk), hist, 1) for lk in latched]
    return subs


def run_recorder(cfg: RecorderConfig, *, ready: threading.Event | None = None) -> int:
    """Run the recorder until SIGINT/SIGTERM; returns the exit code (0 ok, 1 on write errors).

    Start-up, in this order so that a failure leaves no file behind: the key expressions are
    validated (:class:`~services.bus.messages.InvalidKeyError`) and the output checked
    (:class:`RecorderError`: unwritable, exists, too little space) before joining the bus; then
    the session opens (:class:`~services.bus.errors.BusError` if it cannot); then the file is
    created and the subscriptions declared. A failure after the file was created deletes it,
    so a retry needs no ``--overwrite``.
    """
    rc = cfg.recorder
    key_exprs = [validate_key_expr(k) for k in rc.key_exprs] or [Keys(cfg.prefix).all.key]
    out = Path(rc.output) if rc.output else default_output_path()
    first = out if not (rc.split_size_mb or rc.split_duration_s) else out.with_name(
        f"{out.stem}-0000{out.suffix}")
    _check_writable(first, rc.min_free_mb, rc.overwrite)
    app = _Recorder(cfg, out, key_exprs, ready)
    run_service(app)
    # after the close: the subscriptions are drained and the file is finalised
    return 1 if app.failed.is_set() or app.dropped else 0


class _Recorder(ServiceApp):
    """Writes every sample of the key expressions to MCAP (see the module docstring)."""

    name = "recorder"

    def __init__(
        self, cfg: RecorderConfig, out: Path, key_exprs: list[str], ready: threading.Event | None
    ) -> None:
        super().__init__(cfg)
        self.cfg, self.out, self.key_exprs, self.ready = cfg, out, key_exprs, ready
        self.sink: McapSink | None = None
        self.failed = threading.Event()
        self._svc: Service | None = None

    def setup(self, svc: Service) -> None:
        self._svc = svc
        rc = self.cfg.recorder
        try:
            self.sink = McapSink(
                self.out,
                chunk_size=rc.chunk_size,
                compression=rc.compression,
                split_size_mb=rc.split_size_mb,
                split_duration_s=rc.split_duration_s,
                min_free_mb=rc.min_free_mb,
                overwrite=rc.overwrite,
                metadata={
                    "project_version": svc.version,
                    "config": json.dumps(config_to_dict(self.cfg), sort_keys=True),
                    "key_exprs": json.dumps(self.key_exprs),
                },
                library=f"psm-dataflow {svc.version} recorder",
            )
            self.failed = _start_recording(svc, self.sink, self.key_exprs, rc)
        except BaseException:
            if self.sink is not None:
                self.sink.discard()
            raise

    def loop(self, svc: Service) -> None:
        if self.ready is not None:
            self.ready.set()
        svc.wait()

    @property
    def dropped(self) -> int:
        """Samples dropped by the subscriptions (0 unless a queue overflowed)."""
        return self._svc.counters.dropped if self._svc is not None else 0


def _start_recording(
    svc: Any, sink: McapSink, key_exprs: list[str], rc: RecorderSection
) -> threading.Event:
    """Declare the recording subscriptions, the flusher and the finalising hook; returns the
    event set when a write fails."""
    failed = threading.Event()
    stop_lock = threading.Lock()
    not_written = [0]  # samples received after the recording stopped

    def stopped(exc: BaseException) -> None:
        # The first failure says it once (error line, DEGRADED with the reason); the service
        # stays up, and the rest of the stack does not notice.
        with stop_lock:
            if failed.is_set():
                return
            failed.set()
            text = sink.failure or f"recording stopped: {exc}"
            svc.set_degraded(text)
            svc.record_error(text)

    def on_sample(raw: Any) -> None:
        if failed.is_set():
            not_written[0] += 1
            return
        try:
            sink.write(raw.key, raw.encoding, raw.payload, raw.recv_ns)
        except (OSError, RecorderError) as exc:
            stopped(exc)

    def flusher() -> None:
        while not svc.stop_event.wait(rc.flush_interval_s):
            if failed.is_set():
                return
            try:
                sink.flush()
            except (OSError, RecorderError) as exc:
                stopped(exc)

    def finalise() -> None:
        if failed.is_set():
            svc.log.info("recording had stopped", extra={"files": [str(p) for p in sink.paths],
                                                          "messages": sink.message_count,
                                                          "not_written": not_written[0]})
            return
        try:
            sink.close()
        except RecorderError as exc:
            stopped(exc)
            return
        svc.log.info(
            "recording finalised",
            extra={"files": [str(p) for p in sink.paths], "messages": sink.message_count,
                   "channels": len(sink.channel_counts)},
        )

    for kx, handler, history in _subscriptions(svc.keys, key_exprs, rc.history, on_sample):
        svc.subscribe_raw(kx, handler, queue_size=rc.queue_size, history=history,
                          delivery="channel", timestamps=history > 0)
    svc.on_close(finalise)
    threading.Thread(target=flusher, name="flusher", daemon=True).start()
    svc.log.info("recording", extra={"output": str(sink.paths[0]), "key_exprs": key_exprs})
    return failed
