"""Bus benchmarks: runtime round-trip latency vs raw zenoh-python, recorder throughput.

Run ``python -m benchmarks.bus`` (``--quick`` for a short smoke run). Writes
``benchmarks/results/bus.md`` and ``benchmarks/results/bus.json``.

1. **Round-trip latency** (two processes on loopback, multicast off, peer-to-peer TCP):

   * *raw*: zenoh-python publishers/subscribers with the same QoS as the control loop (express,
     real-time priority, blocking congestion control); the pong process's subscriber callback
     republishes the bytes it got, the ping process's callback sets a ``threading.Event``.
   * *runtime*: the project's :class:`services.bus.runtime.Service`: ping publishes a typed
     ``ArmState`` on ``<prefix>/arm/state``; pong's subscription (bounded queue + worker thread,
     decode, type check) answers with an ``ArmCommand`` echoing the tick on
     ``<prefix>/arm/command``; ping's subscription decodes it and checks the tick.

   * *runtime inline*: the same typed path with the opt-in ``delivery="inline"`` (handlers on
     zenoh's thread, for handlers that return in microseconds).

   All are measured in the same run, in alternating blocks of 300 (raw, runtime, inline, raw,
   ...) so machine load affects them alike; p50/p99 over all round trips after a warm-up;
   ratio = runtime/raw.

2. **Recorder throughput**: a ``psm record`` process listens on loopback; a publisher process
   sends at a fixed offered rate for a fixed time (small: 7-joint ``ArmState`` bytes, ~150 B,
   through a batched non-express zenoh publisher so one Python process can offer > 100k msg/s;
   images: 640x480 JPEG ``CompressedImage`` from OpenCV through the runtime's camera
   publisher). The bench watches the recorder's
   ``ServiceStatus`` until it has received everything, stops it with SIGTERM and counts the
   messages in the finalised MCAP. *lost* = published - recorded; *lag* = ``log_time`` of the
   last recorded message (taken when the writer thread dequeues it) minus the time the
   publisher's last put returned. A rate "keeps up" when lost == 0 and lag < 1 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from services.supervisor import ManagedProcess, free_port

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
QOS = {"express": True}


def _cfg(listen: str | None = None, connect: str | None = None, prefix: str = "psm") -> Any:
    from services.bus.config import ServiceConfig, load_config

    ov: dict[str, Any] = {"zenoh.multicast": False, "prefix": prefix, "log_level": "WARNING"}
    if listen:
        ov["zenoh.listen"] = [listen]
    if connect:
        ov["zenoh.connect"] = [connect]
    return load_config(ServiceConfig, env={}, overrides=ov)


def _spawn(workdir: Path, name: str, *args: str) -> ManagedProcess:
    """Start ``python args`` through the supervisor's process class (log in ``workdir``)."""
    return ManagedProcess(name, [sys.executable, *args], workdir / f"{name}.log")


def _line(proc: ManagedProcess, start: str, timeout_s: float) -> str:
    """The first line of ``proc``'s output that starts with ``start`` (bounded wait)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in proc.log_text().splitlines():
            if line.startswith(start):
                return line
        if not proc.alive():
            break
        time.sleep(0.02)
    raise RuntimeError(f"{proc.name} printed no line starting with {start!r}: {proc.log_tail()}")


def _until_terminated() -> None:
    """Block until SIGTERM or SIGINT (the child roles' lifetime)."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(0.5):
        pass


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q / 100 * (len(s) - 1)))]


def _state_bytes(i: int) -> bytes:
    from services.bus.messages import ArmState, quat, vec3

    return ArmState(stamp_ns=1 + i * 2_000_000, tick=i, sim_time_ns=i * 2_000_000,
                    q=[0.1] * 7, dq=[0.01] * 7, ee_position=vec3(0.3, 0.0, 0.4),
                    ee_orientation=quat(0, 0, 0, 1), frame_id="base").SerializeToString()


# --------------------------------------------------------------------------------------------
# Latency
# --------------------------------------------------------------------------------------------


