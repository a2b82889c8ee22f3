"""Service runtime: the one skeleton every bus process runs on.

A service process is a :class:`ServiceApp`: a typed config, a ``setup`` (subscriptions,
publishers, liveliness watches) and optionally a ``loop``. :func:`run_service` does the rest,
the same way for every process: it opens the session (:func:`open_session`; an unreachable
router or a busy port is a :class:`~services.bus.errors.BusError`), runs ``setup``, declares
the liveliness token and starts the status, installs the SIGINT/SIGTERM handlers, runs the
``loop`` until stopped, runs ``teardown`` and closes the bus (bounded: a hung Zenoh teardown
ends the process). Errors reach ``services.cli.dispatch``, which prints them as one line.
The :class:`Service` it hands to the app gives every process the same behaviour:

* structured logging (``text`` or ``json`` lines on stderr) tagged with the service name;
* a liveliness token at ``Keys.liveliness(name)`` while it runs;
* a periodic :class:`~services.bus.messages.ServiceStatus` on ``Keys.status(name)`` with the
  counters ``received``, ``rejected``, ``published``, ``errors``, ``dropped``;
* typed publishers/subscribers whose Zenoh QoS comes from the :class:`~services.bus.messages.Topic`
  (control loop: express + real-time priority; camera: droppable; goals/obstacles: cached by an
  advanced publisher and fetched by advanced subscribers as history for late joiners);
* subscription callbacks run on a worker thread fed by a bounded queue: the Zenoh receive thread
  only enqueues (a full queue drops the sample and counts it in ``dropped``);
* malformed payloads / wrong encodings are counted as ``rejected`` (and by reason in
  ``rejected_by_reason``), logged (rate-limited) and skipped — the service keeps running;
  exceptions in callbacks are counted as ``errors``;
* graceful shutdown on SIGINT/SIGTERM: stop subscriptions, drain the queues, run the
  ``on_close`` hooks (flush outputs), publish a final status and close the session.

Example::

    from services.bus.config import ServiceConfig, load_config
    from services.bus.messages import ArmCommand, ArmState
    from services.bus.runtime import Service, ServiceApp, run_service

    class Planner(ServiceApp):
        name = "planner"

        def setup(self, svc: Service) -> None:
            cmd_pub = svc.publisher(svc.keys.arm_command)

            def on_state(state: ArmState, key: str) -> None:
                cmd_pub.put(ArmCommand(stamp_ns=state.stamp_ns, tick=state.tick,
                                       mode=ArmCommand.CARTESIAN_ACCELERATION))

            svc.subscribe(svc.keys.arm_state, on_state)

    run_service(Planner(load_config(ServiceConfig, "configs/stack.toml")))
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from google.protobuf.message import Message

from services.bus.config import ServiceConfig, ZenohConfig
from services.bus.messages import (
    ServiceStatus,
    StreamClass,
    Topic,
    decode,
    encoding_for,
)

__all__ = [
    "Counters",
    "RawSample",
    "Service",
    "ServiceApp",
    "Subscription",
    "TypedPublisher",
    "init_zenoh_log",
    "open_session",
    "project_version",
    "publisher_matching",
    "run_service",
    "setup_logging",
    "zenoh_config",
]

_LOG_RESERVED = set(logging.LogRecord("", 0, "", 0, "", (), None).__dict__) | {"message"}


# --------------------------------------------------------------------------------------------
# Logging
# --------------------------------------------------------------------------------------------


class _Formatter(logging.Formatter):
    """``text``: ``<UTC time> <LEVEL> <service> <message> k=v ...``; ``json``: one object."""

    def __init__(self, service: str, fmt: str) -> None:
        super().__init__()
        self.service = service
        self.json = fmt == "json"

    def format(self, record: logging.LogRecord) -> str:
        service = record.name[4:] if record.name.startswith("psm.") else self.service
        fields = {k: v for k, v in record.__dict__.items() if k not in _LOG_RESERVED}
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        ts += f".{int(record.msecs):03d}Z"
        if self.json:
            out = {
                "ts": ts,
                "level": record.levelname,
                "service": service,
                "logger": record.name,
                "msg": record.getMessage(),
                **fields,
            }
            if record.exc_info:
                out["exc"] = self.formatException(record.exc_info)
            return json.dumps(out, default=str)
        extra = "".join(f" {k}={v!r}" if isinstance(v, str) else f" {k}={v}" for k, v in
                        fields.items())
        line = f"{ts} {record.levelname} {service}: {record.getMessage()}{extra}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


def setup_logging(service: str, level: str = "INFO", fmt: str = "text") -> logging.Logger:
    """Configure the ``psm`` logger hierarchy to write structured lines to stderr; returns the
    logger ``psm.<service>``. Extra fields: ``log.info("msg", extra={"key": k, "n": 3})``."""
    root = logging.getLogger("psm")
    root.setLevel(level)
    for h in list(root.handlers):
        if getattr(h, "_psm_runtime", False):
            root.removeHandler(h)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter(service, fmt))
    handler._psm_runtime = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.propagate = False
    return logging.getLogger(f"psm.{service}")


class _RateLimiter:
    """Allow one event per ``period_s``; counts the suppressed ones in between."""

    def __init__(self, period_s: float = 1.0) -> None:
        self.period_s = period_s
        self._last = -1e18
        self.suppressed = 0
        self._lock = threading.Lock()

    def allow(self) -> int | None:
        """``None`` if suppressed, else the number suppressed since the last allowed event."""
        now = time.monotonic()
        with self._lock:
            if now - self._last >= self.period_s:
                n, self.suppressed, self._last = self.suppressed, 0, now
                return n
            self.suppressed += 1
            return None


def project_version() -> str:
    """The installed ``psm-dataflow`` version, else the one in ``pyproject.toml``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("psm-dataflow")
    except PackageNotFoundError:
        import tomllib
        from pathlib import Path

        pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
        try:
            with pyproject.open("rb") as fh:
                return str(tomllib.load(fh)["project"]["version"])
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "0+unknown"


