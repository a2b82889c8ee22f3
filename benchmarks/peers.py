"""Peer benchmark: a trivial two-node lockstep pair on dora-rs, raw zenoh-python and the runtime.

Run ``python -m benchmarks.peers`` (``--quick`` for a short smoke run, ``--round-trips N`` for
the number of measured round trips per variant). Writes ``benchmarks/results/peers.md`` and
``benchmarks/results/peers.json``.

The same pair in three frameworks, five variants, all started in one run and measured in
alternating blocks:
a *ping* node sends a small message, a *pong* node answers it at once, ping sends the next one
only after the answer (lockstep) and times each round trip with ``time.perf_counter_ns``.

1. **dora-rs** (``dora run dataflow.yml``: no ``dora up``, no coordinator; the daemon runs
   inside the ``dora run`` process, the two nodes are its child processes). The dataflow
   (:func:`dataflow_yaml`, written into a temporary directory) has two Python nodes,
   ``python -u -m benchmarks.peers --dora-node ping|pong``; ping sends a pyarrow ``int64``
   array (the tick plus 19 more values: 160 bytes) on output ``ping``, pong sends the array it
   got back on ``pong``. ``dora run`` starts the nodes with the first ``python`` on ``PATH``,
   so the benchmark puts this interpreter's ``bin`` first; ``DORA_ZENOH_MULTICAST=off``.
2. **raw zenoh-python through a router**: ``psm serve router`` on ``tcp/127.0.0.1:<port>``,
   ping and pong zenoh *clients* of it (multicast scouting off), express publishers with the
   control loop's QoS (real-time priority, blocking congestion control) as in
   :mod:`benchmarks.bus`'s raw path; pong's subscriber callback republishes the bytes it got
   (a 155-byte encoded ``ArmState``), ping's callback hands them to the waiting loop, which
   checks they are the ones it sent. Both callbacks run on zenoh's receive thread
   (``Callback(..., indirect=False)``), as the stack's control loop does, and that thread keeps
   its Python thread state (:func:`services.bus.runtime.receive_thread_handler`: without it
   zenoh-python creates and destroys one for every sample, and the pair does ~25 % fewer round
   trips a second here).
3. **the project's runtime through the same router**: :class:`services.bus.runtime.Service`
   clients; ping publishes a typed ``ArmState`` on ``<prefix>/arm/state``, pong's subscription
   (decode, type check) answers with an ``ArmCommand`` echoing the tick on
   ``<prefix>/arm/command``, ping's subscription decodes it and checks the tick. Both
   subscriptions take the control stream as the stack's control loop does (the arm its
   commands, the planner its states): ``"inline"`` delivery, on zenoh's receive thread
   (:data:`CONTROL_DELIVERY`; the runtime's default for control streams, a bounded channel and
   a worker thread, costs one thread wake-up more per message).
4. and 5. **raw zenoh-python and the runtime peer to peer** (``raw-p2p``, ``runtime-p2p``): the
   same two pairs, ping and pong zenoh *peers* that listen on ``tcp/127.0.0.1:0`` and connect to
   the same router, which tells each about the other (gossip scouting); they then link directly
   and their messages never pass the router, as between the processes of ``configs/stack.toml``.
   Each zenoh pair has its own key prefix (:func:`variant_prefix`).

Every ping is driven by the benchmark over a TCP control connection on 127.0.0.1 (outside the
timed loops): ``run N`` makes it do N round trips and answer with their count and elapsed
time. After a warm-up of each variant, the variants take turns in blocks of 300 round trips
(the order rotates every round), so machine load affects them alike. At the end each ping
writes its round-trip times to a JSON file that the benchmark reads.

Figures per variant: round trips/s = measured round trips / the sum of the blocks' elapsed
times (ping's clock, first send to last answer); RTT p50 / p99 / max over all measured round
trips; CPU per round trip = utime + stime from ``/proc/<pid>/stat`` of every process of the
variant (raw and runtime: router, ping, pong; dora: the ``dora run`` process and all its
descendants), read by the benchmark right before and after each block, summed over the blocks,
divided by the round trips (``/proc`` CPU times advance in clock ticks, 10 ms: the per-block
rounding averages out over the blocks). The router is shared by the two routed zenoh variants;
its CPU counts for the variant whose block is running (the peer-to-peer variants do not use it).
The CPU the idle variants' processes use while another variant's block runs is reported too (it
competes for the same 2 cores).

Target: project runtime p50 / dora-rs p50 ≤ 0.7, the runtime as the stack deploys it (peer to
peer; the routed ratio is reported beside it). Also reported: runtime p50 / raw zenoh p50,
and the figures measured earlier on this machine (dora-rs 2,740 round trips/s, p50 342 µs; raw
zenoh through a router 4,660/s, p50 191 µs) next to this run's.

Processes are started with :class:`services.supervisor.ManagedProcess` and stopped by PID
(``dora run`` gets SIGTERM and stops its nodes; node processes still alive after it are then
killed by PID). Every wait is bounded: per round trip (2 s), per block, per start-up, the whole
run, the child processes' own lifetime (``--max-seconds``) and ``dora run --stop-after``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchmarks.bus import _line, _pct, _spawn, _state_bytes
from services.supervisor import (
    SUPERVISOR_PID_ENV,
    ManagedProcess,
    cpu_seconds,
    free_port,
    psm_argv,
    wait_port,
)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

VARIANTS: tuple[str, ...] = ("dora", "raw", "runtime", "raw-p2p", "runtime-p2p")
#: The zenoh variants: (the pair's code, zenoh mode of ping and pong).
ZENOH_VARIANTS: dict[str, tuple[str, str]] = {
    "raw": ("raw", "client"), "runtime": ("runtime", "client"),
    "raw-p2p": ("raw", "peer"), "runtime-p2p": ("runtime", "peer"),
}
LABELS = {
    "dora": "dora-rs (`dora run`, 2 Python nodes)",
    "raw": "raw zenoh-python via router",
    "runtime": "project runtime via router",
    "raw-p2p": "raw zenoh-python peer to peer",
    "runtime-p2p": "project runtime peer to peer (as the stack runs)",
}
#: Target: project runtime p50 / dora-rs p50, the runtime as ``configs/stack.toml`` deploys it
#: (peers linked directly; the routed variant is reported beside it).
TARGET_RATIO = 0.7
#: Figures measured earlier on this machine (same pair), shown beside this run's.
REFERENCE = {
    "dora": {"round_trips_per_s": 2740.0, "p50_us": 342.0},
    "raw": {"round_trips_per_s": 4660.0, "p50_us": 191.0},
}
PER_BLOCK = 300
POOL = 1000  #: distinct pre-built messages per ping (tick modulo POOL)
RT_TIMEOUT_S = 2.0  #: one round trip
BLOCK_TIMEOUT_S = 60.0  #: one block (control reply)
STARTUP_TIMEOUT_S = 90.0
CHILD_MAX_S = 1800.0  #: a child process ends by itself after this long
DORA_FILLER = 19  #: int64 values after the tick in the dora payload (160 bytes in all)
PREFIX = "peers"


def variant_name(kind: str, mode: str) -> str:
    """The variant of the zenoh pair ``kind`` (raw, runtime) whose nodes run in zenoh ``mode``."""
    return kind if mode == "client" else f"{kind}-p2p"


def variant_prefix(variant: str) -> str:
    """The key prefix of a zenoh variant's pair (each pair has its own: they run side by side)."""
    return PREFIX + variant.replace("-", "")