def _pong_raw(endpoint: str) -> None:
    import zenoh

    from services.bus.runtime import open_session

    session = open_session(_cfg(connect=endpoint).zenoh)
    pub = session.declare_publisher("bench/raw/pong", express=True,
                                    priority=zenoh.Priority.REAL_TIME,
                                    congestion_control=zenoh.CongestionControl.BLOCK)
    sub = session.declare_subscriber("bench/raw/ping", lambda s: pub.put(s.payload))
    print("ready", flush=True)
    _until_terminated()
    sub.undeclare()
    session.close()


def _pong_runtime(endpoint: str, delivery: str | None = None) -> None:
    from services.bus.messages import ArmCommand, ArmState
    from services.bus.runtime import Service

    prefix = "bench" if delivery is None else "benchinline"
    svc = Service("pong", _cfg(connect=endpoint, prefix=prefix)).start()
    cmd = svc.publisher(svc.keys.arm_command)

    def on_state(state: ArmState, _key: str) -> None:
        cmd.put(ArmCommand(stamp_ns=state.stamp_ns, tick=state.tick,
                           mode=ArmCommand.CARTESIAN_ACCELERATION, source="pong"))

    svc.subscribe(svc.keys.arm_state, on_state, delivery=delivery)
    print("ready", flush=True)
    _until_terminated()
    svc.close()


def bench_latency(n_blocks: int, per_block: int, warmup: int) -> dict[str, Any]:
    """Alternating raw/runtime ping-pong blocks; returns RTT statistics in microseconds."""
    import zenoh

    from services.bus.messages import ArmCommand, ArmState
    from services.bus.runtime import Service

    ep = f"tcp/127.0.0.1:{free_port()}"
    svc = Service("ping", _cfg(listen=ep, prefix="bench")).start()
    session = svc.session
    pongs = []
    logs = tempfile.TemporaryDirectory()
    for role in ("pong-raw", "pong-runtime", "pong-inline"):
        p = _spawn(Path(logs.name), role, "-m", "benchmarks.bus", "--role", role, "--endpoint", ep)
        pongs.append(p)
        _line(p, "ready", 60)
    try:
        # raw path
        raw_event = threading.Event()
        raw_pub = session.declare_publisher("bench/raw/ping", express=True,
                                            priority=zenoh.Priority.REAL_TIME,
                                            congestion_control=zenoh.CongestionControl.BLOCK)
        raw_sub = session.declare_subscriber("bench/raw/pong", lambda s: raw_event.set())
        # runtime path
        rt_event = threading.Event()
        expected_tick = [-1]
        bad = [0]
        state_pub = svc.publisher(svc.keys.arm_state)

        def on_cmd(cmd: ArmCommand, _key: str) -> None:
            if cmd.tick != expected_tick[0]:
                bad[0] += 1
            rt_event.set()

        svc.subscribe(svc.keys.arm_command, on_cmd)
        # runtime path with opt-in inline delivery (handlers run on zenoh's thread)
        from services.bus.messages import Keys

        ik = Keys("benchinline")
        in_event = threading.Event()
        in_pub = svc.publisher(ik.arm_state)
        svc.subscribe(ik.arm_command, lambda _c, _k: in_event.set(), delivery="inline")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (
                raw_pub.matching_status.matching and state_pub.has_subscribers
                and in_pub.has_subscribers):
            time.sleep(0.01)
        time.sleep(0.3)
        payload = _state_bytes(0)
        states = [ArmState.FromString(_state_bytes(i)) for i in range(per_block)]

        def raw_block(n: int) -> list[float]:
            out = []
            for _ in range(n):
                raw_event.clear()
                t0 = time.perf_counter_ns()
                raw_pub.put(payload)
                if not raw_event.wait(2.0):
                    raise RuntimeError("raw pong timed out")
                out.append((time.perf_counter_ns() - t0) / 1e3)
            return out

        def rt_block(n: int) -> list[float]:
            out = []
            for i in range(n):
                rt_event.clear()
                st = states[i % len(states)]
                expected_tick[0] = st.tick
                t0 = time.perf_counter_ns()
                state_pub.put(st)
                if not rt_event.wait(2.0):
                    raise RuntimeError("runtime pong timed out")
                out.append((time.perf_counter_ns() - t0) / 1e3)
            return out

        def inline_block(n: int) -> list[float]:
            out = []
            for i in range(n):
                in_event.clear()
                t0 = time.perf_counter_ns()
                in_pub.put(states[i % len(states)])
                if not in_event.wait(2.0):
                    raise RuntimeError("inline pong timed out")
                out.append((time.perf_counter_ns() - t0) / 1e3)
            return out

        raw_block(warmup)
        rt_block(warmup)
        inline_block(warmup)
        raw: list[float] = []
        rt: list[float] = []
        inl: list[float] = []
        for _ in range(n_blocks):
            raw += raw_block(per_block)
            rt += rt_block(per_block)
            inl += inline_block(per_block)
        raw_sub.undeclare()
        raw_pub.undeclare()
    finally:
        for p in pongs:
            p.stop(10)
        logs.cleanup()
        svc.close()
    res = {
        "round_trips_each": len(raw),
        "raw_p50_us": _pct(raw, 50), "raw_p99_us": _pct(raw, 99),
        "runtime_p50_us": _pct(rt, 50), "runtime_p99_us": _pct(rt, 99),
        "inline_p50_us": _pct(inl, 50), "inline_p99_us": _pct(inl, 99),
        "wrong_tick_replies": bad[0],
    }
    res["ratio_p50"] = res["runtime_p50_us"] / res["raw_p50_us"]
    res["ratio_p99"] = res["runtime_p99_us"] / res["raw_p99_us"]
    res["inline_ratio_p50"] = res["inline_p50_us"] / res["raw_p50_us"]
    res["inline_ratio_p99"] = res["inline_p99_us"] / res["raw_p99_us"]
    return res