# --------------------------------------------------------------------------------------------
# Session
# --------------------------------------------------------------------------------------------

_zenoh_log_initialised = False


def zenoh_config(cfg: ZenohConfig, extra: Mapping[str, Any] | None = None) -> Any:
    """A ``zenoh.Config`` from a validated :class:`ZenohConfig` (the optional JSON5 file is
    loaded first, the typed fields override it), then ``extra`` (zenoh config path -> JSON
    value, e.g. the router's ``{"access_control": {...}}``)."""
    import zenoh

    conf = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    if cfg.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(cfg.multicast)))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(bool(cfg.gossip)))
    # A client whose router goes away keeps its session and reconnects on its own, declaring
    # its subscribers, publishers' interests and liveliness tokens again (zenoh 1.x); the retry
    # period starts at 0.1 s and doubles up to reconnect_max_s (zenoh's default: 1 s up to 4 s).
    # The first connection still fails at once (connect/timeout_ms 0 in client mode): an
    # unreachable router at start is one error line.
    max_ms = round(cfg.reconnect_max_s * 1000)
    conf.insert_json5("connect/retry", json.dumps(
        {"period_init_ms": min(100, max_ms), "period_max_ms": max_ms, "period_increase_factor": 2}))
    # Samples carry an HLC timestamp (advanced publishers' caches and late joiners rely on it).
    conf.insert_json5("timestamping/enabled", "true")
    if cfg.shared_memory:
        conf.insert_json5("transport/shared_memory/enabled", "true")
    if cfg.low_latency:
        enable_low_latency(conf)
    if cfg.user:
        # User/password authentication at the router (its dictionary: ``[router] users_file``);
        # the password is read from its file now, never kept in the config.
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(cfg.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(cfg.password()))
    for path, value in (extra or {}).items():
        conf.insert_json5(path, json.dumps(value))
    return conf


def enable_low_latency(conf: Any) -> None:
    """Switch a ``zenoh.Config`` to the low-latency unicast transport (``zenoh.low_latency``).
    Zenoh refuses it together with QoS (the transport has a single queue), so QoS goes off."""
    conf.insert_json5("transport/unicast/lowlatency", "true")
    conf.insert_json5("transport/unicast/qos/enabled", "false")


def init_zenoh_log(directives: Sequence[str] = ()) -> None:
    """Start zenoh's (Rust) log output, once per process: the filter is ``RUST_LOG`` (default
    ``error``) followed by ``directives`` (``target=level`` items of a tracing ``EnvFilter``;
    a more specific target wins, so they apply whatever ``RUST_LOG`` says). zenoh writes these
    lines to stdout. Later calls do nothing."""
    import os

    import zenoh

    global _zenoh_log_initialised
    if _zenoh_log_initialised:
        return
    _zenoh_log_initialised = True
    old = os.environ.get("RUST_LOG")
    base = (old or "").strip() or "error"
    # zenoh reads the filter from RUST_LOG when it is set (the fallback only applies when it is
    # not), so the directives go in there for the call, and the variable is put back after it.
    os.environ["RUST_LOG"] = ",".join([base, *directives])
    try:
        zenoh.init_log_from_env_or(base)
    finally:
        if old is None:
            del os.environ["RUST_LOG"]
        else:
            os.environ["RUST_LOG"] = old


def publisher_matching(pub: Any) -> bool | None:
    """Whether a zenoh publisher has a matching subscriber (``None``: unknown, e.g. an
    advanced publisher, which does not report it). zenoh's ``MatchingStatus`` object is always
    truthy: its ``matching`` attribute is the answer."""
    status = getattr(pub, "matching_status", None)
    return None if status is None else bool(status.matching)


def open_session(cfg: ZenohConfig, extra: Mapping[str, Any] | None = None) -> Any:
    """Open a ``zenoh.Session`` from config (``extra``: see :func:`zenoh_config`). Zenoh's own
    (Rust) log level follows ``RUST_LOG``, default ``error`` (:func:`init_zenoh_log`).

    Raises :class:`~services.bus.errors.BusError` (one line naming the endpoint) when Zenoh
    refuses: an unreachable router in client mode, a listen endpoint already in use, a
    malformed endpoint or config file."""
    import zenoh

    from services.bus.errors import session_error

    init_zenoh_log()
    try:
        session = zenoh.open(zenoh_config(cfg, extra))
    except zenoh.ZError as exc:
        raise session_error(
            exc, cfg.mode, cfg.connect, cfg.listen, user=cfg.user, zid=str((extra or {}).get("id", ""))
        ) from None
    if cfg.mode == "peer" and cfg.connect:
        wait_for_peer_links(session)
    return session


