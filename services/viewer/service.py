"""The ``psm view`` service: a running cell, live in Foxglove.

A Foxglove WebSocket server (``foxglove-sdk``; sub-protocol ``foxglove.sdk.v1``) that forwards
the cell's samples as they are:

* one subscriber on each forwarded key expression (default ``<prefix>/**``) into a zenoh ring
  channel of ``queue_size`` samples: Zenoh's receive threads run no Python and never wait (when
  the viewer is behind, the ring drops its oldest samples). The forwarding thread sleeps
  ``poll_period_s`` (10 ms), takes what the ring holds and drops, with a dictionary lookup per
  sample, what no client is subscribed to and what the stream's rate limit
  (``[viewer] max_rate_hz``, by message type) does not allow: a throttled stream forwards the
  newest sample of the batch. So an idle viewer costs a few microseconds per sample and a
  hundred short wake-ups a second; what is forwarded is handed to the server (each client has
  its own bounded backlog, ``client_backlog``; a slow client loses its oldest data messages).
  Nothing the viewer does can slow a publisher;
* one Foxglove channel per key, created on the key's first sample: topic = the key (as in the
  recordings), encoding ``protobuf``, schema = the ``FileDescriptorSet`` of the type named by the
  sample's encoding (:func:`~services.bus.messages.file_descriptor_set`). The payload bytes are
  forwarded unchanged (no decode, no re-encode); the log time is the message's own stamp
  (:func:`~services.bus.messages.stamp_ns_of`, receive time when it has none) or, with
  ``log_time = "receive"``, the receive time. A key whose encoding names no bus type is not
  forwarded (counted once as rejected); a sample whose type differs from its channel's is
  rejected;
* latched streams (goals, obstacles, scene, the planner's goal): their publishers' caches are
  queried at start (advanced subscribers on the latched selectors, as the recorder), the last
  sample of each latched key is kept, and a client that subscribes to it gets it at once.
  Duplicates from the two paths are told apart by the samples' Zenoh timestamps.

Subscriptions come from the server's listener (``on_subscribe`` / ``on_unsubscribe``), per
channel. The status counts ``received`` (every sample taken from the rings), ``published``
(forwarded to the server) and ``dropped`` (latched samples of a full queue); the per-stream
counts (forwarded, throttled) are logged at exit.
"""

from __future__ import annotations

import contextlib
import queue
import re
import threading
import time
from typing import Any

from services.bus.errors import BusError
from services.bus.messages import (
    ENCODING_PREFIX,
    MESSAGE_TYPES,
    file_descriptor_set,
    stamp_ns_of,
)
from services.bus.runtime import RawSample, Service, ServiceApp, run_service
from services.viewer.config import ViewerConfig

__all__ = ["SERVICE_NAME", "ViewerService", "main", "start_foxglove_server"]

SERVICE_NAME = "viewer"

# What the forwarding thread's queue holds: a latched sample (history path), a re-send.
_LATCHED, _RESEND = range(2)

_OS_ERROR = re.compile(r"([A-Za-z][A-Za-z ]+?) \(os error \d+\)")


class _Stream:
    """One key: its Foxglove channel and the state of its throttle (see the module docstring)."""

    __slots__ = ("channel", "encoding", "forwarded", "key", "last", "last_ts", "latched",
                 "next_ns", "period_ns", "rejected", "subscribers", "throttled")

    def __init__(self, key: str, encoding: str, latched: bool, period_ns: int) -> None:
        self.key = key
        self.encoding = encoding  #: the channel's Zenoh encoding
        self.latched = latched
        self.period_ns = period_ns  #: 0: unthrottled
        self.next_ns = 0  #: monotonic time from which the next sample may be forwarded
        self.subscribers = 0  #: clients subscribed to the channel
        self.channel: Any = None  #: the Foxglove channel (None: not created yet, or not forwarded)
        self.rejected = False  #: the key's encoding names no bus type: never forwarded
        self.last: tuple[bytes, str, int] | None = None  #: latched: payload, encoding, recv ns
        self.last_ts = 0  #: latched: Zenoh timestamp of ``last`` [ns]
        self.forwarded = 0
        self.throttled = 0

    def admit(self, now_ns: int) -> bool:
        """Whether the throttle lets a sample arriving at ``now_ns`` (monotonic) through. The
        allowed times advance by whole periods, so no window of length T holds more than
        ``T / period + 1`` forwarded samples; after a pause the schedule restarts."""
        if self.period_ns == 0:
            return True
        if now_ns < self.next_ns:
            self.throttled += 1
            return False
        nxt = self.next_ns + self.period_ns
        self.next_ns = nxt if now_ns < nxt else now_ns + self.period_ns
        return True