# --------------------------------------------------------------------------------------------
# Recorder throughput
# --------------------------------------------------------------------------------------------


def _jpeg_640x480(seed: int = 0) -> bytes:
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    h, w = 480, 640
    y, x = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = (x * 255 // w).astype(np.uint8)
    img[..., 1] = (y * 255 // h).astype(np.uint8)
    img[..., 2] = 128
    for _ in range(12):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(10, 80)), [int(v) for v in rng.integers(0, 255, 3)],
                   -1)
    img = cv2.add(img, rng.integers(0, 24, img.shape, dtype=np.uint8))
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    return buf.tobytes()


def _publisher(endpoint: str, kind: str, rate: float, seconds: float) -> None:
    """Publish ``rate`` msg/s for ``seconds`` through the runtime's typed publishers."""
    from services.bus.messages import ArmState, CompressedImage
    from services.bus.runtime import Service

    svc = Service("benchpub", _cfg(connect=endpoint)).start()
    n = int(rate * seconds)
    if kind == "small":
        # Load generator: ArmState bytes on <prefix>/arm/state through a batched (non-express)
        # zenoh publisher, so one Python process can offer > 100k msg/s.
        import zenoh

        topic = svc.keys.arm_state
        raw_pub = svc.session.declare_publisher(
            topic.key, encoding=zenoh.Encoding(topic.encoding or ""),
            congestion_control=zenoh.CongestionControl.BLOCK)

        class _Pub:
            has_subscribers = property(lambda self: raw_pub.matching_status.matching)

            def put_bytes(self, b: bytes) -> None:
                raw_pub.put(b)

        pub = _Pub()  # type: ignore[assignment]
        msgs = [_state_bytes(i) for i in range(n)]
        ArmState.FromString(msgs[0])
    else:
        pub = svc.publisher(svc.keys.camera_image("bench"))
        jpeg = _jpeg_640x480()
        msgs = []
        for i in range(n):
            img = CompressedImage(frame_id="cam", format="jpeg", data=jpeg)
            img.timestamp.seconds = 1 + i // 60
            img.timestamp.nanos = (i % 60) * 16_000_000
            msgs.append(img.SerializeToString())
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and not pub.has_subscribers:
        time.sleep(0.01)
    time.sleep(0.3)
    batch = max(1, int(rate / 200))  # pace in 5 ms batches
    t0 = time.monotonic()
    sent = 0
    while sent < n:
        for _ in range(min(batch, n - sent)):
            pub.put_bytes(msgs[sent])
            sent += 1
        due = t0 + sent / rate
        d = due - time.monotonic()
        if d > 0:
            time.sleep(d)
    t1 = time.monotonic()
    print(json.dumps({"sent": sent, "seconds": t1 - t0, "end_wall": time.time(),
                      "bytes": len(msgs[0])}), flush=True)
    time.sleep(0.3)
    svc.close()