#: :func:`wait_for_peer_links`: the set of linked peers must stay the same this long [s] ...
PEER_LINKS_SETTLE_S = 0.25
#: ... within this long after the session opened [s] (then the session is used as it is).
PEER_LINKS_TIMEOUT_S = 3.0


def wait_for_peer_links(
    session: Any, settle_s: float = PEER_LINKS_SETTLE_S, timeout_s: float = PEER_LINKS_TIMEOUT_S
) -> bool:
    """Wait until a peer that connects to a router has linked to the other peers.

    The router tells a new peer about the others (gossip scouting) and the peer opens a direct
    link to each, within milliseconds on loopback; the router does not forward one peer's
    samples to another, so what the new peer publishes before a link exists never reaches that
    peer (a restarted planner's first commands would miss the recorder). Returns True once a
    router is connected and the set of linked peers (``session.info.peers_zid()``) has not
    changed for ``settle_s``; False after ``timeout_s`` (the session is used as it is)."""
    info = session.info
    deadline = time.monotonic() + timeout_s
    linked: frozenset[str] | None = None
    since = time.monotonic()
    while True:
        now = time.monotonic()
        peers = frozenset(str(z) for z in info.peers_zid())
        if peers != linked:
            linked, since = peers, now
        elif now - since >= settle_s and any(True for _ in info.routers_zid()):
            return True
        if now >= deadline:
            return False
        time.sleep(0.01)


def _qos_kwargs(topic: Topic) -> dict[str, Any]:
    import zenoh

    q = topic.qos
    return {
        "priority": getattr(zenoh.Priority, q.priority),
        "express": q.express,
        "congestion_control": getattr(zenoh.CongestionControl, q.congestion),
    }


#: Per OS thread: whether that zenoh receive thread keeps its Python thread state.
_KEPT_THREAD_STATE = threading.local()


def _keep_thread_state() -> None:
    """Keep the calling thread's Python thread state for the life of the thread (called with
    the GIL held, on a thread Python did not create): one more ``PyGILState_Ensure`` that is
    never released, so the ``PyGILState_Release`` at the end of each callback no longer
    brings the count to zero and destroys the state."""
    import ctypes

    ctypes.pythonapi.PyGILState_Ensure()
    _KEPT_THREAD_STATE.kept = True


def receive_thread_handler(callback: Callable[[Any], None]) -> Any:
    """A zenoh subscriber handler that runs ``callback(sample)`` on zenoh's receive thread
    (``zenoh.handlers.Callback(..., indirect=False)``), for the control loop's streams: no hand-off
    to a Python callback thread.

    Zenoh's receive threads are not Python threads. For every sample zenoh-python takes the GIL
    with ``PyGILState_Ensure`` and returns it with ``PyGILState_Release``; on a thread without a
    Python thread state of its own that creates a thread state and destroys it again, sample
    after sample (measured here: ~19 µs of CPU a sample, 9.0 % → 5.5 % of a core for 1,830
    samples/s with a callback that only counts; ``docs/bus.md``, *Callbacks on the receive
    thread*). On its first sample a receive thread keeps its thread state for good
    (:func:`_keep_thread_state`): one thread state and its 16 KiB frame stack per receive
    thread, which zenoh keeps for the session's life.
    """
    import zenoh

    state = _KEPT_THREAD_STATE

    def on_sample(sample: Any) -> None:
        if not getattr(state, "kept", False):
            _keep_thread_state()
        callback(sample)

    return zenoh.handlers.Callback(on_sample, indirect=False)


# --------------------------------------------------------------------------------------------
# Counters, publishers, subscriptions
# --------------------------------------------------------------------------------------------


class Counters:
    """Thread-safe service counters reported in :class:`ServiceStatus`."""

    __slots__ = ("_lock", "dropped", "errors", "published", "received", "rejected", "rejected_by")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.received = 0
        self.rejected = 0
        self.published = 0
        self.errors = 0
        self.dropped = 0
        #: ``rejected`` by reason (``encoding``, ``malformed``, ``tick``, ...).
        self.rejected_by: dict[str, int] = {}

    def add(self, name: str, n: int = 1) -> None:
        """Increment counter ``name`` by ``n``."""
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def reject(self, reason: str) -> None:
        """Count one rejected input under ``reason``."""
        with self._lock:
            self.rejected += 1
            self.rejected_by[reason] = self.rejected_by.get(reason, 0) + 1

    def rejections(self) -> dict[str, int]:
        """A copy of the rejected counts by reason."""
        with self._lock:
            return dict(self.rejected_by)

    def snapshot(self, received: int = 0) -> dict[str, int]:
        """A consistent copy of all counters (``received`` is added to the own count)."""
        with self._lock:
            return {
                "received": self.received + received,
                "rejected": self.rejected,
                "published": self.published,
                "errors": self.errors,
                "dropped": self.dropped,
            }