# --------------------------------------------------------------------------------------------
# Pure parts: dataflow, statistics, ratios, verdict, report
# --------------------------------------------------------------------------------------------


def dataflow_yaml(control: str, out_file: str | Path, max_seconds: float = CHILD_MAX_S) -> str:
    """The dora dataflow of the pair: node ``ping`` (output ``ping``, input ``pong/pong``) and
    node ``pong`` (output ``pong``, input ``ping/ping``), both ``python -u -m benchmarks.peers
    --dora-node ...`` (``python``: the first on the ``PATH`` of ``dora run``)."""
    common = f"--max-seconds {max_seconds:g}"
    ping_args = f"-u -m benchmarks.peers --dora-node ping --control {control} --out-file {out_file} {common}"
    pong_args = f"-u -m benchmarks.peers --dora-node pong {common}"
    return (
        "# generated by benchmarks/peers.py: the lockstep ping/pong pair\n"
        "nodes:\n"
        "  - id: ping\n"
        "    path: python\n"
        f"    args: {json.dumps(ping_args)}\n"
        "    inputs:\n"
        "      pong: pong/pong\n"
        "    outputs:\n"
        "      - ping\n"
        "  - id: pong\n"
        "    path: python\n"
        f"    args: {json.dumps(pong_args)}\n"
        "    inputs:\n"
        "      ping: ping/ping\n"
        "    outputs:\n"
        "      - pong\n"
    )


def block_sizes(round_trips: int, per_block: int = PER_BLOCK) -> list[int]:
    """``round_trips`` split into blocks of ``per_block`` (the last one may be shorter)."""
    if round_trips < 1:
        raise ValueError(f"round trips must be >= 1, got {round_trips}")
    full, rest = divmod(round_trips, per_block)
    return [per_block] * full + ([rest] if rest else [])


def block_order(round_index: int, variants: Sequence[str] = VARIANTS) -> list[str]:
    """The variants' order in round ``round_index``: rotated by one every round."""
    k = round_index % len(variants)
    return [*variants[k:], *variants[:k]]


def summarize(rtt_us: Sequence[float], elapsed_s: float, cpu_s: dict[str, float],
              wrong_replies: int = 0) -> dict[str, Any]:
    """One variant's figures from its measured round trips: rate, RTT percentiles [µs] and CPU
    per round trip [µs] (total and per process; ``cpu_s``: CPU seconds by process)."""
    n = len(rtt_us)
    if n == 0 or elapsed_s <= 0:
        raise ValueError("no round trips to summarize")
    cpu_total = sum(cpu_s.values())
    return {
        "round_trips": n,
        "elapsed_s": elapsed_s,
        "round_trips_per_s": n / elapsed_s,
        "min_us": min(rtt_us),
        "mean_us": sum(rtt_us) / n,
        "p10_us": _pct(list(rtt_us), 10),
        "p50_us": _pct(list(rtt_us), 50),
        "p90_us": _pct(list(rtt_us), 90),
        "p99_us": _pct(list(rtt_us), 99),
        "p999_us": _pct(list(rtt_us), 99.9),
        "max_us": max(rtt_us),
        "cpu_s": cpu_total,
        "cpu_per_round_trip_us": cpu_total / n * 1e6,
        "cpu_per_round_trip_us_by_process": {k: v / n * 1e6 for k, v in cpu_s.items()},
        "wrong_replies": wrong_replies,
    }