def bench_recorder(kind: str, rate: float, seconds: float, workdir: Path) -> dict[str, Any]:
    """One offered-rate step; returns counts, achieved rate and drain lag."""
    from services.bus.log import read_samples
    from services.bus.messages import Keys
    from services.bus.runtime import Service

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    out = workdir / f"rec-{kind}-{int(rate)}.mcap"
    rec = _spawn(workdir, f"recorder-{kind}-{int(rate)}", "-m", "services.bus.cli", "record", "-o", str(out),
                 "--listen", ep, "--no-multicast", "--log-level", "WARNING", "--set", "status_period_s=0.1")
    statuses: list[tuple[float, Any]] = []
    watcher = Service("benchwatch", _cfg(connect=ep)).start()
    watcher.subscribe(Keys().status("recorder"), lambda m, _k: statuses.append((time.time(), m)))
    try:
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not statuses:
            time.sleep(0.05)
        if not statuses:
            raise RuntimeError("recorder did not start")
        pub = _spawn(workdir, f"pub-{kind}-{int(rate)}", "-m", "benchmarks.bus", "--role", f"pub-{kind}",
                     "--endpoint", ep, "--rate", str(rate), "--seconds", str(seconds))
        report = json.loads(_line(pub, "{", seconds + 60))
        pub.wait(60)
        pub.stop()
        sent = int(report["sent"])
        end_wall = float(report["end_wall"])
        # Stop the recorder only once it has everything: its `received` (which also counts
        # status traffic) has reached `sent` and then grows at status-traffic pace only
        # (< 200 msg/s over the last >= 0.5 s).
        drained_at = None
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            if len(statuses) >= 2:
                t, st = statuses[-1]
                older = [(t0, s0) for t0, s0 in statuses if t - t0 >= 0.5]
                if older and st.received >= sent and t >= end_wall:
                    t0, s0 = older[-1]
                    if (st.received - s0.received) / (t - t0) < 200:
                        drained_at = t
                        break
            time.sleep(0.05)
        max_backlog = max((st.queued for _, st in statuses), default=0)
    finally:
        watcher.close()
        rc = rec.stop(30)
    key = Keys().arm_state.key if kind == "small" else Keys().camera_image("bench").key
    recorded = 0
    last_log_ns = 0
    for smp in read_samples(out, topics=[key], strict=True):
        recorded += 1
        last_log_ns = max(last_log_ns, smp.log_time_ns)
    # lag = when the recorder's writer took the last message off its receive channel (its
    # log_time) minus when the publisher finished putting (both wall clock, same machine)
    lag = max(0.0, last_log_ns / 1e9 - end_wall) if recorded else None
    size = out.stat().st_size
    out.unlink()
    return {
        "kind": kind, "offered_rate": rate, "seconds": seconds, "sent": sent,
        "publish_rate": sent / report["seconds"], "msg_bytes": report["bytes"],
        "recorded": recorded, "lost": sent - recorded,
        "drain_lag_s": lag,
        "recorded_rate": None if lag is None else recorded / (report["seconds"] + lag),
        "drained_via_status": drained_at is not None,
        "max_backlog": max_backlog, "recorder_exit": rc, "file_mb": size / 1e6,
    }