class TypedPublisher:
    """Publishes messages of one :class:`Topic` with its QoS and encoding."""

    def __init__(
        self, service: Service, topic: Topic, key: str | None = None, *, count: bool = True
    ) -> None:
        import zenoh

        if topic.msg_type is None:
            raise TypeError(f"topic {topic.key} has no message type; use a concrete topic")
        self.topic = topic
        self.key = key or topic.key
        self.encoding = encoding_for(topic.msg_type)
        self._counters = service.counters
        self._count = count
        self._closed = False
        kwargs = _qos_kwargs(topic)
        if topic.qos.history > 0:
            import zenoh.ext as zext

            self._pub = zext.declare_advanced_publisher(
                service.session,
                self.key,
                encoding=self.encoding,
                cache=zext.CacheConfig(max_samples=topic.qos.history),
                publisher_detection=True,
                **kwargs,
            )
        else:
            self._pub = service.session.declare_publisher(
                self.key, encoding=zenoh.Encoding(self.encoding), **kwargs
            )

    def put(self, msg: Message) -> None:
        """Serialise and publish ``msg`` (must be the topic's type)."""
        if type(msg) is not self.topic.msg_type:
            raise TypeError(
                f"{self.key} carries {self.topic.msg_type.DESCRIPTOR.full_name}, "  # type: ignore[union-attr]
                f"got {type(msg).__name__}"
            )
        self.put_bytes(msg.SerializeToString())

    @property
    def has_subscribers(self) -> bool | None:
        """Whether a matching subscriber exists (``None``: unknown for cached/latched
        publishers, which zenoh does not report). It can turn true a little before the route
        through a router is complete: lockstep starters should confirm with a round trip or
        wait a few hundred ms before the first sample that must not be lost."""
        return publisher_matching(self._pub)

    def put_bytes(self, payload: bytes) -> None:
        """Publish an already serialised message of the topic's type. Once the publisher is
        closed (the service shuts down) a sample from a callback still running is dropped."""
        try:
            self._pub.put(payload)
        except Exception:
            if self._closed:
                return
            raise
        if self._count:
            self._counters.add("published")

    def close(self) -> None:
        """Undeclare the publisher (later :meth:`put` calls are dropped)."""
        self._closed = True
        with contextlib.suppress(Exception):
            self._pub.undeclare()


class RawSample(NamedTuple):
    """A received sample, undecoded: key, payload bytes, encoding string, receive time (UNIX
    ns, wall clock) and, for subscriptions made with ``timestamps=True``, the sample's Zenoh
    HLC timestamp (publication time, UNIX ns; 0 if absent or not requested)."""

    key: str
    payload: bytes
    encoding: str
    recv_ns: int
    ts_ns: int = 0