def compare(variants: dict[str, dict[str, Any]], target: float = TARGET_RATIO) -> dict[str, Any]:
    """Ratios of the project runtime to dora-rs and to raw zenoh, and the target's verdict (on
    the runtime as the stack deploys it: peer to peer)."""
    rt, dora, raw = variants["runtime"], variants["dora"], variants["raw"]
    rt_p2p, raw_p2p = variants["runtime-p2p"], variants["raw-p2p"]
    ratio = rt_p2p["p50_us"] / dora["p50_us"]
    return {
        "runtime_p2p_over_dora_p50": ratio,
        "runtime_p2p_over_dora_p99": rt_p2p["p99_us"] / dora["p99_us"],
        "runtime_p2p_over_dora_cpu": rt_p2p["cpu_per_round_trip_us"] / dora["cpu_per_round_trip_us"],
        "runtime_p2p_over_dora_rate": rt_p2p["round_trips_per_s"] / dora["round_trips_per_s"],
        "runtime_p2p_over_raw_p2p_p50": rt_p2p["p50_us"] / raw_p2p["p50_us"],
        "runtime_p2p_over_raw_p2p_p99": rt_p2p["p99_us"] / raw_p2p["p99_us"],
        "runtime_p2p_over_raw_p2p_cpu": (rt_p2p["cpu_per_round_trip_us"]
                                         / raw_p2p["cpu_per_round_trip_us"]),
        "raw_p2p_over_dora_p50": raw_p2p["p50_us"] / dora["p50_us"],
        "runtime_over_dora_p50": rt["p50_us"] / dora["p50_us"],
        "runtime_over_dora_p99": rt["p99_us"] / dora["p99_us"],
        "runtime_over_dora_cpu": rt["cpu_per_round_trip_us"] / dora["cpu_per_round_trip_us"],
        "runtime_over_dora_rate": rt["round_trips_per_s"] / dora["round_trips_per_s"],
        "runtime_over_raw_p50": rt["p50_us"] / raw["p50_us"],
        "runtime_over_raw_p99": rt["p99_us"] / raw["p99_us"],
        "runtime_over_raw_cpu": rt["cpu_per_round_trip_us"] / raw["cpu_per_round_trip_us"],
        "raw_over_dora_p50": raw["p50_us"] / dora["p50_us"],
        "target_runtime_over_dora_p50": target,
        "met": bool(ratio <= target),
    }


def verdict_text(cmp: dict[str, Any]) -> str:
    """One plain sentence: the target, the measured ratio, met or not met."""
    word = "met" if cmp["met"] else "NOT met"
    return (f"Target project runtime p50 / dora-rs p50 ≤ {cmp['target_runtime_over_dora_p50']:.2f}×, "
            f"the runtime as the stack deploys it (peer to peer): measured "
            f"{cmp['runtime_p2p_over_dora_p50']:.2f}× — **{word}** (through the router: "
            f"{cmp['runtime_over_dora_p50']:.2f}×).")


def _f(v: float, nd: int = 0) -> str:
    return f"{v:,.{nd}f}"


