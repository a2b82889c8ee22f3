"""A fuzzer for a running stack: ``python -m tests.faults.fuzz_tool ENDPOINT [--prefix P]
[--duration S] [--cycles N] [--rate N] [--names person,cam0] [--seed K]``.

For ``duration`` seconds (or, with ``--cycles N``, until every key has had every kind ``N`` times;
``duration`` is then the bound) it publishes, as a client of the router at ``ENDPOINT``, on every key
of the catalogue (:meth:`services.bus.messages.Keys.catalogue`, the one module that spells the
keys; the parametrised ones with each of ``names``: the stack's goal and camera) about ``rate``
samples per second in all, cycling through these kinds of bad input:

* ``bytes`` — random bytes with the key's encoding;
* ``encoding`` — the key's message with another encoding: ``text/plain``, JSON, an unknown
  schema, none;
* ``type`` — a valid message of another type, with that type's encoding;
* ``reinterpreted`` — a valid message of another type with the key's encoding (its bytes read
  as the key's type);
* ``values`` — the key's own type with every number NaN, ±inf or ±1e308;
* ``ticks`` — the key's own type with plausible numbers but ticks and stamps that are not the
  arm's: jumping (the live tick ± 1000, random, 0, 2^63 - 1) and stale or future stamps (the
  live stamp ∓ 10 s, 1, 2^62).

It follows the arm's real state stream (:class:`services.robot.protocol.StateStream`, so its own
fuzzed states never mislead it) to place ticks and stamps near the live ones. Messages that a
receiver would obey as they are — an ``ObstacleCommand`` CLEAR, a REMOVE of a known id, an ADD
of a plausible obstacle — are never generated: a valid command is not a fault, and keeping them
off the bus is the access control's job. It prints one JSON line: how many samples of each kind
went to each key, and how long the router took to take the last of them (``flushed_s``).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import threading
import time
from collections import Counter
from typing import Any

from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

KINDS = ("bytes", "encoding", "type", "reinterpreted", "values", "ticks")
BAD_FLOATS = (math.nan, math.inf, -math.inf, 1e308, -1e308)
WRONG_ENCODINGS = ("text/plain", "application/json", "application/protobuf;psm.Nope", "")
#: Fields that carry a tick or a stamp (every project message: stamp_ns + tick/seq).
_TICK_FIELDS = frozenset({"tick", "state_tick", "clearance_tick", "seq", "frame_stamp_ns"})
_STAMP_FIELDS = frozenset({"stamp_ns", "sim_time_ns"})


class LiveClock:
    """The arm's live tick and stamp, from its real states only."""

    def __init__(self) -> None:
        from services.robot.protocol import StateStream

        self._stream = StateStream()
        self._lock = threading.Lock()

    def on_state(self, sample: Any) -> None:
        from services.bus.messages import ArmState, decode

        try:
            st = decode(sample.payload.to_bytes(), str(sample.encoding), ArmState)
        except ValueError:
            return
        dt = float(st.dt_s)  # type: ignore[attr-defined]
        if not (math.isfinite(dt) and dt > 0):
            return
        with self._lock:
            self._stream.check(int(st.tick), int(st.stamp_ns), dt)  # type: ignore[attr-defined]

    def now(self) -> tuple[int, int]:
        """``(tick, stamp_ns)`` of the latest real state (``(0, 0)`` before one)."""
        with self._lock:
            return max(0, self._stream.last_tick), self._stream.last_stamp