def bench_raw_mcap(n: int) -> dict[str, float]:
    """Same-run references: the reference ``mcap`` writer alone and the recorder's sink alone
    (no bus), writing ``n`` small ArmState messages to a temporary file; msg/s."""
    from mcap.writer import Writer

    from services.bus.messages import ArmState, Keys, encoding_for, schema_name_of
    from services.bus.recorder import McapSink

    msgs = [_state_bytes(i) for i in range(n)]
    key = Keys().arm_state.key
    enc = encoding_for(ArmState)
    with tempfile.TemporaryDirectory() as tmp:
        with open(Path(tmp) / "ref.mcap", "wb") as fh:
            w = Writer(fh)
            w.start()
            sid = w.register_schema(schema_name_of(ArmState), "protobuf", b"")
            ch = w.register_channel(key, "protobuf", sid)
            t0 = time.perf_counter()
            for i, m in enumerate(msgs):
                w.add_message(ch, i, m, i)
            w.finish()
            ref = n / (time.perf_counter() - t0)
        sink = McapSink(Path(tmp) / "sink.mcap")
        t0 = time.perf_counter()
        for i, m in enumerate(msgs):
            sink.write(key, enc, m, i + 1)
        sink.close()
        own = n / (time.perf_counter() - t0)
    return {"reference_mcap_writer_msgs_per_s": ref, "recorder_sink_msgs_per_s": own}


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def _keeps_up(r: dict[str, Any]) -> bool:
    return r["lost"] == 0 and r["drain_lag_s"] is not None and r["drain_lag_s"] < 1.0