def start_foxglove_server(host: str, port: int, name: str, listener: Any, backlog: int) -> tuple[Any, Any]:
    """Start a Foxglove WebSocket server on ``host:port`` with its own context; returns
    ``(server, context)``. A port in use or an address that cannot be bound is a
    :class:`~services.bus.errors.BusError` (one line)."""
    import foxglove

    context = foxglove.Context()
    try:
        server = foxglove.start_server(
            name=name, host=host, port=port, server_listener=listener, context=context,
            message_backlog_size=backlog,
        )
    except (RuntimeError, OSError, ValueError) as exc:
        text = " ".join(str(exc).split()).removeprefix("FoxgloveError: ")
        m = _OS_ERROR.search(text)
        why = m.group(1).lower() if m else text
        raise BusError(f"cannot serve the Foxglove WebSocket on {host}:{port}: {why}") from None
    return server, context


class _Listener:
    """The server's listener: counts each channel's subscribed clients (SDK threads)."""

    def __init__(self, viewer: ViewerService) -> None:
        self.viewer = viewer

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.viewer.subscribed(channel.id, +1)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self.viewer.subscribed(channel.id, -1)


class ViewerService(ServiceApp):
    """The viewer process (see the module docstring)."""

    name = SERVICE_NAME
    svc: Service

    def __init__(self, config: ViewerConfig) -> None:
        super().__init__(config)
        self.config: ViewerConfig = config
        self.section = config.viewer
        self._streams: dict[str, _Stream] = {}
        self._by_channel: dict[int, _Stream] = {}
        #: Subscriptions to channels not registered yet: a client can subscribe as soon as a
        #: channel is advertised, before ``foxglove.Channel`` has returned to the viewer.
        self._early: dict[int, int] = {}
        self._lock = threading.Lock()  # subscription counts (SDK threads) vs channel creation
        # Latched samples from the history subscriptions and re-sends, for the forwarding thread.
        self._q: queue.SimpleQueue[tuple[int, Any]] = queue.SimpleQueue()
        self._rings: list[Any] = []
        self._latched_kes: list[Any] = []
        self._kes: list[Any] = []
        self._worker: threading.Thread | None = None
        # Before the session: a busy port fails before the process joins the bus.
        sec = self.section
        self.server, self.context = start_foxglove_server(
            sec.host, sec.port, f"psm {config.prefix}", _Listener(self), sec.client_backlog)
        self.port = int(self.server.port)

    # ------------------------------------------------------------------ setup
    def setup(self, svc: Service) -> None:
        """Subscriptions (live into zenoh ring channels, the latched streams' history) and the
        forwarding thread."""
        import zenoh

        self.svc = svc
        keys = svc.keys
        key_exprs = list(self.section.key_exprs) or [keys.all.key]
        self._kes = [zenoh.KeyExpr(k) for k in key_exprs]
        self._latched_kes = [zenoh.KeyExpr(t.key) for t in keys.latched_selectors()]
        for ke in self._kes:
            # A ring channel: Zenoh's thread runs no Python at all; when the forwarding thread
            # is behind by more than queue_size samples the oldest are dropped.
            sub = svc.session.declare_subscriber(ke, zenoh.handlers.RingChannel(self.config.queue_size))
            self._rings.append(sub.handler)
            svc.on_close(sub.undeclare)
        if self.section.history:
            for lk in self._latched_kes:
                if any(k.intersects(lk) for k in self._kes):
                    svc.subscribe_raw(str(lk), self._on_history, history=1, timestamps=True)
        self._worker = threading.Thread(target=self._run, name="forward", daemon=True)
        self._worker.start()
        svc.on_close(self._stop)  # runs before the undeclarations (hooks run in reverse)
        svc.log.info(
            "Foxglove WebSocket server listening (sub-protocol foxglove.sdk.v1)",
            extra={"url": f"ws://{self.section.host}:{self.port}", "key_exprs": key_exprs},
        )

    # ------------------------------------------------------------------ other threads
    def _on_history(self, raw: RawSample) -> None:
        """A latched sample from an advanced subscriber (history, and live ones again)."""
        if any(k.intersects(raw.key) for k in self._kes):
            self._put(_LATCHED, raw)

    def _put(self, kind: int, item: Any, force: bool = False) -> None:
        """Queue for the forwarding thread; a full queue drops the sample (counted). ``force``:
        a re-send, never dropped (at most one per subscription)."""
        if not force and self._q.qsize() >= self.config.queue_size:
            self.svc.counters.add("dropped")
            return
        self._q.put((kind, item))

    def subscribed(self, channel_id: int, delta: int) -> None:
        """A client subscribed (+1) to a channel or unsubscribed (-1) (the server's threads); a
        latched channel's last sample goes to the new subscriber."""
        with self._lock:
            st = self._by_channel.get(channel_id)
            if st is None:
                self._early[channel_id] = self._early.get(channel_id, 0) + delta
                return
            st.subscribers = max(0, st.subscribers + delta)
        if delta > 0 and st.latched:
            self._put(_RESEND, st, force=True)

    # ------------------------------------------------------------------ forwarding thread
    def _run(self) -> None:
        """Every ``poll_period_s`` (sleeping in between): take what the rings hold and forward
        what a client is subscribed to and the throttles allow; then the latched samples and
        re-sends."""
        period = self.section.poll_period_s
        stop = self.svc.stop_event
        while not stop.wait(period):
            try:
                self._drain()
            except Exception as exc:
                self.svc.record_error(f"forwarding failed: {exc!r}", exc)

    def _drain(self) -> None:
        now = time.monotonic_ns()
        wall = time.time_ns()
        batch: list[Any] = []
        for ring in self._rings:
            for _ in range(self.config.queue_size):  # at most what the ring holds
                sample = ring.try_recv()
                if sample is None:
                    break
                batch.append(sample)
        if batch:
            self.svc.counters.add("received", len(batch))
        # Newest first: a throttled stream forwards the newest sample of the batch; then the
        # forwarded ones in arrival order. A stream found unsubscribed stays so for the older
        # samples of the batch: a client subscribing meanwhile (an SDK thread) gets the stream
        # from its next sample on, without a gap, never an older sample and then a gap.
        out: list[tuple[_Stream, Any]] = []
        streams = self._streams
        closed: set[str] = set()
        for sample in reversed(batch):
            key = str(sample.key_expr)
            if key in closed:
                continue
            st = streams.get(key)
            if st is None:
                st = self._new_stream(key, str(sample.encoding))
            if st.latched:
                out.append((st, sample))
            elif st.subscribers <= 0 or st.channel is None:
                closed.add(key)
            elif st.admit(now):
                out.append((st, sample))
        for st, sample in reversed(out):
            encoding = str(sample.encoding)
            payload = sample.payload.to_bytes()
            if st.latched:
                ts = sample.timestamp
                self._latched(st, payload, encoding, wall,
                              0 if ts is None else ts.get_time_as_ntp64().as_nanos(), now)
            else:
                self._forward(st, payload, encoding, wall)
        for _ in range(self._q.qsize()):
            kind, item = self._q.get_nowait()
            if kind == _RESEND:
                if item.channel is not None and item.last is not None:
                    self._log(item, *item.last)
                continue
            st = streams.get(item.key) or self._new_stream(item.key, item.encoding)
            self._latched(st, item.payload, item.encoding, item.recv_ns, item.ts_ns, now)

    def _new_stream(self, key: str, encoding: str) -> _Stream:
        """The stream of a key's first sample, with its channel (none for an encoding that names
        no bus type: counted once as rejected)."""
        import foxglove

        name = encoding.removeprefix(ENCODING_PREFIX)
        st = _Stream(key, encoding, any(lk.intersects(key) for lk in self._latched_kes),
                     self.section.period_ns(name))
        self._streams[key] = st
        if not encoding.startswith(ENCODING_PREFIX) or name not in MESSAGE_TYPES:
            st.rejected = True
            self.svc.record_rejection(
                key, f"encoding {encoding!r} names no bus message type: not forwarded", "encoding")
            return st
        schema = foxglove.Schema(name=name, encoding="protobuf", data=file_descriptor_set(name))
        channel = foxglove.Channel(key, schema=schema, message_encoding="protobuf",
                                   context=self.context, metadata={"zenoh_encoding": encoding})
        with self._lock:
            st.channel = channel
            self._by_channel[channel.id()] = st
            st.subscribers = max(0, self._early.pop(channel.id(), 0))
        return st

    def _latched(self, st: _Stream, payload: bytes, encoding: str, recv_ns: int, ts_ns: int,
                 now: int) -> None:
        """Keep a latched stream's newest sample; forward it when subscribed."""
        if st.channel is None or (ts_ns and ts_ns <= st.last_ts):
            return  # not forwarded, or the same sample from the other path, or an older one
        if encoding != st.encoding:
            self._wrong_type(st, encoding)
            return
        st.last, st.last_ts = (payload, encoding, recv_ns), ts_ns
        if st.subscribers > 0 and st.admit(now):
            self._log(st, payload, encoding, recv_ns)

    def _forward(self, st: _Stream, payload: bytes, encoding: str, recv_ns: int) -> None:
        if encoding != st.encoding:
            self._wrong_type(st, encoding)
            return
        self._log(st, payload, encoding, recv_ns)

    def _wrong_type(self, st: _Stream, encoding: str) -> None:
        self.svc.record_rejection(st.key, f"{encoding!r} on a {st.encoding!r} channel", "type")

    def _log(self, st: _Stream, payload: bytes, encoding: str, recv_ns: int) -> None:
        log_time = recv_ns
        if self.section.log_time == "stamp":
            stamp = stamp_ns_of(payload, encoding)
            if stamp is not None:
                log_time = stamp
        st.channel.log(payload, log_time=log_time)
        st.forwarded += 1
        self.svc.counters.add("published")

    # ------------------------------------------------------------------ shutdown
    def _stop(self) -> None:
        """End the forwarding thread, stop the server, log the per-stream counts."""
        if self._worker is not None:
            self.svc.stop_event.set()
            self._worker.join(5.0)
        self.teardown_server()
        streams = sorted(self._streams.values(), key=lambda s: s.key)
        self.svc.log.info("viewer streams", extra={
            "streams": len(streams),
            "forwarded": {s.key: s.forwarded for s in streams if s.forwarded},
            "throttled": {s.key: s.throttled for s in streams if s.throttled},
        })

    def teardown_server(self) -> None:
        """Stop the WebSocket server (idempotent)."""
        server, self.server = self.server, None
        if server is not None:
            with contextlib.suppress(Exception):
                server.stop()

    def teardown(self, svc: Service) -> None:
        """A failed set-up still stops the server."""
        if self._worker is None:
            self.teardown_server()


def main(config: ViewerConfig) -> int:
    """Run the viewer with a loaded config; returns the exit code."""
    app = ViewerService(config)
    try:
        return run_service(app)
    finally:
        app.teardown_server()