class Fuzzer:
    """Bad samples for the catalogue topics (see the module docstring)."""

    def __init__(self, rng: random.Random, clock: LiveClock) -> None:
        from services.bus.messages import MESSAGE_TYPES

        self.rng = rng
        self.clock = clock
        self.types = list(MESSAGE_TYPES.values())

    # -- values --------------------------------------------------------------------------------
    def _tick(self) -> int:
        live, _ = self.clock.now()
        return self.rng.choice([0, (1 << 63) - 1, self.rng.getrandbits(62), live + 1000,
                                max(0, live - 1000)])

    def _stamp(self) -> int:
        _, live = self.clock.now()
        return self.rng.choice([1, 1 << 62, self.rng.getrandbits(62), live + 10_000_000_000,
                                max(1, live - 10_000_000_000)])

    def _float(self, bad: bool) -> float:
        return self.rng.choice(BAD_FLOATS) if bad else self.rng.uniform(-1.0, 1.0)

    def _scalar(self, f: FieldDescriptor, bad: bool) -> Any:
        t = f.type
        if t in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
            return self._float(bad)
        if f.name in _STAMP_FIELDS:
            return self._stamp()
        if f.name in _TICK_FIELDS:
            return self._tick()
        if t == FieldDescriptor.TYPE_BOOL:
            return self.rng.random() < 0.5
        if t == FieldDescriptor.TYPE_STRING:
            return "".join(self.rng.choice("abcxyz_-/ ") for _ in range(self.rng.randint(0, 12)))
        if t == FieldDescriptor.TYPE_BYTES:
            return self.rng.randbytes(self.rng.randint(0, 64))
        if t == FieldDescriptor.TYPE_ENUM:
            values = [v.number for v in f.enum_type.values]
            return self.rng.choice([*values, 99])
        if t in (FieldDescriptor.TYPE_UINT32, FieldDescriptor.TYPE_FIXED32):
            return self.rng.getrandbits(32)
        if t in (FieldDescriptor.TYPE_INT32, FieldDescriptor.TYPE_SINT32, FieldDescriptor.TYPE_SFIXED32):
            return self.rng.randint(-(1 << 31), (1 << 31) - 1)
        if t in (FieldDescriptor.TYPE_UINT64, FieldDescriptor.TYPE_FIXED64):
            return self.rng.getrandbits(63)
        return self.rng.randint(-(1 << 62), (1 << 62))

    def fill(self, msg: Message, bad: bool, depth: int = 0) -> Message:
        """Set every field of ``msg``: numbers bad (NaN, inf, 1e308) when ``bad``, else
        plausible; ticks and stamps never the arm's (:meth:`_tick`, :meth:`_stamp`)."""
        for f in msg.DESCRIPTOR.fields:
            if f.type == FieldDescriptor.TYPE_MESSAGE:
                if depth >= 3 or f.message_type.GetOptions().map_entry:
                    continue
                if f.is_repeated:
                    for _ in range(self.rng.randint(0, 3)):
                        self.fill(getattr(msg, f.name).add(), bad, depth + 1)
                else:
                    self.fill(getattr(msg, f.name), bad, depth + 1)
            elif f.is_repeated:
                getattr(msg, f.name).extend(self._scalar(f, bad) for _ in range(self.rng.randint(0, 9)))
            else:
                setattr(msg, f.name, self._scalar(f, bad))
        return msg

    def _own(self, cls: type[Message], bad: bool) -> Message:
        from services.bus.messages import ObstacleCommand

        msg = self.fill(cls(), bad)
        if isinstance(msg, ObstacleCommand):
            # Never a command a monitor would obey as it is (module docstring): ADD / MOVE of an
            # obstacle with NaN, inf or 1e308 in it, REMOVE of an id nobody has, or no action.
            msg.action = self.rng.choice([ObstacleCommand.ADD, ObstacleCommand.MOVE,
                                          ObstacleCommand.REMOVE, 99])
            msg.id = msg.obstacle.id = f"fuzz-{self.rng.getrandbits(32)}"
            msg.obstacle.position.x = self.rng.choice(BAD_FLOATS)
        return msg

    # -- samples -------------------------------------------------------------------------------
    def sample(self, topic: Any, kind: str) -> tuple[bytes, str]:
        """``(payload, encoding)`` of one bad sample of ``kind`` for ``topic``."""
        from services.bus.messages import encoding_for

        cls = topic.msg_type
        enc = encoding_for(cls)
        if kind == "bytes":
            return self.rng.randbytes(self.rng.randint(1, 256)), enc
        if kind == "encoding":
            return self._own(cls, True).SerializeToString(), self.rng.choice(WRONG_ENCODINGS)
        other = self.rng.choice([t for t in self.types if t is not cls])
        if kind == "type":
            return self.fill(other(), False).SerializeToString(), encoding_for(other)
        if kind == "reinterpreted":
            return self.fill(other(), self.rng.random() < 0.5).SerializeToString(), enc
        return self._own(cls, kind == "values").SerializeToString(), enc


def topics(prefix: str, names: list[str]) -> list[Any]:
    """Every concrete catalogue topic of ``prefix``, the parametrised ones once per name."""
    from services.bus.messages import Keys

    keys = Keys(prefix)
    out: dict[str, Any] = {}
    for name in names:
        for t in keys.catalogue(name):
            out.setdefault(t.key, t)
    return list(out.values())