def write_report(res: dict[str, Any]) -> None:
    """Write bus.json and bus.md."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bus.json").write_text(json.dumps(res, indent=2) + "\n")
    lat = res["latency"]
    lines = [
        "# Bus benchmarks",
        "",
        f"Measured {res['date_utc']} on {res['machine']} ({res['cpus']} CPUs, shared; load "
        f"average at start {res['load_avg']}), zenoh {res['zenoh']}, python {res['python']}. "
        "Produced by `python -m benchmarks.bus`; method in the module docstring.",
        "",
        "## Round-trip latency: project runtime vs raw zenoh-python (same run)",
        "",
        "Two processes on loopback TCP, multicast off. Raw: callback republishes the bytes. "
        "Runtime: typed ArmState -> pong Service (bounded zenoh channel + worker thread, decode, "
        "type check) -> typed ArmCommand echoing the tick -> ping Service (same path). Alternating blocks of "
        f"{res['params']['per_block']} round trips, {lat['round_trips_each']} each after warm-up.",
        "",
        "| path | p50 (µs) | p99 (µs) |",
        "|---|---:|---:|",
        f"| raw zenoh-python | {lat['raw_p50_us']:.0f} | {lat['raw_p99_us']:.0f} |",
        f"| project runtime (default: channel + worker thread) | {lat['runtime_p50_us']:.0f} | "
        f"{lat['runtime_p99_us']:.0f} |",
        f"| **ratio runtime/raw** | **{lat['ratio_p50']:.2f}×** | **{lat['ratio_p99']:.2f}×** |",
        f"| project runtime, opt-in `delivery=\"inline\"` | {lat['inline_p50_us']:.0f} | "
        f"{lat['inline_p99_us']:.0f} |",
        f"| ratio inline/raw | {lat['inline_ratio_p50']:.2f}× | {lat['inline_ratio_p99']:.2f}× |",
        "",
        f"Target ≤ 1.5× at p50 and p99: p50 {'met' if lat['ratio_p50'] <= 1.5 else 'NOT met'}, "
        f"p99 {'met' if lat['ratio_p99'] <= 1.5 else 'NOT met'}. Replies with a wrong tick: "
        f"{lat['wrong_tick_replies']}.",
        "",
        "## Recorder throughput",
        "",
        "A publisher process sends at a fixed offered rate; `psm record` (separate process) "
        "writes the MCAP; messages counted in the finalised file. Lag = log time of the last "
        "message in the file (when the recorder's writer took it off its receive channel) "
        "minus the time the publisher finished. Recorder rate = recorded / (publish time + "
        "lag). 'keeps up' = 0 lost and lag < 1 s. The recorder never drops: "
        "when it falls behind, zenoh back-pressure slows the publisher (blocking congestion "
        "control), so 'lost' stays 0 and the lag shows the shortfall.",
        "",
        "| kind | msg size (B) | offered (msg/s) | achieved publish (msg/s) | sent | recorded "
        "| lost | lag (s) | recorder rate (msg/s) | keeps up |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in res["recorder"]:
        lag = "n/a" if r["drain_lag_s"] is None else f"{r['drain_lag_s']:.2f}"
        rate = "n/a" if r["recorded_rate"] is None else f"{r['recorded_rate']:.0f}"
        lines.append(
            f"| {r['kind']} | {r['msg_bytes']} | {r['offered_rate']:.0f} | "
            f"{r['publish_rate']:.0f} | {r['sent']} | {r['recorded']} | {r['lost']} | "
            f"{lag} | {rate} | {'yes' if _keeps_up(r) else 'no'} |")
    best = res["summary"]
    ref = res["writer_reference"]
    lines += [
        "",
        "Same-run references (one process, no bus, 200,000 small messages to a file): the "
        f"reference `mcap` Python writer alone does **{ref['reference_mcap_writer_msgs_per_s']:.0f}"
        f" msg/s**, the recorder's own sink (lean writer + channel/schema lookup + stamp "
        f"extraction) **{ref['recorder_sink_msgs_per_s']:.0f} msg/s**. The issue's baseline "
        "(~200,000 msg/s for the raw writer) was measured on an idle machine; the ratio of the "
        "recorder's end-to-end rate to the reference writer's rate in the same run is the "
        "load-independent figure.",
        "",
        f"Highest offered rate kept up with zero loss: small messages "
        f"**{best['small_max_rate']:.0f} msg/s** (target ≥ 50,000), 640×480 JPEG frames "
        f"**{best['jpeg_max_rate']:.0f} frames/s** (target ≥ 60).",
        "",
    ]
    (RESULTS / "bus.md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    """Entry point (also the child roles used by the benchmark itself)."""
    ap = argparse.ArgumentParser(description="bus benchmarks")
    ap.add_argument("--quick", action="store_true", help="short smoke run")
    ap.add_argument("--role", help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--no-write", action="store_true", help="do not write results/")
    args = ap.parse_args(argv)
    if args.role == "pong-raw":
        _pong_raw(args.endpoint)
        return 0
    if args.role == "pong-runtime":
        _pong_runtime(args.endpoint)
        return 0
    if args.role == "pong-inline":
        _pong_runtime(args.endpoint, "inline")
        return 0
    if args.role in ("pub-small", "pub-jpeg"):
        _publisher(args.endpoint, args.role[4:], args.rate, args.seconds)
        return 0

    from importlib.metadata import version

    quick = args.quick
    params = {"blocks": 2 if quick else 20, "per_block": 300,
              "warmup": 200 if quick else 500,
              "small_rates": [20_000, 50_000] if quick else [25_000, 50_000, 75_000, 100_000],
              "jpeg_rates": [60] if quick else [30, 60, 120, 240],
              "seconds": 2.0 if quick else 4.0}
    res: dict[str, Any] = {
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": platform.machine(), "cpus": os.cpu_count(),
        "load_avg": ", ".join(f"{v:.2f}" for v in os.getloadavg()),
        "python": platform.python_version(), "zenoh": version("eclipse-zenoh"),
        "params": params,
    }
    print("raw mcap writer ...", flush=True)
    res["writer_reference"] = bench_raw_mcap(50_000 if quick else 200_000)
    print(json.dumps(res["writer_reference"]), flush=True)
    print("latency ...", flush=True)
    res["latency"] = bench_latency(params["blocks"], params["per_block"], params["warmup"])
    print(json.dumps(res["latency"]), flush=True)
    res["recorder"] = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind, rates in (("small", params["small_rates"]), ("jpeg", params["jpeg_rates"])):
            for rate in rates:
                print(f"recorder {kind} {rate}/s ...", flush=True)
                r = bench_recorder(kind, float(rate), params["seconds"], Path(tmp))
                print(json.dumps(r), flush=True)
                res["recorder"].append(r)
    ok_small = [r["offered_rate"] for r in res["recorder"] if r["kind"] == "small"
                and _keeps_up(r)]
    ok_jpeg = [r["offered_rate"] for r in res["recorder"] if r["kind"] == "jpeg"
               and _keeps_up(r)]
    res["summary"] = {"small_max_rate": max(ok_small, default=0.0),
                      "jpeg_max_rate": max(ok_jpeg, default=0.0),
                      "latency_ratio_p50": res["latency"]["ratio_p50"],
                      "latency_ratio_p99": res["latency"]["ratio_p99"]}
    if not args.no_write:
        write_report(res)
        print(f"wrote {RESULTS / 'bus.md'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