class Subscription:
    """A subscriber whose callback runs on its own worker thread (by default never on Zenoh's).

    Three deliveries:

    * ``"queue"`` (default for data, camera, latched streams): the Zenoh callback only stamps
      the receive time and appends to a bounded queue; when the queue is full the sample is
      dropped and counted (``dropped``) — a slow consumer never stalls the session.
    * ``"channel"`` (control streams, the recorder): a bounded zenoh ``FifoChannel``; the
      receive thread runs no Python at all (no GIL), and a full channel applies back-pressure
      instead of dropping — lossless, like the blocking congestion control of those streams.
      The receive time is taken when the worker dequeues the sample (equal to the arrival time
      unless the worker is behind).
    * ``"inline"`` (opt-in only): the callback runs on Zenoh's receive thread — lowest latency,
      for handlers that return within microseconds (store the latest value, set an event);
      anything heavier stalls every stream of the session.
    * ``"latest"`` (opt-in only): a zenoh ``RingChannel`` of one sample and no worker thread.
      The receive thread keeps the newest sample (no Python, no GIL); the consumer calls
      :meth:`take` when it wants the current value, and the callback runs on its thread. For a
      consumer that samples a fast stream (a clock from the arm's 500 Hz state): the samples it
      never takes cost it nothing and are counted neither as received nor as dropped.
    """

    def __init__(
        self,
        service: Service,
        key_expr: str,
        handler: Callable[[RawSample], None],
        *,
        queue_size: int,
        history: int = 0,
        delivery: str = "queue",
        timestamps: bool = False,
        name: str = "",
    ) -> None:
        import zenoh

        if delivery not in ("queue", "channel", "inline", "latest"):
            raise ValueError(
                f"delivery must be 'queue', 'channel', 'inline' or 'latest', got {delivery!r}"
            )
        self.service = service
        self.key_expr = key_expr
        self.name = name or key_expr
        self.delivery = delivery
        self.timestamps = timestamps
        self._handler = handler
        self._q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._max = queue_size
        self.dropped = 0
        self.received = 0
        self._drop_log = _RateLimiter(1.0)
        self._closed = False
        self._put_kind = zenoh.SampleKind.PUT
        self._zerror = zenoh.ZError
        if delivery == "channel":
            target: Any = zenoh.handlers.FifoChannel(queue_size)
        elif delivery == "latest":
            target = zenoh.handlers.RingChannel(1)
        elif delivery == "inline":
            put_kind = zenoh.SampleKind.PUT

            def on_sample(sample: Any) -> None:
                self._process(sample, time.time_ns(), put_kind)

            # On zenoh's receive thread: zenoh-python's default (a bare callable, or
            # indirect=True) hands every sample to a Python callback thread of its own — one
            # thread wake-up more.
            target = receive_thread_handler(on_sample)
        else:
            target = self._on_sample
        if history > 0:
            import zenoh.ext as zext

            self._sub = zext.declare_advanced_subscriber(
                service.session,
                key_expr,
                target,
                history=zext.HistoryConfig(detect_late_publishers=True, max_samples=history),
            )
        else:
            self._sub = service.session.declare_subscriber(key_expr, target)
        self._worker: threading.Thread | None = None
        if delivery in ("channel", "latest"):
            self._channel = self._sub.handler
        if delivery == "latest":
            return  # the consumer's thread takes the samples
        run = self._run_channel if delivery == "channel" else self._run_queue  # "inline": idle
        self._worker = threading.Thread(target=run, name=f"sub:{self.name}", daemon=True)
        self._worker.start()

    # Zenoh receive thread ("queue" delivery): enqueue only.
    def _on_sample(self, sample: Any) -> None:
        recv_ns = time.time_ns()
        if self._q.qsize() >= self._max:
            self.dropped += 1
            self.service.counters.add("dropped")
            n = self._drop_log.allow()
            if n is not None:
                self.service.log.warning(
                    "queue full, dropping samples",
                    extra={"key_expr": self.key_expr, "queue_size": self._max,
                           "suppressed": n},
                )
            return
        self._q.put((sample, recv_ns))

    def _process(self, sample: Any, recv_ns: int, put_kind: Any) -> None:
        if sample.kind != put_kind:
            return
        ts_ns = 0
        if self.timestamps and sample.timestamp is not None:
            ts_ns = sample.timestamp.get_time_as_ntp64().as_nanos()
        raw = RawSample(
            str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding), recv_ns, ts_ns
        )
        self.received += 1
        try:
            self._handler(raw)
        except Exception as exc:
            self.service.record_error(f"handler for {raw.key} failed: {exc!r}", exc)

    def _run_queue(self) -> None:
        import zenoh

        put_kind = zenoh.SampleKind.PUT
        get = self._q.get
        while True:
            item = get()
            if item is None:
                return
            self._process(item[0], item[1], put_kind)

    def _run_channel(self) -> None:
        import zenoh

        put_kind = zenoh.SampleKind.PUT
        recv = self._channel.recv
        try_recv = self._channel.try_recv
        process = self._process
        now = time.time_ns
        while True:
            try:
                sample = try_recv()  # cheap while there is a backlog
                if sample is None:
                    sample = recv()  # blocks in Rust with the GIL released
            except zenoh.ZError:  # undeclared and drained
                return
            process(sample, now(), put_kind)

    def take(self) -> bool:
        """``"latest"`` delivery: run the callback on the newest sample that arrived since the
        last call, on the caller's thread. Returns whether there was one."""
        if self.delivery != "latest":
            raise RuntimeError(f"take() needs delivery 'latest', this subscription has {self.delivery!r}")
        if self._closed:
            return False
        try:
            sample = self._channel.try_recv()
        except self._zerror:  # undeclared
            return False
        if sample is None:
            return False
        self._process(sample, time.time_ns(), self._put_kind)
        return True

    def pending(self) -> int:
        """Samples waiting in the queue (0 for ``channel`` and ``latest`` delivery, which zenoh
        does not report)."""
        return self._q.qsize()

    def close(self, drain_timeout_s: float = 10.0) -> None:
        """Undeclare the subscriber, let the worker finish the queued samples (up to
        ``drain_timeout_s``) and stop it."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self._sub.undeclare()
        if self._worker is not None:
            self._q.put(None)
            self._worker.join(drain_timeout_s)


# --------------------------------------------------------------------------------------------
# Service
# --------------------------------------------------------------------------------------------


class Service:
    """A bus service: session, logging, liveliness, status, typed pub/sub, clean shutdown.

    Use as a context manager (``start()`` on enter, ``close()`` on exit) and call :meth:`run`
    to block until a signal or :meth:`stop`.
    """

    def __init__(
        self,
        name: str,
        config: ServiceConfig,
        *,
        session: Any | None = None,
        version: str | None = None,
        zenoh: ZenohConfig | None = None,
        zenoh_extra: Mapping[str, Any] | None = None,
    ) -> None:
        from services.bus.messages import Keys

        self.name = name
        self.config = config
        self.keys = Keys(config.prefix)
        self.keys.status(name)  # validates the name as a key chunk
        self.version = version or project_version()
        self.log = setup_logging(name, config.log_level, config.log_format)
        self.counters = Counters()
        self.stop_event = threading.Event()
        self._stop_signal: int | None = None  # set by the SIGINT/SIGTERM watcher
        self._signal_pipe: tuple[int, int] | None = None
        self.state = ServiceStatus.STARTING
        self.last_error = ""
        self._degraded: str | None = None
        self._error_log = _RateLimiter(1.0)
        self._reject_log = _RateLimiter(1.0)
        self._own_session = session is None
        self._mode = (zenoh or config.zenoh).mode
        self.session = (
            session if session is not None else open_session(zenoh or config.zenoh, zenoh_extra)
        )
        self._subs: list[Subscription] = []
        self._pubs: list[TypedPublisher] = []
        self._on_close: list[Callable[[], None]] = []
        self._others: list[Any] = []
        self._token: Any = None
        self._status_pub: TypedPublisher | None = None
        self._status_thread: threading.Thread | None = None
        self._status_seq = 0
        self._t0 = time.monotonic()
        self._closed = False
        self._last_counts: dict[str, int] = {}
        self.log.info(
            "session open",
            extra={"zid": str(self.session.zid()), "mode": (zenoh or config.zenoh).mode,
                   "prefix": config.prefix, "version": self.version},
        )

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> Service:
        """Declare the liveliness token and start the periodic status publisher."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(
                self.keys.liveliness(self.name).key
            )
            self._status_pub = TypedPublisher(self, self.keys.status(self.name), count=False)
            self.state = ServiceStatus.RUNNING
            self._status_thread = threading.Thread(
                target=self._status_loop, name="status", daemon=True
            )
            self._status_thread.start()
        return self

    def __enter__(self) -> Service:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def install_signal_handlers(self) -> None:
        """SIGINT/SIGTERM stop the service (main thread only; no-op elsewhere).

        The Python-level handler records nothing and takes no lock: it runs between two
        bytecodes of the main thread, which may be inside the very lock an ``Event.set`` takes
        (a second signal arriving while the first handler was in ``Event.set`` deadlocked a
        process). Instead the interpreter's C-level handler writes the signal number to a
        wake-up pipe (``signal.set_wakeup_fd``, async-signal-safe) and a watcher thread sets
        :attr:`stop_event` from ordinary thread context. A second SIGINT (a user insisting)
        interrupts the main thread; repeated SIGTERMs (a supervisor, the parent-death signal)
        change nothing, so the shutdown that is running (e.g. finalising a recording) completes.
        """
        if threading.current_thread() is not threading.main_thread() or self._signal_pipe:
            return
        import _thread
        import os

        r, w = os.pipe()
        os.set_blocking(w, False)
        self._signal_pipe = (r, w)

        def handler(signum: int, _frame: Any) -> None:
            """The signal was written to the wake-up pipe; the watcher acts on it."""

        def watch() -> None:
            sigints = 0
            while True:
                try:
                    data = os.read(r, 64)
                except OSError:
                    return
                if not data:
                    return
                for signum in data:
                    if signum not in (signal.SIGINT, signal.SIGTERM):
                        continue
                    if self._stop_signal is None:
                        self._stop_signal = signum
                        self.stop_event.set()
                    if signum == signal.SIGINT:
                        sigints += 1
                        if sigints >= 2:
                            _thread.interrupt_main()

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)
        signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        threading.Thread(target=watch, name="signals", daemon=True).start()

    def stop(self) -> None:
        """Ask :meth:`run` to return (thread-safe)."""
        self.stop_event.set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until the service is stopped (or ``timeout_s``); True if stopped. Waits in
        short slices so a signal handler's stop is seen at once."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.stop_event.is_set():
            remaining = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
            if remaining <= 0:
                return False
            self.stop_event.wait(remaining)
        return True

    def on_close(self, fn: Callable[[], None]) -> None:
        """Register ``fn`` to run at close, after subscriptions are drained (e.g. flush a file)."""
        self._on_close.append(fn)

    def close(self) -> None:
        """Stop subscriptions (draining their queues), run ``on_close`` hooks, publish a final
        status, drop the liveliness token and close the session. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._stop_signal is not None:
            self.log.info("signal received, shutting down", extra={"signal": self._stop_signal})
        self.state = ServiceStatus.STOPPING
        self.stop_event.set()
        for s in self._subs:
            s.close()
        for fn in reversed(self._on_close):
            try:
                fn()
            except Exception as exc:
                self.record_error(f"on_close hook failed: {exc!r}", exc)
        if self._status_thread is not None:
            self._status_thread.join(2.0)
        if self._status_pub is not None:
            with contextlib.suppress(Exception):
                self._publish_status()
        for o in self._others:
            with contextlib.suppress(Exception):
                o.undeclare()
        for p in self._pubs:
            p.close()
        if self._token is not None:
            with contextlib.suppress(Exception):
                self._token.undeclare()
        if self.config.health_file:
            with contextlib.suppress(OSError):
                Path(self.config.health_file).unlink()
        if self._own_session:
            with contextlib.suppress(Exception):
                self.session.close()
        self.log.info("closed", extra=self.counters.snapshot(sum(s.received for s in self._subs)))

    # -- errors --------------------------------------------------------------------------------
    def record_error(self, text: str, exc: BaseException | None = None) -> None:
        """Count an internal error, remember it for the status and log it (rate-limited)."""
        self.counters.add("errors")
        self.last_error = text
        n = self._error_log.allow()
        if n is not None:
            self.log.error(text, exc_info=exc, extra={"suppressed": n})

    def record_rejection(self, key: str, reason: str, kind: str = "invalid") -> None:
        """Count a rejected input sample under ``kind`` (a short reason: ``encoding``,
        ``schema``, ``type``, ``malformed``, ``non_finite``, ``tick``, ``stamp``, ...; the
        status's ``rejected_by_reason``) and log it with the one-line ``reason``
        (rate-limited)."""
        self.counters.reject(kind)
        self.last_error = f"rejected on {key}: {reason}"
        n = self._reject_log.allow()
        if n is not None:
            self.log.warning("rejected sample", extra={"key": key, "reason": reason, "kind": kind,
                                                       "suppressed": n})

    # -- pub/sub ---------------------------------------------------------------------------------
    def publisher(self, topic: Topic, key: str | None = None) -> TypedPublisher:
        """A publisher for ``topic`` with the topic's QoS (``key`` overrides the key, e.g. after
        a prefix remap)."""
        pub = TypedPublisher(self, topic, key)
        self._pubs.append(pub)
        return pub

    def subscribe(
        self,
        topic: Topic,
        callback: Callable[[Any, str], None],
        *,
        queue_size: int | None = None,
        history: int | None = None,
        delivery: str | None = None,
    ) -> Subscription:
        """Subscribe to ``topic`` (may be a wildcard such as ``keys.goals_all``);
        ``callback(msg, key)`` gets the decoded message on a worker thread.

        Samples whose encoding is not the topic's type, or whose bytes do not parse, are
        counted as rejected and logged; the callback is not called. ``history`` (default: the
        topic's QoS) asks late-joiner history from advanced publishers. ``delivery`` (default:
        ``"channel"`` for control streams, else ``"queue"``) see :class:`Subscription`.
        """
        expected = topic.msg_type

        def handle(raw: RawSample) -> None:
            try:
                msg = decode(raw.payload, raw.encoding, expected)
            except ValueError as exc:
                self.record_rejection(raw.key, str(exc), getattr(exc, "kind", "malformed"))
                return
            callback(msg, raw.key)

        if delivery is None:
            delivery = "channel" if topic.qos.stream_class == StreamClass.CONTROL else "queue"
        return self.subscribe_raw(
            topic.key,
            handle,
            queue_size=queue_size,
            history=topic.qos.history if history is None else history,
            delivery=delivery,
        )

    def subscribe_raw(
        self,
        key_expr: str,
        callback: Callable[[RawSample], None],
        *,
        queue_size: int | None = None,
        history: int = 0,
        delivery: str = "queue",
        timestamps: bool = False,
    ) -> Subscription:
        """Subscribe without decoding: ``callback(RawSample)`` on a worker thread."""
        sub = Subscription(
            self,
            key_expr,
            callback,
            queue_size=queue_size or self.config.queue_size,
            history=history,
            delivery=delivery,
            timestamps=timestamps,
        )
        self._subs.append(sub)
        return sub

    def watch_liveliness(
        self, services: Iterable[str] | None, on_change: Callable[[str, bool], None]
    ) -> None:
        """Call ``on_change(service, alive)`` when a service's liveliness token appears or
        disappears (``services=None``: every service of the prefix). Already-alive services are
        reported at once."""
        import zenoh

        wanted = None if services is None else set(services)
        base = self.keys.liveliness_all.key[:-1]

        def cb(sample: Any) -> None:
            name = str(sample.key_expr)[len(base):]
            if wanted is not None and name not in wanted:
                return
            try:
                on_change(name, sample.kind == zenoh.SampleKind.PUT)
            except Exception as exc:
                self.record_error(f"liveliness callback failed: {exc!r}", exc)

        sub = self.session.liveliness().declare_subscriber(
            self.keys.liveliness_all.key, cb, history=True
        )
        self._others.append(sub)

    # -- status ----------------------------------------------------------------------------------
    def set_degraded(self, reason: str | None) -> None:
        """While ``reason`` is set, :meth:`status_message` reports DEGRADED with ``reason`` as
        ``last_error``; ``None`` clears it (thread-safe: one attribute assignment)."""
        self._degraded = reason

    def status_message(self) -> ServiceStatus:
        """The current :class:`ServiceStatus` (not published)."""
        c = self.counters.snapshot(sum(sub.received for sub in self._subs))
        state = self.state
        if state == ServiceStatus.RUNNING and self._last_counts and (
            c["errors"] > self._last_counts.get("errors", 0)
        ):
            state = ServiceStatus.DEGRADED
        degraded = self._degraded
        last_error = self.last_error
        if state == ServiceStatus.RUNNING and degraded is not None:
            state, last_error = ServiceStatus.DEGRADED, degraded
        self._status_seq += 1
        return ServiceStatus(
            stamp_ns=time.time_ns(),
            seq=self._status_seq,
            service=self.name,
            state=state,
            uptime_s=time.monotonic() - self._t0,
            last_error=last_error,
            version=self.version,
            queued=sum(s.pending() for s in self._subs),
            rejected_by_reason=self.counters.rejections(),
            **c,
        )

    def _publish_status(self) -> None:
        msg = self.status_message()
        self._last_counts = {"errors": msg.errors}
        assert self._status_pub is not None
        self._status_pub.put(msg)

    def _status_loop(self) -> None:
        period = self.config.status_period_s
        while not self.stop_event.wait(period):
            try:
                self._publish_status()
            except Exception as exc:
                self.record_error(f"status publication failed: {exc!r}", exc)
            if self.config.health_file:
                self._write_health(Path(self.config.health_file))

    def connected(self) -> bool:
        """The session reaches the network: a client is connected to a router (peers and
        routers always count as connected)."""
        if self._mode != "client":
            return True
        try:
            return bool(list(self.session.info.routers_zid()))
        except Exception:
            return False

    def _write_health(self, path: Path) -> None:
        """Rewrite the health file (atomically) while the service runs and is connected; a
        healthcheck tests its age. When disconnected the file is left to age."""
        if not self.connected():
            return
        try:
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(json.dumps({"service": self.name, "state": ServiceStatus.State.Name(self.state),
                                       "uptime_s": round(time.monotonic() - self._t0, 1)}))
            os.replace(tmp, path)
        except OSError as exc:
            self.record_error(f"health file {path}: {exc.strerror}", exc)


# --------------------------------------------------------------------------------------------
# The service skeleton
# --------------------------------------------------------------------------------------------


class ServiceApp:
    """One service process: a typed config, a :meth:`setup` (subscriptions, publishers,
    liveliness watches) and optionally a :meth:`loop`; :func:`run_service` does the rest
    (session, liveliness token, status, signals, shutdown, error reporting).

    Subclasses set :attr:`name` (the liveliness token and status name) and implement
    :meth:`setup`; a service with work of its own (the arm's control loop, a camera) overrides
    :meth:`loop`, which must return soon after ``svc.stop_event`` is set::

        class Echo(ServiceApp):
            name = "echo"

            def setup(self, svc: Service) -> None:
                svc.subscribe_raw(svc.keys.all.key, self.on_sample)

    What can fail without the bus (a model file, a camera device) is best opened in
    ``__init__``, before the session: the process then fails before it joins the bus. Errors
    raised by ``__init__`` or ``setup`` end the process with one error line and exit code 2,
    like a bad config.
    """

    name: str = ""

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        #: The process's exit code once the loop has returned (0 unless the service sets it).
        self.exit_code = 0

    def zenoh_config(self) -> ZenohConfig:
        """The zenoh settings of the process's session (default: the config's ``[zenoh]``)."""
        return self.config.zenoh

    def zenoh_extra(self) -> dict[str, Any]:
        """zenoh settings beyond :class:`ZenohConfig` (config path -> JSON value; default
        none), e.g. the router's access control."""
        return {}

    def setup(self, svc: Service) -> None:
        """Declare subscriptions, publishers and watches (before the liveliness token)."""

    def loop(self, svc: Service) -> None:
        """The service's own work; the default waits until the service is stopped."""
        svc.wait()

    def teardown(self, svc: Service) -> None:
        """Called after the loop (or after a failed :meth:`setup`: it must cope with a partial
        set-up), before the bus is closed: write statistics, close files and devices."""