def run(endpoint: str, prefix: str, duration_s: float, rate: float, names: list[str],
        seed: int, sent_log: str | None = None, cycles: int = 0) -> dict[str, Any]:
    """Fuzz the stack at ``endpoint`` (see the module docstring); returns the counts and
    ``cycles_done`` (how many times every key had every kind). With
    ``sent_log``, every sample sent is also written there, one line each: key, kind, encoding,
    the payload's BLAKE2b-128 digest and its size [bytes] (to find which ones a receiver missed)."""
    import hashlib

    import zenoh

    from services.bus.config import ZenohConfig
    from services.bus.messages import Keys
    from services.bus.runtime import zenoh_config

    session = zenoh.open(zenoh_config(ZenohConfig(mode="client", connect=[endpoint], multicast=False)))
    clock = LiveClock()
    state_sub = session.declare_subscriber(Keys(prefix).arm_state.key, clock.on_state)
    fuzzer = Fuzzer(random.Random(seed), clock)
    catalogue = topics(prefix, names)
    # Blocking congestion control: every sample reaches the router (zenoh's default drops under
    # congestion), so what the stack received is what this counted.
    pubs = {t.key: session.declare_publisher(t.key, congestion_control=zenoh.CongestionControl.BLOCK)
            for t in catalogue}
    sent: Counter[str] = Counter()
    period = 1.0 / rate
    # Every key has a subscriber in a stack (the recorder's <prefix>/**): start once the router
    # has told this session so (up to 10 s), and a little later (the route can lag the status).
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not all(p.matching_status.matching for p in pubs.values()):
        time.sleep(0.05)
    time.sleep(0.5)
    t0 = time.monotonic()
    i = 0
    total = cycles * len(KINDS) * len(catalogue) if cycles > 0 else None
    log = open(sent_log, "w") if sent_log else None  # noqa: SIM115 (closed below)
    try:
        while time.monotonic() - t0 < duration_s and (total is None or i < total):
            topic = catalogue[i % len(catalogue)]
            kind = KINDS[(i // len(catalogue)) % len(KINDS)]
            payload, encoding = fuzzer.sample(topic, kind)
            pubs[topic.key].put(payload, encoding=encoding)
            if log is not None:
                digest = hashlib.blake2b(payload, digest_size=16).hexdigest()
                log.write(f"{topic.key}\t{kind}\t{encoding}\t{digest}\t{len(payload)}\n")
            sent[f"{topic.key[len(prefix) + 1:]}:{kind}"] += 1
            i += 1
            delay = t0 + i * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        seconds = time.monotonic() - t0
        flushed_s = _barrier(endpoint, session, prefix)
    finally:
        if log is not None:
            log.close()
        state_sub.undeclare()
        for p in pubs.values():
            p.undeclare()
        session.close()
    return {"published": i, "seconds": round(seconds, 3), "keys": len(catalogue),
            "cycles_done": i // (len(KINDS) * len(catalogue)),
            "flushed_s": flushed_s, "by_key_and_kind": dict(sorted(sent.items()))}


def _barrier(endpoint: str, session: Any, prefix: str, timeout_s: float = 30.0) -> float | None:
    """Wait until the router has taken every sample this session published; returns how long
    that took [s] (None if not within ``timeout_s``).

    Under blocking congestion control a slow subscriber (the recorder, under the flood) pushes
    back up to this session, whose transmit queue can still hold samples when the flood ends;
    closing the session then would drop them. So one more sample goes out on the same priority
    lane, on a key outside the stack's prefix that only a second session of this tool
    subscribes to: the router forwards in order, so once it arrives there, everything before it
    has left this session.
    """
    import zenoh

    from services.bus.config import ZenohConfig
    from services.bus.runtime import zenoh_config

    key = f"{prefix}_fuzz/barrier"
    arrived = threading.Event()
    probe = zenoh.open(zenoh_config(ZenohConfig(mode="client", connect=[endpoint], multicast=False)))
    try:
        sub = probe.declare_subscriber(key, lambda _s: arrived.set())
        pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        t0 = time.monotonic()
        deadline = t0 + timeout_s
        while time.monotonic() < deadline and not pub.matching_status.matching:
            time.sleep(0.02)
        pub.put(b"barrier")
        ok = arrived.wait(max(0.0, deadline - time.monotonic()))
        pub.undeclare()
        sub.undeclare()
        return round(time.monotonic() - t0, 3) if ok else None
    finally:
        probe.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.faults.fuzz_tool", description=__doc__.split("\n")[0])
    ap.add_argument("endpoint", help="the stack's router, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--prefix", default="psm")
    ap.add_argument("--duration", type=float, default=5.0, help="seconds (with --cycles: at most)")
    ap.add_argument("--cycles", type=int, default=0,
                    help="stop once every key has had every kind this many times (0: run for --duration)")
    ap.add_argument("--rate", type=float, default=2000.0, help="samples per second, all keys together")
    ap.add_argument("--names", default="person,cam0", help="goal and camera names of the stack")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sent-log", help="write every sample sent here (key, kind, encoding, digest, size)")
    args = ap.parse_args(argv)
    result = run(args.endpoint, args.prefix, args.duration, args.rate, args.names.split(","), args.seed,
                 args.sent_log, args.cycles)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
