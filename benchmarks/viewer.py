"""Viewer benchmark: what ``psm view`` costs a running 500 Hz stack.

Run ``python -m benchmarks.viewer`` (``--seconds 20`` per scenario, ``--quick`` for 8 s). Writes
``benchmarks/results/viewer.md`` and ``benchmarks/results/viewer.json``.

Scenarios, each a fresh stack on 127.0.0.1 (multicast off) started by the supervisor of ``psm
up`` from the benchmark's own stack file: router, ``psm arm`` (realtime, 500 Hz) and the probe
``psm arm probe`` answering every state (1,000 samples/s of control traffic, plus the arm's
transforms and every process's status):

1. **no viewer**;
2. **viewer, no client**: the same stack with ``--view`` (:func:`services.stack.load_stack`
   ``view=True``, the code path of ``psm up --view``), nobody connected;
3. **viewer + client**: a Foxglove WebSocket client (its own process, ``foxglove.sdk.v1``)
   subscribed to every channel, with the default rate limits (state and command at 50 Hz).

CPU is read per process from ``/proc/<pid>/stat`` (utime + stime) over the window after a
warm-up, as % of one core. The arm and the probe run at normal scheduling. The client reports
the messages it received per topic (and its own CPU, not counted as the stack's).
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.arm import _load
from benchmarks.stack import stack_header
from services.stack import load_stack
from services.supervisor import ManagedProcess, Supervisor, cpu_seconds, free_port

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

SCENARIOS: dict[str, dict[str, bool]] = {
    "no viewer": {"view": False, "client": False},
    "viewer, no client": {"view": True, "client": False},
    "viewer + client": {"view": True, "client": True},
}


def _stack_file(workdir: Path, endpoint: str, view_port: int) -> Path:
    text = stack_header("viewer-benchmark", endpoint, workdir) + f"""
[[stack.processes]]
name = "router"
command = ["serve", "router"]
[[stack.processes]]
name = "arm"
command = ["arm"]
needs = ["router"]
[[stack.processes]]
name = "probe"
command = ["arm", "probe", "--pattern", "hold"]
needs = ["router", "arm"]

[router]
listen = [{json.dumps(endpoint)}]
[arm]
dt_s = 0.002
[viewer]
port = {view_port}
"""
    path = workdir / "stack.toml"
    path.write_text(text)
    return path


def run_scenario(name: str, seconds: float, warmup_s: float) -> dict[str, Any]:
    """Start the scenario's stack (and client), measure CPU over ``seconds``, stop."""
    spec = SCENARIOS[name]
    with tempfile.TemporaryDirectory(prefix="viewer-bench-") as tmp:
        workdir = Path(tmp)
        view_port = free_port()
        stack = load_stack(_stack_file(workdir, f"tcp/127.0.0.1:{free_port()}", view_port),
                           view=spec["view"], env={})
        sup = Supervisor(stack, out=io.StringIO(), live=False)
        client: ManagedProcess | None = None
        client_out = workdir / "client.json"
        try:
            sup.start()
            procs = {row.name: row.proc for row in sup.rows}
            if spec["client"]:
                client = ManagedProcess(
                    "client", [sys.executable, "-m", "benchmarks.viewer", "--client", str(view_port),
                               "--client-seconds", str(warmup_s + seconds + 1.0),
                               "--client-out", str(client_out)],
                    workdir / "client.log")
                procs["client"] = client
            time.sleep(warmup_s)
            before = {n: cpu_seconds(p.pid) or 0.0 for n, p in procs.items()}
            load_before = _load()
            t0 = time.monotonic()
            time.sleep(seconds)
            window = time.monotonic() - t0
            after = {n: cpu_seconds(p.pid) or 0.0 for n, p in procs.items()}
            alive = {n: p.poll() is None for n, p in procs.items()}
            load_after = _load()
            if client is not None and client.wait(30.0) is None:
                client.stop(5)
        finally:
            if client is not None and client.poll() is None:
                client.stop(5)
            sup.shutdown()
        received = json.loads(client_out.read_text()) if client_out.exists() else {}
    cpu = {n: round(100.0 * (after[n] - before[n]) / window, 1) for n in procs}
    return {
        "window_s": round(window, 2),
        "cpu_pct": cpu,
        "stack_cpu_pct": round(sum(v for n, v in cpu.items() if n != "client"), 1),
        "alive_during_window": alive,
        "loadavg": [load_before, load_after],
        "client": received,
    }