#: A shutdown whose Zenoh teardown hangs this long ends the process (the loop has stopped).
CLOSE_TIMEOUT_S = 5.0


def run_service(app: ServiceApp, *, session: Any | None = None, install_signals: bool = True) -> int:
    """Run ``app``: open the session, ``setup``, declare the liveliness token and start the
    status, run the ``loop`` until SIGINT/SIGTERM or :meth:`Service.stop`, ``teardown``, close.
    Returns the exit code."""
    svc = Service(app.name, app.config, session=session, zenoh=app.zenoh_config(),
                  zenoh_extra=app.zenoh_extra())
    try:
        try:
            app.setup(svc)
            svc.start()
            if install_signals:
                svc.install_signal_handlers()
            app.loop(svc)
        finally:
            app.teardown(svc)
    finally:
        _close_bounded(svc)
    return app.exit_code


def _close_bounded(svc: Service) -> None:
    """Close the service; in a process's main thread, a Zenoh teardown that hangs for
    :data:`CLOSE_TIMEOUT_S` ends the process (exit code 1) after dumping every thread's stack
    to stderr. The watchdog is faulthandler's C thread: it needs no GIL, so it also fires when
    the hang holds the GIL."""
    import faulthandler

    if threading.current_thread() is not threading.main_thread():
        svc.close()
        return
    faulthandler.dump_traceback_later(CLOSE_TIMEOUT_S, exit=True)
    try:
        svc.close()
    finally:
        faulthandler.cancel_dump_traceback_later()


def stream_class_of(topic: Topic) -> StreamClass:
    """The delivery class of a topic (for documentation and tests)."""
    return topic.qos.stream_class