def render_markdown(res: dict[str, Any]) -> str:
    """The markdown report of one run (``res`` as :func:`run` returns it)."""
    v = res["variants"]
    cmp = res["comparison"]
    p = res["params"]
    lines = [
        "# Peer benchmark: trivial two-node lockstep pair — dora-rs vs raw zenoh-python vs the "
        "project runtime",
        "",
        f"Measured {res['date_utc']} on {res['machine']} ({res['cpus']} CPUs, shared; load "
        f"average at start {res['load_avg_start']}, at end {res['load_avg_end']}; all CPUs "
        f"{res['machine_busy_pct_before']:.0f} % busy in the 2 s before the run, "
        f"{res['machine_busy_pct_during']:.0f} % during it, this benchmark included); python "
        f"{res['python']}, dora-rs {res['versions']['dora-rs']} / dora-rs-cli "
        f"{res['versions']['dora-rs-cli']}, pyarrow {res['versions']['pyarrow']}, zenoh "
        f"{res['versions']['eclipse-zenoh']}. Produced by `python -m benchmarks.peers`; method "
        "in the module docstring.",
        "",
        "Ping sends a small message, pong answers at once, ping sends the next only after the "
        "answer. All five variants run in the same run, in alternating blocks of "
        f"{p['per_block']} round trips (order rotating) after a warm-up of {p['warmup']} each; "
        f"{p['round_trips']} measured round trips per variant. CPU = utime + stime from "
        "`/proc/<pid>/stat` of every process of the variant over the blocks.",
        "",
        "| variant | processes counted | round trips/s | RTT p50 (µs) | p99 (µs) | max (µs) "
        "| CPU per round trip (µs) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for name in VARIANTS:
        s = v[name]
        procs = ", ".join(s["processes"])
        lines.append(
            f"| {LABELS[name]} | {procs} | {_f(s['round_trips_per_s'])} | {_f(s['p50_us'])} | "
            f"{_f(s['p99_us'])} | {_f(s['max_us'])} | {_f(s['cpu_per_round_trip_us'])} |")
    lines += [
        "",
        "| ratio | p50 | p99 | CPU per round trip | round trips/s |",
        "|---|---:|---:|---:|---:|",
        f"| **project runtime peer to peer / dora-rs** | **{cmp['runtime_p2p_over_dora_p50']:.2f}×** | "
        f"{cmp['runtime_p2p_over_dora_p99']:.2f}× | {cmp['runtime_p2p_over_dora_cpu']:.2f}× | "
        f"{cmp['runtime_p2p_over_dora_rate']:.2f}× |",
        f"| project runtime peer to peer / raw zenoh peer to peer | "
        f"{cmp['runtime_p2p_over_raw_p2p_p50']:.2f}× | {cmp['runtime_p2p_over_raw_p2p_p99']:.2f}× | "
        f"{cmp['runtime_p2p_over_raw_p2p_cpu']:.2f}× | "
        f"{v['runtime-p2p']['round_trips_per_s'] / v['raw-p2p']['round_trips_per_s']:.2f}× |",
        f"| raw zenoh peer to peer / dora-rs | {cmp['raw_p2p_over_dora_p50']:.2f}× | "
        f"{v['raw-p2p']['p99_us'] / v['dora']['p99_us']:.2f}× | "
        f"{v['raw-p2p']['cpu_per_round_trip_us'] / v['dora']['cpu_per_round_trip_us']:.2f}× | "
        f"{v['raw-p2p']['round_trips_per_s'] / v['dora']['round_trips_per_s']:.2f}× |",
        f"| project runtime via router / dora-rs | {cmp['runtime_over_dora_p50']:.2f}× | "
        f"{cmp['runtime_over_dora_p99']:.2f}× | {cmp['runtime_over_dora_cpu']:.2f}× | "
        f"{cmp['runtime_over_dora_rate']:.2f}× |",
        f"| project runtime / raw zenoh, both via router | {cmp['runtime_over_raw_p50']:.2f}× | "
        f"{cmp['runtime_over_raw_p99']:.2f}× | {cmp['runtime_over_raw_cpu']:.2f}× | "
        f"{v['runtime']['round_trips_per_s'] / v['raw']['round_trips_per_s']:.2f}× |",
        f"| raw zenoh via router / dora-rs | {cmp['raw_over_dora_p50']:.2f}× | "
        f"{v['raw']['p99_us'] / v['dora']['p99_us']:.2f}× | "
        f"{v['raw']['cpu_per_round_trip_us'] / v['dora']['cpu_per_round_trip_us']:.2f}× | "
        f"{v['raw']['round_trips_per_s'] / v['dora']['round_trips_per_s']:.2f}× |",
        "",
        verdict_text(cmp),
        "",
        "Replies that were not the answer to the message just sent: "
        + ", ".join(f"{n} {v[n]['wrong_replies']}" for n in VARIANTS) + ".",
        "",
        "While one variant's block ran, the processes of the others (idle, waiting for their "
        "turn) used "
        + ", ".join(f"{v[n]['other_variants_cpu_pct_during_blocks']:.1f} % of one core during "
                    f"{n}'s blocks" for n in VARIANTS)
        + " (`/proc` CPU times advance in clock ticks of 10 ms; summed over all blocks).",
        "",
        "## CPU per round trip by process (µs)",
        "",
        "| variant | process | CPU per round trip (µs) |",
        "|---|---|---:|",
    ]
    for name in VARIANTS:
        for proc, us in v[name]["cpu_per_round_trip_us_by_process"].items():
            lines.append(f"| {name} | {proc} | {us:.1f} |")
    lines += [
        "",
        "## Against the figures measured earlier on this machine",
        "",
        "| variant | earlier round trips/s | this run | earlier p50 (µs) | this run |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, ref in REFERENCE.items():
        lines.append(f"| {LABELS[name]} | {_f(ref['round_trips_per_s'])} | "
                     f"{_f(v[name]['round_trips_per_s'])} | {_f(ref['p50_us'])} | "
                     f"{_f(v[name]['p50_us'])} |")
    lines += [
        "",
        "## Setup",
        "",
        "- dora-rs: `dora run dataflow.yml` (no `dora up`, no coordinator: the daemon runs inside "
        "the `dora run` process); nodes `python -u -m benchmarks.peers --dora-node ping|pong` "
        f"started by dora; payload a pyarrow int64 array of {1 + DORA_FILLER} values "
        f"({8 * (1 + DORA_FILLER)} bytes); `DORA_ZENOH_MULTICAST=off`. Processes seen: "
        + "; ".join(res.get("dora_processes", [])) + ".",
        "- raw zenoh: `psm serve router` on 127.0.0.1, ping and pong zenoh clients (multicast "
        "off), express publishers, real-time priority, blocking congestion control; 155-byte "
        "ArmState bytes echoed by pong's callback; callbacks on zenoh's receive thread.",
        "- project runtime: `Service` clients of the same router; typed `ArmState` on "
        "`<prefix>/arm/state`, answered by an `ArmCommand` echoing the tick on "
        f"`<prefix>/arm/command`; `{CONTROL_DELIVERY}` delivery (on zenoh's receive thread), as the "
        "stack's arm and planner take the control stream.",
        "- peer to peer (`-p2p`): the same two pairs with ping and pong zenoh peers that listen "
        "on 127.0.0.1 and connect to the same router, which tells each about the other "
        "(gossip): their messages then go directly from one to the other, as between the "
        "processes of `configs/stack.toml`. The router carries no message of theirs, and its "
        "CPU is not counted for them.",
        "- each zenoh pair has its own keys (prefix "
        + ", ".join(f"`{variant_prefix(n)}`" for n in ZENOH_VARIANTS) + ").",
        "",
    ]
    return "\n".join(lines)


def write_report(res: dict[str, Any], out: Path = RESULTS) -> None:
    """Write ``peers.json`` and ``peers.md`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "peers.json").write_text(json.dumps(res, indent=2) + "\n")
    (out / "peers.md").write_text(render_markdown(res))


# --------------------------------------------------------------------------------------------
# Processes
# --------------------------------------------------------------------------------------------


def _parent_pid(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            return int(fh.read().rsplit(b")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def descendants(pid: int) -> list[int]:
    """The PIDs of every live descendant of ``pid`` (from ``/proc``)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            ppid = _parent_pid(int(entry))
            if ppid is not None:
                children.setdefault(ppid, []).append(int(entry))
    out: list[int] = []
    todo = list(children.get(pid, []))
    while todo and len(out) < 10_000:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return sorted(out)


def _cpu_of(pids: Sequence[int]) -> dict[int, float]:
    """CPU seconds (utime + stime) of each of ``pids``; raises if one is gone."""
    out = {}
    for pid in pids:
        c = cpu_seconds(pid)
        if c is None:
            raise RuntimeError(f"process {pid} ({_cmdline(pid)}) is gone")
        out[pid] = c
    return out


def _cpu_times() -> tuple[int, int]:
    """(busy, total) jiffies of all CPUs from ``/proc/stat``."""
    with open("/proc/stat") as fh:
        vals = [int(x) for x in fh.readline().split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)  # idle + iowait
    return sum(vals) - idle, sum(vals)


def machine_busy_pct(seconds: float = 1.0) -> float:
    """How busy the whole machine is over ``seconds``, % of all CPUs (other people's jobs
    included): the context for the figures of a run on a shared machine."""
    b0, t0 = _cpu_times()
    time.sleep(seconds)
    b1, t1 = _cpu_times()
    return 100.0 * (b1 - b0) / max(1, t1 - t0)


def _cmdline(pid: int) -> str:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return "?"
    return " ".join(a.decode(errors="replace") for a in raw.split(b"\0") if a)


def _dora_name(pid: int, root: int) -> str:
    """A short name for a process of the ``dora run`` tree."""
    if pid == root:
        return "dora run (daemon)"
    cmd = _cmdline(pid)
    for role in ("ping", "pong"):
        if f"--dora-node {role}" in cmd:
            return f"{role} node"
    return f"pid {pid}: {cmd[:60]}"


def _wait_port(port: int, timeout_s: float, proc: ManagedProcess) -> None:
    wait_port(port, timeout_s, proc)


def _wait_terminated(max_s: float) -> None:
    """Block until SIGTERM or SIGINT, at most ``max_s``."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait(max_s)


def _bus_cfg(endpoint: str, mode: str, prefix: str) -> Any:
    """Service config of a zenoh ``mode`` session (client, or peer listening on 127.0.0.1) that
    connects to the router at ``endpoint``, multicast off."""
    from services.bus.config import ServiceConfig, load_config

    listen = ["tcp/127.0.0.1:0"] if mode == "peer" else []
    return load_config(ServiceConfig, env={}, overrides={
        "zenoh.mode": mode, "zenoh.connect": [endpoint], "zenoh.listen": listen,
        "zenoh.multicast": False, "prefix": prefix, "log_level": "WARNING"})


#: The runtime's delivery of the control stream, as the stack's control loop takes it: the arm
#: (commands) and the planner (states) handle it on zenoh's receive thread.
CONTROL_DELIVERY = "inline"


def _on_receive_thread(callback: Callable[[Any], None]) -> Any:
    """A raw zenoh subscriber's handler that runs ``callback`` on zenoh's receive thread (as
    :data:`CONTROL_DELIVERY`; a bare callable would get a Python callback thread of its own),
    the thread keeping its Python thread state as the runtime's does."""
    from services.bus.runtime import receive_thread_handler

    return receive_thread_handler(callback)


def _express(session: Any, key: str) -> Any:
    import zenoh

    return session.declare_publisher(key, express=True, priority=zenoh.Priority.REAL_TIME,
                                     congestion_control=zenoh.CongestionControl.BLOCK)


# --------------------------------------------------------------------------------------------
# The ping side: one control loop, three ways of doing one round trip
# --------------------------------------------------------------------------------------------


RoundTrip = Callable[[int], bool]  #: one lockstep round trip of tick k; True if the answer matched


def _ping_loop(variant: str, control: str, out_file: Path, one: RoundTrip,
               max_seconds: float) -> int:
    """Connect to the benchmark at ``control``, run the blocks it asks for, write the recorded
    round-trip times to ``out_file`` at ``quit``. Bounded: idle timeout, ``max_seconds``."""
    host, port = control.rsplit(":", 1)
    sock = socket.create_connection((host, int(port)), timeout=30)
    sock.settimeout(max_seconds)
    f = sock.makefile("rwb")
    f.write(f"hello {variant} {os.getpid()}\n".encode())
    f.flush()
    rtt_us: list[float] = []
    blocks: list[dict[str, Any]] = []
    tick = 0
    deadline = time.monotonic() + max_seconds
    while time.monotonic() < deadline:
        words = f.readline().decode().split()
        if not words or words[0] == "quit":
            break
        n, record = int(words[1]), words[2] == "1"
        out: list[float] = []
        bad = 0
        try:
            t_start = time.perf_counter_ns()
            for _ in range(n):
                t0 = time.perf_counter_ns()
                ok = one(tick)
                out.append((time.perf_counter_ns() - t0) / 1e3)
                bad += not ok
                tick += 1
            elapsed = time.perf_counter_ns() - t_start
        except Exception as exc:  # reported to the benchmark, which stops the run
            f.write(f"error {type(exc).__name__}: {exc}\n".encode())
            f.flush()
            return 1
        if record:
            rtt_us += out
            blocks.append({"n": n, "elapsed_ns": elapsed, "wrong": bad})
        f.write(f"done {n} {elapsed} {bad}\n".encode())
        f.flush()
    out_file.write_text(json.dumps({"variant": variant, "rtt_us": rtt_us, "blocks": blocks}))
    with contextlib.suppress(OSError):
        f.write(b"bye\n")
        f.flush()
    sock.close()
    return 0


def _dora_ping(control: str, out_file: Path, max_seconds: float) -> int:
    import pyarrow as pa
    from dora import Node

    node = Node()
    filler = [0] * DORA_FILLER
    pool = [pa.array([i, *filler], type=pa.int64()) for i in range(POOL)]

    def one(k: int) -> bool:
        node.send_output("ping", pool[k % POOL])
        deadline = time.monotonic() + RT_TIMEOUT_S
        while True:
            ev = node.next(timeout=RT_TIMEOUT_S)
            if ev is None:
                raise RuntimeError("dora event stream closed")
            if ev["type"] == "INPUT" and ev["id"] == "pong":
                return bool(ev["value"][0].as_py() == k % POOL)
            if ev["type"] in ("STOP", "ERROR") or time.monotonic() > deadline:
                raise RuntimeError(f"no answer from pong: {ev['type']} {ev.get('error', '')}")

    return _ping_loop("dora", control, out_file, one, max_seconds)


def _dora_pong(max_seconds: float) -> int:
    from dora import Node

    node = Node()
    deadline = time.monotonic() + max_seconds
    while time.monotonic() < deadline:
        ev = node.next(timeout=1.0)
        if ev is None or ev["type"] == "STOP":
            break
        if ev["type"] == "INPUT":
            node.send_output("pong", ev["value"])
    return 0


def _raw_ping(endpoint: str, mode: str, control: str, out_file: Path, max_seconds: float) -> int:
    from services.bus.runtime import open_session

    variant = variant_name("raw", mode)
    prefix = variant_prefix(variant)
    session = open_session(_bus_cfg(endpoint, mode, prefix).zenoh)
    pub = _express(session, f"{prefix}/ping")
    event = threading.Event()
    reply: list[bytes] = [b""]

    def on_pong(sample: Any) -> None:
        reply[0] = sample.payload.to_bytes()
        event.set()

    sub = session.declare_subscriber(f"{prefix}/pong", _on_receive_thread(on_pong))
    _wait_for(lambda: bool(pub.matching_status.matching), "raw pong")
    time.sleep(0.3)
    pool = [_state_bytes(i) for i in range(POOL)]

    def one(k: int) -> bool:
        event.clear()
        payload = pool[k % POOL]
        pub.put(payload)
        if not event.wait(RT_TIMEOUT_S):
            raise RuntimeError("raw pong timed out")
        return reply[0] == payload

    try:
        return _ping_loop(variant, control, out_file, one, max_seconds)
    finally:
        sub.undeclare()
        pub.undeclare()
        session.close()


def _raw_pong(endpoint: str, mode: str, max_seconds: float) -> int:
    from services.bus.runtime import open_session

    prefix = variant_prefix(variant_name("raw", mode))
    session = open_session(_bus_cfg(endpoint, mode, prefix).zenoh)
    pub = _express(session, f"{prefix}/pong")
    sub = session.declare_subscriber(f"{prefix}/ping", _on_receive_thread(lambda s: pub.put(s.payload)))
    print("ready", flush=True)
    _wait_terminated(max_seconds)
    sub.undeclare()
    session.close()
    return 0


def _runtime_ping(endpoint: str, mode: str, control: str, out_file: Path, max_seconds: float) -> int:
    from services.bus.messages import ArmCommand, ArmState
    from services.bus.runtime import Service

    variant = variant_name("runtime", mode)
    svc = Service("ping", _bus_cfg(endpoint, mode, variant_prefix(variant))).start()
    event = threading.Event()
    expected = [-1]
    matched = [False]

    def on_cmd(cmd: ArmCommand, _key: str) -> None:
        matched[0] = cmd.tick == expected[0]
        event.set()

    pub = svc.publisher(svc.keys.arm_state)
    svc.subscribe(svc.keys.arm_command, on_cmd, delivery=CONTROL_DELIVERY)
    _wait_for(lambda: bool(pub.has_subscribers), "runtime pong")
    time.sleep(0.3)
    pool = [ArmState.FromString(_state_bytes(i)) for i in range(POOL)]

    def one(k: int) -> bool:
        event.clear()
        st = pool[k % POOL]
        expected[0] = st.tick
        pub.put(st)
        if not event.wait(RT_TIMEOUT_S):
            raise RuntimeError("runtime pong timed out")
        return matched[0]

    try:
        return _ping_loop(variant, control, out_file, one, max_seconds)
    finally:
        svc.close()


def _runtime_pong(endpoint: str, mode: str, max_seconds: float) -> int:
    from services.bus.messages import ArmCommand, ArmState
    from services.bus.runtime import Service

    svc = Service("pong", _bus_cfg(endpoint, mode, variant_prefix(variant_name("runtime", mode)))).start()
    cmd = svc.publisher(svc.keys.arm_command)

    def on_state(state: ArmState, _key: str) -> None:
        cmd.put(ArmCommand(stamp_ns=state.stamp_ns, tick=state.tick,
                           mode=ArmCommand.CARTESIAN_ACCELERATION, source="pong"))

    svc.subscribe(svc.keys.arm_state, on_state, delivery=CONTROL_DELIVERY)
    print("ready", flush=True)
    _wait_terminated(max_seconds)
    svc.close()
    return 0


def _wait_for(cond: Callable[[], bool], what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.01)
    raise RuntimeError(f"{what} not matched within {timeout_s:.0f} s")


# --------------------------------------------------------------------------------------------
# The benchmark
# --------------------------------------------------------------------------------------------


class _Ping:
    """The benchmark's end of one ping's control connection."""

    def __init__(self, conn: socket.socket) -> None:
        self.conn = conn
        self.f = conn.makefile("rwb")
        hello = self.f.readline().decode().split()  # "hello <variant> <pid>"
        ok = len(hello) == 3 and hello[0] == "hello" and hello[1] in VARIANTS
        self.variant = hello[1] if ok else ""
        self.pid = int(hello[2]) if ok else 0

    def ask(self, line: str, timeout_s: float = BLOCK_TIMEOUT_S) -> list[str]:
        self.conn.settimeout(timeout_s)
        self.f.write(line.encode() + b"\n")
        self.f.flush()
        words = self.f.readline().decode().split()
        if not words or words[0] == "error":
            raise RuntimeError(f"{self.variant} ping: {' '.join(words) or 'connection closed'}")
        return words

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.f.close()
            self.conn.close()


def _dora_exe() -> str:
    bin_dir = str(Path(sys.executable).parent)
    exe = shutil.which("dora", path=bin_dir + os.pathsep + os.environ.get("PATH", ""))
    if exe is None:
        raise RuntimeError("the dora CLI is not installed (pip install 'psm-dataflow[bench]': "
                           "dora-rs-cli and dora-rs 1.1)")
    return exe


def _start_dora(workdir: Path, control: str, max_seconds: float) -> ManagedProcess:
    """Write the dataflow into ``workdir`` and start ``dora run`` on it."""
    exe = _dora_exe()
    flow = workdir / "dataflow.yml"
    flow.write_text(dataflow_yaml(control, workdir / "dora-ping.json", max_seconds))
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["DORA_ZENOH_MULTICAST"] = "off"
    env.pop(SUPERVISOR_PID_ENV, None)  # the nodes' parent is dora, not this process
    return ManagedProcess("dora", [exe, "run", str(flow), "--stop-after", f"{int(max_seconds)}s",
                                   "--log-level", "info"],
                          workdir / "dora.log", env=env, cwd=workdir)


def _stop_dora(proc: ManagedProcess, nodes: Sequence[int]) -> None:
    """``dora run`` ends by itself once ping has quit (pong's input closes); else SIGTERM.
    Node processes (their own process groups) still alive afterwards are killed by PID."""
    if proc.wait(20) is None:
        proc.stop(15)
    else:
        proc.stop(1)
    for pid in nodes:
        if _parent_pid(pid) is not None and "--dora-node" in _cmdline(pid):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)


def run(round_trips: int, warmup: int, per_block: int = PER_BLOCK,
        max_run_s: float = 900.0) -> dict[str, Any]:
    """Start the three pairs, measure them in alternating blocks, stop everything; returns the
    per-variant figures, per-block data and the comparison."""
    sizes = block_sizes(round_trips, per_block)
    t_run = time.monotonic()
    child_max = max_run_s + 120.0
    with tempfile.TemporaryDirectory(prefix="peers-") as tmp:
        workdir = Path(tmp)
        listener = socket.create_server(("127.0.0.1", 0))
        listener.settimeout(STARTUP_TIMEOUT_S)
        control = f"127.0.0.1:{listener.getsockname()[1]}"
        port = free_port()
        ep = f"tcp/127.0.0.1:{port}"
        procs: dict[str, ManagedProcess] = {}
        pings: dict[str, _Ping] = {}
        dora_nodes: list[int] = []
        try:
            procs["router"] = ManagedProcess(
                "router", psm_argv(["serve", "router", "--listen", ep, "--no-multicast",
                                    "--log-level", "WARNING"]), workdir / "router.log")
            _wait_port(port, 30, procs["router"])
            mx = ["--max-seconds", str(child_max)]
            for v, (kind, mode) in ZENOH_VARIANTS.items():
                procs[f"{v}-pong"] = _spawn(workdir, f"{v}-pong", "-m", "benchmarks.peers", "--role",
                                            f"{kind}-pong", "--mode", mode, "--endpoint", ep, *mx)
                _line(procs[f"{v}-pong"], "ready", 60)
                procs[f"{v}-ping"] = _spawn(
                    workdir, f"{v}-ping", "-m", "benchmarks.peers", "--role", f"{kind}-ping",
                    "--mode", mode, "--endpoint", ep, "--control", control,
                    "--out-file", str(workdir / f"{v}-ping.json"), *mx)
            procs["dora"] = _start_dora(workdir, control, child_max)
            deadline = time.monotonic() + STARTUP_TIMEOUT_S
            while len(pings) < len(VARIANTS) and time.monotonic() < deadline:
                for name, p in procs.items():
                    if not p.alive():
                        raise RuntimeError(f"{name} exited at start: {p.log_tail()}")
                with contextlib.suppress(TimeoutError):
                    listener.settimeout(1.0)
                    conn, _ = listener.accept()
                    conn.settimeout(30)
                    ping = _Ping(conn)
                    if ping.variant:
                        pings[ping.variant] = ping
                    else:
                        ping.close()
            if len(pings) < len(VARIANTS):
                missing = sorted(set(VARIANTS) - set(pings))
                tails = "\n".join(f"--- {n}\n{p.log_tail()}" for n, p in procs.items())
                raise RuntimeError(f"pings not connected: {missing}\n{tails}")
            dora_nodes = descendants(procs["dora"].pid)
            pids: dict[str, dict[str, int]] = {
                "dora": {"dora run (daemon)": procs["dora"].pid,
                         **{_dora_name(p, procs["dora"].pid): p for p in dora_nodes}},
                **{v: {"router": procs["router"].pid, "ping": procs[f"{v}-ping"].pid,
                       "pong": procs[f"{v}-pong"].pid} for v in ("raw", "runtime")},
                **{v: {"ping": procs[f"{v}-ping"].pid, "pong": procs[f"{v}-pong"].pid}
                   for v in ("raw-p2p", "runtime-p2p")},
            }
            if pings["dora"].pid not in dora_nodes:
                raise RuntimeError(f"dora ping {pings['dora'].pid} is not a child of dora run")
            every = sorted({pid for v in VARIANTS for pid in pids[v].values()})
            # warm-up
            for v in VARIANTS:
                pings[v].ask(f"run {warmup} 0")
            cpu: dict[str, dict[str, float]] = {v: dict.fromkeys(pids[v], 0.0) for v in VARIANTS}
            blocks: dict[str, list[dict[str, Any]]] = {v: [] for v in VARIANTS}
            for r, n in enumerate(sizes):
                if time.monotonic() - t_run > max_run_s:
                    raise RuntimeError(f"run took longer than {max_run_s:.0f} s")
                for v in block_order(r):
                    w0 = time.monotonic()
                    before = _cpu_of(every)
                    words = pings[v].ask(f"run {n} 1")
                    after = _cpu_of(every)
                    wall = time.monotonic() - w0
                    mine = {pids[v][k] for k in pids[v]}
                    for k, pid in pids[v].items():
                        cpu[v][k] += after[pid] - before[pid]
                    others = sum(after[p] - before[p] for p in every if p not in mine)
                    blocks[v].append({
                        "n": int(words[1]), "elapsed_ns": int(words[2]), "wrong": int(words[3]),
                        "cpu_s": sum(after[p] - before[p] for p in mine),
                        "wall_s": wall, "other_variants_cpu_s": others})
            late = sorted(set(descendants(procs["dora"].pid)) - set(dora_nodes))
            for v in VARIANTS:
                pings[v].ask("quit", 30)
            samples = {}
            for v in VARIANTS:
                path = workdir / f"{v}-ping.json"
                deadline = time.monotonic() + 20
                while not path.exists() and time.monotonic() < deadline:
                    time.sleep(0.05)
                samples[v] = json.loads(path.read_text())
        finally:
            for p in pings.values():
                p.close()
            listener.close()
            for name in [f"{v}-{r}" for r in ("ping", "pong") for v in ZENOH_VARIANTS]:
                if name in procs:
                    if procs[name].wait(5) is None:
                        procs[name].stop(10)
                    else:
                        procs[name].stop(1)
            if "dora" in procs:
                _stop_dora(procs["dora"], dora_nodes)
            if "router" in procs:
                procs["router"].stop(10)
    variants = {}
    for v in VARIANTS:
        rtt = samples[v]["rtt_us"]
        elapsed = sum(b["elapsed_ns"] for b in blocks[v]) / 1e9
        s = summarize(rtt, elapsed, cpu[v], sum(b["wrong"] for b in blocks[v]))
        s["processes"] = list(pids[v])
        s["blocks"] = blocks[v]
        wall = sum(b["wall_s"] for b in blocks[v])
        s["other_variants_cpu_pct_during_blocks"] = (
            100.0 * sum(b["other_variants_cpu_s"] for b in blocks[v]) / wall)
        variants[v] = s
    dora_procs = [f"{name} (pid {pid}): {_cmdline_short(name)}" for name, pid in pids["dora"].items()]
    return {"variants": variants, "comparison": compare(variants), "dora_processes": dora_procs,
            "dora_processes_started_later": late, "wall_s": time.monotonic() - t_run}


def _cmdline_short(name: str) -> str:
    if name.startswith("dora run"):
        return "`dora run dataflow.yml` (daemon in-process)"
    if name.endswith("node"):
        return f"`python -u -m benchmarks.peers --dora-node {name.split()[0]}`"
    return name


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("dora-rs", "dora-rs-cli", "pyarrow", "eclipse-zenoh"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write the report (or be one of its child roles)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short smoke run")
    ap.add_argument("--round-trips", type=int, default=None,
                    help="measured round trips per variant (default 15000; --quick 1500)")
    ap.add_argument("--warmup", type=int, default=None, help="warm-up round trips per variant")
    ap.add_argument("--out", type=Path, default=RESULTS, help="where the report goes")
    ap.add_argument("--no-write", action="store_true", help="print the figures, write nothing")
    ap.add_argument("--dora-node", choices=("ping", "pong"), help=argparse.SUPPRESS)
    ap.add_argument("--role", choices=("raw-ping", "raw-pong", "runtime-ping", "runtime-pong"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--mode", choices=("client", "peer"), default="client", help=argparse.SUPPRESS)
    ap.add_argument("--control", help=argparse.SUPPRESS)
    ap.add_argument("--out-file", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--max-seconds", type=float, default=CHILD_MAX_S, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    mx = args.max_seconds
    if args.dora_node == "ping":
        return _dora_ping(args.control, args.out_file, mx)
    if args.dora_node == "pong":
        return _dora_pong(mx)
    if args.role == "raw-ping":
        return _raw_ping(args.endpoint, args.mode, args.control, args.out_file, mx)
    if args.role == "raw-pong":
        return _raw_pong(args.endpoint, args.mode, mx)
    if args.role == "runtime-ping":
        return _runtime_ping(args.endpoint, args.mode, args.control, args.out_file, mx)
    if args.role == "runtime-pong":
        return _runtime_pong(args.endpoint, args.mode, mx)

    round_trips = args.round_trips or (1500 if args.quick else 15000)
    warmup = args.warmup if args.warmup is not None else (300 if args.quick else 1000)
    res: dict[str, Any] = {
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": platform.machine(), "cpus": os.cpu_count(),
        "load_avg_start": ", ".join(f"{v:.2f}" for v in os.getloadavg()),
        "machine_busy_pct_before": round(machine_busy_pct(2.0), 1),
        "python": platform.python_version(), "versions": _versions(),
        "params": {"round_trips": round_trips, "warmup": warmup, "per_block": PER_BLOCK,
                   "blocks": len(block_sizes(round_trips)), "quick": bool(args.quick),
                   "round_trip_timeout_s": RT_TIMEOUT_S},
        "reference": REFERENCE,
    }
    print(f"peers: {round_trips} round trips per variant after {warmup} warm-up ...", flush=True)
    busy0 = _cpu_times()
    res.update(run(round_trips, warmup))
    busy1 = _cpu_times()
    res["machine_busy_pct_during"] = round(
        100.0 * (busy1[0] - busy0[0]) / max(1, busy1[1] - busy0[1]), 1)
    res["load_avg_end"] = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    for v in VARIANTS:
        s = res["variants"][v]
        print(f"{v:12s} {s['round_trips_per_s']:8.0f} rt/s  p50 {s['p50_us']:6.0f} µs  p99 "
              f"{s['p99_us']:6.0f} µs  max {s['max_us']:7.0f} µs  cpu/rt "
              f"{s['cpu_per_round_trip_us']:5.0f} µs", flush=True)
    print(verdict_text(res["comparison"]).replace("**", ""), flush=True)
    if not args.no_write:
        write_report(res, args.out)
        print(f"wrote {args.out / 'peers.md'}", flush=True)
    return 0 if all(math.isfinite(res["variants"][v]["p50_us"]) for v in VARIANTS) else 1


if __name__ == "__main__":
    sys.exit(main())