async def _client(port: int, seconds: float) -> dict[str, Any]:
    """Subscribe to every channel for ``seconds``; messages and bytes per topic, and the rate
    over the last ``seconds`` minus the first second."""
    import struct

    import websockets

    topics: dict[int, str] = {}
    counts: dict[str, list[int]] = {}
    t_start = time.monotonic()
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                  max_size=None) as ws:
        deadline = t_start + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                frame = await asyncio.wait_for(ws.recv(), left)
            except TimeoutError:
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    subs = [{"id": c["id"], "channelId": c["id"]} for c in msg["channels"]]
                    topics.update({c["id"]: c["topic"] for c in msg["channels"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                elif msg["op"] == "status" and msg.get("message", "").startswith("Unknown channel ID: "):
                    # The SDK refuses a subscription that overtakes the channel's registration
                    # (docs/bus.md#live-view): subscribe again to a channel it advertised.
                    cid = int(msg["message"].rsplit(" ", 1)[1])
                    if cid in topics:
                        await ws.send(json.dumps(
                            {"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid}]}))
                continue
            (sub_id,) = struct.unpack_from("<I", frame, 1)
            c = counts.setdefault(topics.get(sub_id, "?"), [0, 0])
            c[0] += 1
            c[1] += len(frame) - 13
    elapsed = time.monotonic() - t_start
    return {"seconds": round(elapsed, 2), "cpu_s": round(time.process_time(), 2),
            "topics": {t: {"messages": n, "bytes": b, "per_s": round(n / elapsed, 1)}
                       for t, (n, b) in sorted(counts.items())}}


def write_report(res: dict[str, Any], out: Path = RESULTS) -> None:
    """Write ``viewer.json`` and ``viewer.md`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "viewer.json").write_text(json.dumps(res, indent=2, default=str))
    sc = res["scenarios"]
    cols = list(sc)
    names = ["router", "arm", "probe", "viewer", "client"]
    lines = [
        "# Viewer benchmark: what `psm view` costs a 500 Hz stack",
        "",
        f"{res['date']} · {res['machine']} · {res['cpus']} CPUs · {res['seconds']} s windows after "
        f"{res['warmup_s']} s warm-up · `python -m benchmarks.viewer` (method: module docstring). "
        "CPU = utime + stime from `/proc/<pid>/stat` over the window, % of one core; the arm and "
        "the probe at normal scheduling.",
        "",
        "| process | " + " | ".join(cols) + " |",
        "|---|" + "---:|" * len(cols),
    ]
    for n in names:
        cells = [f"{sc[k]['cpu_pct'][n]:.1f}" if n in sc[k]["cpu_pct"] else "–" for k in cols]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines.append("| **stack total** (client not counted) | "
                 + " | ".join(f"{sc[k]['stack_cpu_pct']:.1f}" for k in cols) + " |")
    base = sc[cols[0]]["stack_cpu_pct"]
    lines.append("| difference to no viewer | " + " | ".join(
        f"{sc[k]['stack_cpu_pct'] - base:+.1f}" for k in cols) + " |")
    client = sc.get("viewer + client", {}).get("client", {})
    if client.get("topics"):
        lines += ["", f"What the client received ({client['seconds']} s, warm-up included):", "",
                  "| topic | messages/s | bytes |", "|---|---:|---:|"]
        for t, c in client["topics"].items():
            lines.append(f"| `{t}` | {c['per_s']:.1f} | {c['bytes']} |")
    lines += ["", "Load average (1 min) before/after the windows: "
              + ", ".join(f"{k} {sc[k]['loadavg']}" for k in cols) + "."]
    (out / "viewer.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    """Run the three scenarios and write the report (or, with ``--client``, be the client)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="measurement window per scenario")
    ap.add_argument("--warmup", type=float, default=4.0, help="warm-up before each window, s")
    ap.add_argument("--quick", action="store_true", help="8 s windows")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--client", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--client-seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--client-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.client:
        res = asyncio.run(_client(args.client, args.client_seconds))
        assert args.client_out is not None
        args.client_out.write_text(json.dumps(res))
        return 0
    seconds = 8.0 if args.quick else args.seconds
    res: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": platform.machine(), "cpus": os.cpu_count(),
        "seconds": seconds, "warmup_s": args.warmup, "scenarios": {},
    }
    for name in SCENARIOS:
        print(f"scenario {name} ...", flush=True)
        res["scenarios"][name] = run_scenario(name, seconds, args.warmup)
        print(json.dumps(res["scenarios"][name]["cpu_pct"]), flush=True)
    write_report(res, args.out)
    print((args.out / "viewer.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
