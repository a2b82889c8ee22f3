"""Planner benchmark: the cost of one planner tick, the closed loop arm <-> real planner in
lockstep and at 500 Hz, and the CPU of the whole feeding stack.

Run ``python -m benchmarks.planner`` (``--quick``: fewer repetitions and round trips; the task
runs are the same). Writes ``benchmarks/results/planner.md`` and ``benchmarks/results/planner.json``.

a. **Tick cost, in process** (no bus). A real state stream is recorded first: the planner
   service itself (:class:`services.planner.service.PlannerService`, built from a
   :class:`~services.planner.config.PlannerConfig` with the shipped ``configs/feeding.toml``;
   its bus parts replaced by a fake service — counters, ``record_rejection``, ``log`` — and a
   publisher that keeps the bytes) answers every state of the simulated arm
   (:class:`services.arm.sim.ArmSim` as configured in ``configs/stack.toml``, states encoded
   with the arm's :class:`services.robot.protocol.StateEncoder`, commands decoded and applied as
   the arm does), with a static person goal offered as a ``Goal`` at 30 Hz of sim time, through
   the whole feeding task and the planner's linger. The recorded stream (state bytes and goals)
   is then replayed into fresh services: the replay reproduces every command byte for byte
   (checked). **Total** = the service's own Zenoh callback ``PlannerService._on_state`` (decode,
   checks, ``TaskRunner.step``, encode, ``put`` into the fake publisher, latency bookkeeping)
   timed around each call, in ``--reps`` replays without instrumentation. **Parts** come from
   one more replay that performs the same steps as ``_on_state`` one by one: decode
   (``ParseFromString`` into the reused message), ``PlannerService._answer`` (checks, copies,
   ``TaskRunner.step``, encode), within it ``TaskRunner.step`` (timed by a wrapper), within that
   the PSM controller (``PSMController.step``) and the orientation reference
   (``TaskRunner._orientation``), and the command encode (the same ``SerializeToString`` of the
   command just built, timed again right after). Wrappers add well under a microsecond a call;
   the total is from the uninstrumented replays. **Cold**: ``--reps`` more replays in which
   64 MiB are written (one write per cache line) before every 7th call, and only those calls
   timed: the tick with its caches cold, as in the closed loop, where the arm's process runs
   between two states.
b. **Closed loop, lockstep.** ``psm serve router``, ``psm plan`` and ``psm arm`` as separate
   processes (``services.supervisor.ManagedProcess``, ``psm_argv``: the code of this checkout),
   all reading one stack file written by :func:`bench_stack_file` with the arm's and planner's
   fields of ``configs/stack.toml`` (500 Hz, start pose, ``rt_priority``, ``watch_services``)
   on a fresh loopback port, with the stack file's bus topology
   (:func:`benchmarks.stack.zenoh_table`: peers that find each other through the router and
   link directly), multicast off. No camera and no goal
   tracker: the planner runs a copy of ``configs/feeding.toml`` whose live ``person`` step is
   made static (``live = false``: the goal is ``scene.person``; :func:`static_person_task`), so
   the task is the same five steps without a goal source. The planner starts first (its
   liveliness token seen), then the arm, so no tick waits for the planner. The arm's rate is
   measured over a window from the planner's ``PlannerStatus`` (20 Hz: the tick it answered
   last, received by this process): from 0.5 s after the task started to the last status before
   it was done; the arm's ``stats_file`` gives its whole-loop counts and the state→command
   latency. The bound: raw zenoh-python ping-pong (``benchmarks.peers``'s raw ping and pong,
   express publishers, 155-byte ArmState bytes, callbacks on zenoh's receive thread keeping
   their Python thread state as the arm's and the planner's do) on **the same router process**, in the same
   topology as the arm and the planner (peers linked directly), once before the task run and
   once after it: 1 / round-trip p50. Target: arm ticks/s ≥ 0.5× the bound.
c. **Closed loop, realtime 500 Hz.** The same processes with ``clock = "realtime"`` (arm and
   planner at ``SCHED_FIFO`` ``rt_priority`` of ``configs/stack.toml``). A bare timer loop
   (:func:`benchmarks.arm.bench_timer`, 2 ms deadlines with ``time.sleep``, in 0.25 s chunks)
   runs in its own process from the moment the arm's liveliness token appears until the arm is
   stopped: the platform's reference for missed ticks. Target: the arm's rate of missed ticks
   (published more than one dt late) ≤ 2× the timer's rate of deadlines missed by more than
   2 ms. Reported: state→command latency p50 / p99 at the arm (from its ``put`` of state k to
   the arrival of the command answering k) and in the planner (from the state's arrival to the
   command's ``put``, the planner summary's ``planner.latency_us``).
d. **The whole feeding stack, realtime**, through ``psm up``'s code
   (:func:`services.supervisor.run_stack` on ``configs/stack.toml``: router, recorder, arm,
   synthetic camera, goal tracker, planner; overrides as ``psm up --set`` passes them: a fresh
   port and prefix, run directory, recording, summary and stats files in a temporary
   directory). CPU = utime + stime from ``/proc/<pid>/stat`` sampled every 0.25 s, over the
   window from the moment every process is up to the last sample before the planner exits (the
   task done), % of one core. The supervisor runs inside this benchmark's process; its CPU (the
   whole benchmark process, sampler included) is shown beside the stack's. Target: the seven
   stack processes ≤ 100 % of one core in total. Also reported: the task's outcome from the
   supervisor's summary, and the stack's **platform floor** in the same run
   (:mod:`benchmarks.null_stack`): the seven processes replaced by null services that carry the
   same bus traffic (the run's recording gives each key's rate and a payload) and do no work,
   CPU over a 15 s window after 3 s of warm-up — what the stack's messages alone cost on this
   machine, per process and in total, and the stack's total as a multiple of it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import os
import platform
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.host import host_info, host_line
from benchmarks.stack import zenoh_table
from services.arm.stats import MISS_CAUSES_HEAD, miss_causes_text
from services.supervisor import ManagedProcess, cpu_seconds, free_port, psm_argv

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CACHE_DIR = ROOT / "out" / "models"

#: Target (b): lockstep arm ticks/s / raw zenoh ping-pong bound.
LOCKSTEP_RATIO_TARGET = 0.5
#: Target (c): arm missed-tick rate / bare timer missed-deadline rate.
MISS_RATIO_TARGET = 2.0
#: Target (d): the whole feeding stack, % of one core.
STACK_CPU_TARGET_PCT = 100.0
#: Sim-time rate of the static person goal in the in-process replay (a camera's rate), Hz.
GOAL_RATE_HZ = 30.0
#: The planner status window starts this long after the first answered tick, s.
WINDOW_SKIP_S = 0.5
TASK_TIMEOUT_S = 180.0  #: one task run (wall clock)
STARTUP_TIMEOUT_S = 120.0  #: one process's liveliness token
STACK_PROCESSES = ("router", "recorder", "arm", "camera", "goal_tracker", "obstacle_monitor", "planner")
FLOOR_WINDOW_S = 15.0  #: the platform floor's CPU window (part d), s
FLOOR_WARMUP_S = 3.0  #: before it, s


# --------------------------------------------------------------------------------------------
# Pure parts: statistics, windows, verdicts, files
# --------------------------------------------------------------------------------------------


def percentiles(values_us: Sequence[float]) -> dict[str, float]:
    """p50 / p99 / max / mean [µs] and the count of ``values_us``."""
    v = np.asarray(values_us, dtype=float)
    if v.size == 0:
        return {"p50_us": float("nan"), "p99_us": float("nan"), "max_us": float("nan"),
                "mean_us": float("nan"), "n": 0}
    p50, p99 = np.percentile(v, [50, 99])
    return {"p50_us": float(p50), "p99_us": float(p99), "max_us": float(v.max()),
            "mean_us": float(v.mean()), "n": int(v.size)}


def status_window(samples: Sequence[tuple[float, int, str]], skip_s: float = WINDOW_SKIP_S) -> dict[str, Any]:
    """Ticks/s of the arm from the planner's status samples ``(wall time [s], tick answered last,
    state name)``: over the samples from ``skip_s`` after the first one with an answered tick
    (state RUNNING or HOLDING, tick > 0) to the last one before the state became DONE or FAULT."""
    active = [(t, k) for t, k, s in samples if s in ("RUNNING", "HOLDING") and k > 0]
    if len(active) < 2:
        return {"ticks_per_s": float("nan"), "window_s": 0.0, "ticks": 0, "samples": len(active)}
    t_first = active[0][0]
    win = [(t, k) for t, k in active if t >= t_first + skip_s] or active
    if len(win) < 2:
        win = active
    (t0, k0), (t1, k1) = win[0], win[-1]
    dt = t1 - t0
    return {"ticks_per_s": (k1 - k0) / dt if dt > 0 else float("nan"), "window_s": dt,
            "ticks": k1 - k0, "samples": len(win)}


def pingpong_bound(rtt_us: Sequence[float]) -> dict[str, Any]:
    """The lockstep bound of a transport from its round trips [µs]: 1 / round-trip p50."""
    p = percentiles(rtt_us)
    return {**p, "bound_per_s": 1e6 / p["p50_us"] if p["n"] else float("nan")}


def ratio_verdict(value: float, reference: float, target: float, at_least: bool = True) -> dict[str, Any]:
    """``value / reference`` judged against ``target`` (``at_least``: ratio ≥ target, else ≤)."""
    ratio = value / reference if reference else float("nan")
    ok = bool(ratio >= target) if at_least else bool(ratio <= target)
    return {"value": value, "reference": reference, "ratio": ratio, "target": target,
            "at_least": at_least, "ok": ok}


def miss_verdict(arm: Mapping[str, Any], timer: Mapping[str, Any],
                 target: float = MISS_RATIO_TARGET) -> dict[str, Any]:
    """The arm's rate of missed ticks (``missed_ticks`` over published + skipped ticks) against
    the bare timer's rate of deadlines missed by more than 2 ms, judged against ``target``."""
    missed = int(arm.get("missed_ticks") or 0)
    ticks = int(arm.get("published_ticks") or 0) + int(arm.get("skipped_ticks") or 0)
    t_missed = int(timer.get("over_2ms") or 0)
    t_n = int(timer.get("n") or 0)
    arm_rate = missed / ticks if ticks else float("nan")
    t_rate = t_missed / t_n if t_n else float("nan")
    if missed == 0 and ticks:
        ratio = 0.0
    elif t_missed == 0:
        ratio = float("inf")
    else:
        ratio = arm_rate / t_rate
    return {"arm_missed": missed, "arm_ticks": ticks, "arm_rate": arm_rate,
            "timer_missed": t_missed, "timer_deadlines": t_n, "timer_rate": t_rate,
            "ratio": ratio, "target": target, "ok": bool(ratio <= target)}


def cpu_window(samples: Sequence[tuple[float, Mapping[str, float | None]]]) -> dict[str, Any]:
    """CPU % of one core per process over the window from the first sample to the last one in
    which every process was alive (``samples``: ``(wall time [s], {name: cpu seconds or None})``)."""
    if not samples:
        return {"window_s": 0.0, "cpu_pct": {}}
    t0, first = samples[0]
    names = [n for n, v in first.items() if v is not None]
    last = None
    for t, vals in samples[1:]:
        if all(vals.get(n) is not None for n in names):
            last = (t, vals)
    if last is None:
        return {"window_s": 0.0, "cpu_pct": {}}
    t1, end = last
    dt = t1 - t0
    pct = {n: round(100.0 * (float(end[n]) - float(first[n])) / dt, 1) for n in names}  # type: ignore[arg-type]
    return {"window_s": round(dt, 2), "cpu_pct": pct}


def bench_stack_file(*, endpoint: str, prefix: str, clock: str, workdir: Path, task_file: Path,
                     arm: Mapping[str, Any], planner_rt: int, cache_dir: Path = CACHE_DIR,
                     log_level: str = "INFO") -> str:
    """A stack file with the router, the arm and the planner only (``psm up`` could run it):
    the arm's fields as given (dt_s, start_pose, rt_priority, watch_services), stats, summary and
    the task file in ``workdir``."""
    j = json.dumps
    return f"""# generated by benchmarks/planner.py: router + arm + planner, no camera or tracker
prefix = {j(prefix)}
clock = {j(clock)}
log_level = {j(log_level)}
status_period_s = 0.5
{zenoh_table(endpoint)}[stack]
name = "planner-bench"
startup_timeout_s = {STARTUP_TIMEOUT_S}
stop_timeout_s = 15.0
run_dir = {j(str(workdir))}
[[stack.processes]]
name = "router"
command = ["serve", "router"]
[[stack.processes]]
name = "planner"
command = ["plan"]
ends_stack = true
[[stack.processes]]
name = "arm"
command = ["arm"]
[router]
listen = [{j(endpoint)}]
[arm]
dt_s = {float(arm['dt_s'])!r}
start_pose = {j(arm['start_pose'])}
rt_priority = {int(arm['rt_priority'])}
watch_services = {j(list(arm['watch_services']))}
stats_file = {j(str(workdir / 'arm_stats.json'))}
[planner]
task_file = {j(str(task_file))}
cache_dir = {j(str(cache_dir))}
exit_when_done = true
summary_file = {j(str(workdir / 'task_summary.json'))}
rt_priority = {int(planner_rt)}
"""


def deployed() -> dict[str, Any]:
    """The arm's and planner's fields of ``configs/stack.toml`` (how the stack deploys them)."""
    from services.stack import DEFAULT_STACK, load_stack

    st = load_stack(DEFAULT_STACK)
    a = st.configs["arm"].arm  # type: ignore[attr-defined]
    p = st.configs["planner"].planner  # type: ignore[attr-defined]
    return {"arm": {"dt_s": a.dt_s, "start_pose": a.start_pose, "rt_priority": a.rt_priority,
                    "watch_services": list(a.watch_services)},
            "planner_rt_priority": p.rt_priority}


# --------------------------------------------------------------------------------------------
# (a) Tick cost in process
# --------------------------------------------------------------------------------------------


class _Payload:
    __slots__ = ("_b",)

    def __init__(self, b: bytes) -> None:
        self._b = b

    def to_bytes(self) -> bytes:
        return self._b


class _Sample:
    """What the planner's Zenoh callback reads of a sample: ``payload.to_bytes()``, ``encoding``."""

    __slots__ = ("encoding", "payload")

    def __init__(self, b: bytes, encoding: str) -> None:
        self.payload = _Payload(b)
        self.encoding = encoding


class _FakeService:
    """The parts of :class:`services.bus.runtime.Service` the planner's state path uses."""

    def __init__(self) -> None:
        from services.bus.runtime import Counters

        self.counters = Counters()
        self.log = logging.getLogger("benchmarks.planner")
        self.rejections: list[tuple[str, str]] = []

    def record_rejection(self, key: str, reason: str) -> None:
        self.rejections.append((key, reason))


class _CapturePublisher:
    def __init__(self) -> None:
        self.last = b""
        self.n = 0

    def put_bytes(self, b: bytes) -> None:
        self.last = b
        self.n += 1

    def put(self, msg: Any) -> None:
        self.put_bytes(msg.SerializeToString())


def make_planner(task_file: Path | None = None) -> Any:
    """A :class:`PlannerService` with its bus parts replaced (fake service, capturing publisher)."""
    from services.bus.config import load_config
    from services.bus.messages import Keys
    from services.planner.config import PlannerConfig
    from services.planner.service import PlannerService
    from services.tasks.feeding import DEFAULT_FEEDING_CONFIG

    cfg = load_config(PlannerConfig, env={}, overrides={
        "planner.task_file": str(task_file or DEFAULT_FEEDING_CONFIG),
        "planner.cache_dir": str(CACHE_DIR), "planner.rt_priority": 0, "log_level": "WARNING"})
    svc = PlannerService(cfg)
    svc.svc = _FakeService()  # type: ignore[assignment]
    svc._cmd_pub = _CapturePublisher()  # type: ignore[attr-defined]
    svc._goal_pub = _CapturePublisher()  # type: ignore[attr-defined]  # the planner's goal in use
    keys = Keys()  # the planner's keys on the default prefix, as its setup() derives them
    svc._state_key = keys.arm_state.key  # type: ignore[attr-defined]
    svc._goals_prefix = keys.goals_all.key[:-1]  # type: ignore[attr-defined]
    return svc


def record_stream(max_sim_s: float = 60.0) -> dict[str, Any]:
    """Run the planner service against the simulated arm in process through the whole feeding
    task (plus the planner's linger); returns the stream ``[("state", bytes) | ("goal", Goal)]``,
    the commands it answered with and the task summary."""
    from services.bus.messages import ArmCommand, ArmState, Goal, encoding_for, vec3
    from services.robot.protocol import StateEncoder, command_from_message
    from services.stack import DEFAULT_STACK, load_stack

    section = load_stack(DEFAULT_STACK).configs["arm"].arm  # type: ignore[attr-defined]
    from services.arm.sim import ArmSim

    robot = section.load_robot()
    sim = ArmSim(robot, section)
    enc = StateEncoder(list(robot.joint_names), section.frame_id, section.dt_ns * 1e-9)
    svc = make_planner()
    pub = svc._cmd_pub
    encoding = encoding_for(ArmState)
    person = svc.task_config.scene.person
    dt_s = section.dt_ns * 1e-9
    goal_every = max(1, round(1.0 / (GOAL_RATE_HZ * dt_s)))
    linger_ticks = int(svc.config.planner.linger_s / dt_s)
    stream: list[tuple[str, Any]] = []
    replies: list[bytes] = []
    done_at = -1
    for k in range(int(max_sim_s / dt_s)):
        snap = sim.snapshot()
        if k % goal_every == 0:
            g = Goal(stamp_ns=snap.time_ns, name="person", position=vec3(*person), valid=True,
                     frame_id="base", source="bench")
            stream.append(("goal", g))
            svc._on_goal(g, _person_key())
        payload = enc.encode(snap, watchdog_tripped=sim.watchdog_tripped,
                             rejected_commands=sim.counters["rejected"])
        stream.append(("state", payload))
        n_before = pub.n
        svc._on_state(_Sample(payload, encoding))
        if pub.n == n_before:
            raise RuntimeError(f"the planner did not answer tick {snap.tick}: {svc.svc.rejections[-1:]}")
        replies.append(pub.last)
        sim.submit(command_from_message(ArmCommand.FromString(pub.last)))  # type: ignore[arg-type]
        sim.step()
        if done_at < 0 and svc.runner.state in ("DONE", "FAULT"):
            done_at = k
        if done_at >= 0 and k - done_at >= linger_ticks:
            break
    return {"stream": stream, "replies": replies, "summary": svc.runner.summary(), "encoding": encoding,
            "sim_s": len(replies) * dt_s}


#: Cold-cache replay: bytes written before a timed call (more than the machine's caches) ...
COLD_FLUSH_BYTES = 64 * 1024 * 1024
#: ... before every this many calls (the calls in between run warm and are not timed).
COLD_EVERY = 7


def _person_key() -> str:
    """The key the recorded person goals arrive on (the planner's default prefix)."""
    from services.bus.messages import Keys

    return Keys().goal("person").key


def replay_total(rec: dict[str, Any], cold_every: int = 0) -> tuple[list[float], int]:
    """Replay the stream into a fresh service, timing each ``_on_state`` call [µs]; returns the
    times and the number of commands that differ from the recorded ones. ``cold_every`` > 0:
    the caches are flushed (:data:`COLD_FLUSH_BYTES` written, one write per 64-byte line) before
    every ``cold_every``-th call, and only those calls are timed."""
    svc = make_planner()
    pub, enc = svc._cmd_pub, rec["encoding"]
    on_state, on_goal = svc._on_state, svc._on_goal
    person = _person_key()
    junk = np.ones(COLD_FLUSH_BYTES // 8) if cold_every > 0 else None
    clock = time.perf_counter_ns
    out: list[float] = []
    diff = 0
    i = 0
    samples = [(kind, _Sample(x, enc) if kind == "state" else x) for kind, x in rec["stream"]]
    for kind, item in samples:
        if kind == "goal":
            on_goal(item, person)
            continue
        if junk is None or i % cold_every == 0:
            if junk is not None:
                junk[::8] += 1.0
            t0 = clock()
            on_state(item)
            out.append((clock() - t0) * 1e-3)
        else:
            on_state(item)
        diff += pub.last != rec["replies"][i]
        i += 1
    return out, diff


def replay_parts(rec: dict[str, Any]) -> dict[str, list[float]]:
    """Replay the stream once more, timing the parts of ``_on_state`` one by one [µs]."""
    from psm import PSMController

    svc = make_planner()
    pub, enc = svc._cmd_pub, rec["encoding"]
    person = _person_key()
    runner = svc.runner
    clock = time.perf_counter_ns
    parts: dict[str, list[float]] = {k: [] for k in (
        "decode", "answer", "runner_step", "controller", "orientation", "encode", "total")}
    acc = {"runner_step": 0, "controller": 0, "orientation": 0}

    def timed(fn: Callable[..., Any], key: str) -> Callable[..., Any]:
        def wrapper(*a: Any, **kw: Any) -> Any:
            t = clock()
            try:
                return fn(*a, **kw)
            finally:
                acc[key] += clock() - t
        return wrapper

    orig_ctrl = PSMController.step
    PSMController.step = timed(orig_ctrl, "controller")  # type: ignore[method-assign]
    runner.step = timed(runner.step, "runner_step")  # type: ignore[method-assign]
    runner._orientation = timed(runner._orientation, "orientation")  # type: ignore[method-assign]
    try:
        for kind, item in rec["stream"]:
            if kind == "goal":
                svc._on_goal(item, person)
                continue
            sample = _Sample(item, enc)
            for k in acc:
                acc[k] = 0
            # the steps of PlannerService._on_state, one by one
            t0 = clock()
            payload = sample.payload.to_bytes()
            if str(sample.encoding) != svc._state_encoding:
                raise RuntimeError("encoding mismatch")
            with svc._lock:
                st = svc._state
                st.ParseFromString(payload)
                t1 = clock()
                svc.svc.counters.add("received")
                reply = svc._answer(st)
                t2 = clock()
                if reply is None:
                    raise RuntimeError("state rejected in the replay")
                pub.put_bytes(reply)
            t3 = clock()
            svc._cmd.SerializeToString()
            t4 = clock()
            parts["decode"].append((t1 - t0) * 1e-3)
            parts["answer"].append((t2 - t1) * 1e-3)
            parts["encode"].append((t4 - t3) * 1e-3)
            parts["total"].append((t3 - t0) * 1e-3)
            for k, v in acc.items():
                if v:
                    parts[k].append(v * 1e-3)
    finally:
        PSMController.step = orig_ctrl  # type: ignore[method-assign]
    return parts


def bench_tick_cost(reps: int) -> dict[str, Any]:
    """Part (a): record a stream, replay it ``reps`` times for the total and once for the parts."""
    rec = record_stream()
    totals: list[float] = []
    mismatches = 0
    for _ in range(reps):
        t, d = replay_total(rec)
        totals += t
        mismatches += d
    parts = replay_parts(rec)
    cold: list[float] = []
    for _ in range(reps):
        t, d = replay_total(rec, cold_every=COLD_EVERY)
        cold += t
        mismatches += d
    s = rec["summary"]
    return {
        "states": len(rec["replies"]),
        "sim_s": rec["sim_s"],
        "replays": reps,
        "replay_mismatches": mismatches,
        "task_success": s["success"],
        "total": percentiles(totals),
        "total_cold": percentiles(cold),
        "cold_flush_bytes": COLD_FLUSH_BYTES,
        "cold_every": COLD_EVERY,
        "parts": {k: percentiles(v) for k, v in parts.items()},
    }


# --------------------------------------------------------------------------------------------
# Processes: raw ping-pong, the bare timer, a bus observer
# --------------------------------------------------------------------------------------------


def raw_pingpong(endpoint: str, workdir: Path, round_trips: int, warmup: int, tag: str) -> dict[str, Any]:
    """Raw zenoh-python ping-pong on the router at ``endpoint``, in the topology of the stack
    (:func:`benchmarks.stack.deployed_bus`: peers linked directly, or clients of the router)
    (``benchmarks.peers``'s raw ping and pong roles, driven over its control protocol):
    round-trip percentiles, rate, bound."""
    from benchmarks.bus import _line, _spawn
    from benchmarks.peers import PER_BLOCK, _Ping, block_sizes, variant_name
    from benchmarks.stack import deployed_bus

    mode = deployed_bus()[0]

    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(60)
    control = f"127.0.0.1:{listener.getsockname()[1]}"
    out_file = workdir / f"raw-ping-{tag}.json"
    mx = ["--max-seconds", "600"]
    pong = _spawn(workdir, f"raw-pong-{tag}", "-m", "benchmarks.peers", "--role", "raw-pong",
                  "--mode", mode, "--endpoint", endpoint, *mx)
    ping: ManagedProcess | None = None
    conn = None
    try:
        _line(pong, "ready", 60)
        ping = _spawn(workdir, f"raw-ping-{tag}", "-m", "benchmarks.peers", "--role", "raw-ping",
                      "--mode", mode, "--endpoint", endpoint, "--control", control, "--out-file",
                      str(out_file), *mx)
        c, _ = listener.accept()
        c.settimeout(60)
        conn = _Ping(c)
        if conn.variant != variant_name("raw", mode):
            raise RuntimeError(f"unexpected ping: {conn.variant!r}")
        conn.ask(f"run {warmup} 0")
        elapsed_ns = 0
        for n in block_sizes(round_trips, PER_BLOCK):
            words = conn.ask(f"run {n} 1")
            elapsed_ns += int(words[2])
        conn.ask("quit", 30)
        deadline = time.monotonic() + 20
        while not out_file.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        rtt = json.loads(out_file.read_text())["rtt_us"]
    finally:
        if conn is not None:
            conn.close()
        listener.close()
        for p in (ping, pong):
            if p is not None:
                if p.wait(5) is None:
                    p.stop(10)
                else:
                    p.stop(1)
    res = pingpong_bound(rtt)
    res["round_trips_per_s"] = len(rtt) / (elapsed_ns * 1e-9) if elapsed_ns else float("nan")
    return res


def _timer_main(out: Path, max_s: float) -> int:
    """The bare timer reference: 2 ms deadlines (``bench_timer`` in 0.25 s chunks) until SIGTERM
    or ``max_s``; writes the counts and lateness figures to ``out``."""
    from benchmarks.arm import bench_timer

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    c0 = time.process_time()
    t0 = time.monotonic()
    n = over1 = over2 = 0
    p50s: list[float] = []
    worst = 0.0
    while not stop.is_set() and time.monotonic() - t0 < max_s:
        r = bench_timer(0.25, period_s=0.002)
        n += r["n"]
        over1 += r["over_1ms"]
        over2 += r["over_2ms"]
        p50s.append(r["p50_us"])
        worst = max(worst, r["max_us"])
    wall = time.monotonic() - t0
    out.write_text(json.dumps({
        "n": n, "over_1ms": over1, "over_2ms": over2, "period_s": 0.002, "wall_s": wall,
        "p50_us": float(np.median(p50s)) if p50s else float("nan"), "max_us": worst,
        "cpu_pct": round(100.0 * (time.process_time() - c0) / wall, 1) if wall > 0 else 0.0}))
    return 0


class _Observer:
    """This process's Zenoh client of the router: liveliness tokens and the planner's status."""

    def __init__(self, endpoint: str, prefix: str) -> None:
        import zenoh

        from services.bus.config import ServiceConfig, load_config
        from services.bus.messages import Keys, PlannerStatus, decode
        from services.bus.runtime import open_session

        cfg = load_config(ServiceConfig, env={}, overrides={
            "zenoh.mode": "client", "zenoh.connect": [endpoint], "zenoh.multicast": False,
            "prefix": prefix, "log_level": "WARNING"})
        self.session = open_session(cfg.zenoh)
        keys = Keys(prefix)
        base = keys.liveliness_all.key[:-1]
        self.alive: set[str] = set()
        self.status: list[tuple[float, int, str]] = []
        self._lock = threading.Lock()

        def on_token(sample: Any) -> None:
            name = str(sample.key_expr)[len(base):]
            with self._lock:
                if sample.kind == zenoh.SampleKind.PUT:
                    self.alive.add(name)
                else:
                    self.alive.discard(name)

        def on_status(sample: Any) -> None:
            with contextlib.suppress(ValueError):
                msg = decode(sample.payload.to_bytes(), str(sample.encoding), PlannerStatus)
                with self._lock:
                    self.status.append((time.monotonic(), int(msg.state_tick),
                                        PlannerStatus.State.Name(msg.state)))

        self._subs = [
            self.session.liveliness().declare_subscriber(keys.liveliness_all.key, on_token, history=True),
            self.session.declare_subscriber(keys.planner_status.key, on_status),
        ]

    def wait_alive(self, name: str, proc: ManagedProcess, timeout_s: float = STARTUP_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if name in self.alive:
                    return
            if not proc.alive():
                raise RuntimeError(f"{proc.name} exited at start: {proc.log_tail()}")
            time.sleep(0.02)
        raise RuntimeError(f"{name} not alive within {timeout_s:.0f} s: {proc.log_tail()}")

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()
        with contextlib.suppress(Exception):
            self.session.close()


class CpuSampler:
    """Samples ``cpu_seconds`` of named PIDs every ``period_s`` on a thread (bounded by ``max_s``)."""

    def __init__(self, pids: Mapping[str, int], period_s: float = 0.25,
                 max_s: float = TASK_TIMEOUT_S) -> None:
        self.pids = dict(pids)
        self.samples: list[tuple[float, dict[str, float | None]]] = []
        self._stop = threading.Event()
        self._period, self._max = period_s, max_s
        self._thread = threading.Thread(target=self._run, daemon=True, name="cpu-sampler")

    def start(self) -> CpuSampler:
        self.sample()
        self._thread.start()
        return self

    def sample(self) -> None:
        self.samples.append((time.monotonic(), {n: cpu_seconds(p) for n, p in self.pids.items()}))

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self._stop.wait(self._period) and time.monotonic() - t0 < self._max:
            self.sample()

    def stop(self) -> dict[str, Any]:
        self._stop.set()
        self._thread.join(5)
        return cpu_window(self.samples)


# --------------------------------------------------------------------------------------------
# (b), (c) Closed loop arm <-> planner
# --------------------------------------------------------------------------------------------


def closed_loop(clock: str, workdir: Path, *, round_trips: int = 0, warmup: int = 0) -> dict[str, Any]:
    """Router + planner + arm on ``clock`` (see the module docstring, parts b and c); with
    ``round_trips`` the raw ping-pong bound on the same router, in the same topology, before and
    after the task."""
    from services.tasks.feeding import DEFAULT_FEEDING_CONFIG, load_feeding, static_person_task

    dep = deployed()
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"pbench{port}"
    task_file = workdir / "feeding_static_person.toml"
    task_file.write_text(static_person_task(DEFAULT_FEEDING_CONFIG.read_text()))
    assert not any(s.live for s in load_feeding(task_file).task.steps)
    stack_file = workdir / "stack.toml"
    stack_file.write_text(bench_stack_file(endpoint=endpoint, prefix=prefix, clock=clock, workdir=workdir,
                                           task_file=task_file, arm=dep["arm"],
                                           planner_rt=dep["planner_rt_priority"]))
    cfg = ["--config", str(stack_file)]
    procs: dict[str, ManagedProcess] = {}
    timer: ManagedProcess | None = None
    obs: _Observer | None = None
    res: dict[str, Any] = {"clock": clock, "rt_priority": dep["arm"]["rt_priority"],
                           "planner_rt_priority": dep["planner_rt_priority"]}
    timer_out = workdir / "timer.json"
    try:
        procs["router"] = ManagedProcess("router", psm_argv(["serve", "router", *cfg]),
                                         workdir / "router.log")
        _wait_port(port, 30, procs["router"])
        if round_trips:
            res["pingpong_before"] = raw_pingpong(endpoint, workdir, round_trips, warmup, "before")
        obs = _Observer(endpoint, prefix)
        procs["planner"] = ManagedProcess("planner", psm_argv(["plan", *cfg]), workdir / "planner.log")
        obs.wait_alive("planner", procs["planner"])
        procs["arm"] = ManagedProcess("arm", psm_argv(["arm", *cfg]), workdir / "arm.log")
        obs.wait_alive("arm", procs["arm"])
        if clock == "realtime":
            timer = ManagedProcess("bare_timer", [sys.executable, "-m", "benchmarks.planner", "--timer-out",
                                                  str(timer_out), "--timer-max", str(TASK_TIMEOUT_S)],
                                   workdir / "bare_timer.log")
        sampler = CpuSampler({n: p.pid for n, p in procs.items()}).start()
        t0 = time.monotonic()
        rc = None
        while rc is None and time.monotonic() - t0 < TASK_TIMEOUT_S:
            rc = procs["planner"].wait(0.1)
            if rc is None and not procs["arm"].alive():
                raise RuntimeError(f"the arm exited during the task: {procs['arm'].log_tail()}")
        res["task_wall_s"] = round(time.monotonic() - t0, 2)
        cpu = sampler.stop()
        if rc is None:
            raise RuntimeError(f"the planner did not finish within {TASK_TIMEOUT_S:.0f} s")
        res["planner_exit_code"] = rc
        res["arm_alive_at_end"] = procs["arm"].alive()
        procs["arm"].stop(15)
        if timer is not None:
            timer.stop(10)
        res["cpu"] = cpu
        if round_trips:
            res["pingpong_after"] = raw_pingpong(endpoint, workdir, round_trips, warmup, "after")
    finally:
        if obs is not None:
            obs.close()
        if timer is not None and timer.alive():
            timer.stop(5)
        for name in ("arm", "planner", "router"):
            if name in procs:
                procs[name].stop(15)
    res["status_samples"] = len(obs.status) if obs else 0
    res["window"] = status_window(obs.status if obs else [])
    res["arm"] = _read_json(workdir / "arm_stats.json")
    task = _read_json(workdir / "task_summary.json")
    res["task"] = _task_brief(task)
    res["planner_latency_us"] = (task.get("planner") or {}).get("latency_us")
    if timer is not None:
        res["timer"] = _read_json(timer_out)
    res["logs_with_errors"] = {n: (workdir / f"{n}.log").read_text(errors="replace")[-1500:]
                               for n in ("router", "planner", "arm")
                               if "Traceback" in (workdir / f"{n}.log").read_text(errors="replace")}
    return res


def _task_brief(task: Mapping[str, Any]) -> dict[str, Any]:
    if not task:
        return {}
    return {"success": task.get("success"), "state": task.get("state"), "detail": task.get("detail"),
            "steps_succeeded": task.get("steps_succeeded"), "steps_total": task.get("steps_total"),
            "duration_s": task.get("duration_s"),
            "steps": [{k: s.get(k) for k in ("step", "outcome", "success", "duration_s", "position_error_m",
                                             "peak_speed_ratio")} for s in task.get("steps", [])]}


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _wait_port(port: int, timeout_s: float, proc: ManagedProcess) -> None:
    from benchmarks.peers import _wait_port as wait_port

    wait_port(port, timeout_s, proc)


# --------------------------------------------------------------------------------------------
# (d) The whole feeding stack through psm up's code
# --------------------------------------------------------------------------------------------


def stack_overrides(workdir: Path, port: int) -> dict[str, str]:
    """``psm up --set`` overrides for one benchmark run of ``configs/stack.toml``: a fresh port
    and prefix, every output file in ``workdir``."""
    j = json.dumps
    return {
        "prefix": j(f"pstack{port}"),
        "router.listen": j([f"tcp/127.0.0.1:{port}"]),
        "zenoh.connect": j([f"tcp/127.0.0.1:{port}"]),
        "stack.run_dir": j(str(workdir)),
        "recorder.output": j(str(workdir / "run.mcap")),
        "planner.summary_file": j(str(workdir / "task_summary.json")),
        "planner.progress_file": j(str(workdir / "task_progress.json")),
        "planner.cache_dir": j(str(CACHE_DIR)),
        "arm.stats_file": j(str(workdir / "arm_stats.json")),
    }


def whole_stack(workdir: Path, clock: str = "realtime") -> dict[str, Any]:
    """Part (d): ``configs/stack.toml`` run by :func:`services.supervisor.run_stack` as ``psm up
    --clock CLOCK --set ...`` does, CPU per process sampled over the run."""
    from services.bus.config import env_var_name, parse_override
    from services.stack import DEFAULT_STACK, load_stack
    from services.supervisor import Supervisor, run_stack

    sets = {**stack_overrides(workdir, free_port()), "clock": clock}
    parsed = {k: parse_override(v) for k, v in sets.items()}
    stack = load_stack(DEFAULT_STACK, overrides=parsed)
    env = {env_var_name(k): v if isinstance(v, str) else json.dumps(v) for k, v in parsed.items()}
    holder: dict[str, CpuSampler] = {}

    def on_started(sup: Supervisor) -> None:
        pids = {row.name: row.proc.pid for row in sup.rows}
        pids["supervisor (benchmark process)"] = os.getpid()
        holder["sampler"] = CpuSampler(pids).start()

    out = io.StringIO()
    t0 = time.monotonic()
    rc = run_stack(stack, env_overrides=env, out=out, live=False, on_started=on_started,
                   duration_s=TASK_TIMEOUT_S)
    wall = time.monotonic() - t0
    cpu = holder["sampler"].stop() if "sampler" in holder else {"window_s": 0.0, "cpu_pct": {}}
    summary = _read_json(workdir / "summary.json")
    stack_pct = {n: v for n, v in cpu["cpu_pct"].items() if n in STACK_PROCESSES}
    total = round(sum(stack_pct.values()), 1)
    sup_pct = cpu["cpu_pct"].get("supervisor (benchmark process)", float("nan"))
    return {
        "exit_code": rc, "wall_s": round(wall, 2), "reason": summary.get("reason"),
        "cpu": cpu, "stack_total_pct": total, "total_with_supervisor_pct": round(total + sup_pct, 1),
        "task": _task_brief(summary.get("task") or {}),
        "planner_latency_us": ((summary.get("task") or {}).get("planner") or {}).get("latency_us"),
        "arm": summary.get("arm") or {},
        "processes": summary.get("processes"),
        "supervisor_output_tail": out.getvalue()[-3000:] if rc != 0 else "",
    }


def stack_floor(recording: Path, workdir: Path, seconds: float = FLOOR_WINDOW_S) -> dict[str, Any]:
    """The platform floor of part (d) (:func:`benchmarks.null_stack.run_null_stack` with the
    traffic of ``recording``); ``{"problem": ...}`` when the recording cannot give it."""
    from benchmarks.null_stack import run_null_stack, traffic_profile

    try:
        profile = traffic_profile(recording)
    except (OSError, ValueError) as exc:
        return {"problem": f"no traffic profile: {exc}"}
    res = run_null_stack(profile, seconds=seconds, warmup_s=FLOOR_WARMUP_S, workdir=workdir)
    return res | {"rates_hz": {k: round(v["rate_hz"], 1) for k, v in profile["keys"].items()},
                  "payload_bytes": {k: len(v["payload_hex"]) // 2 for k, v in profile["keys"].items()}}


# --------------------------------------------------------------------------------------------
# Verdicts and report
# --------------------------------------------------------------------------------------------


def verdicts(res: dict[str, Any]) -> dict[str, Any]:
    """The three targets, each with the figures it is judged on."""
    out: dict[str, Any] = {}
    b = res.get("lockstep")
    if b:
        rtts = [b["pingpong_before"]["p50_us"], b.get("pingpong_after", {}).get("p50_us", float("nan"))]
        rtts = [r for r in rtts if np.isfinite(r)]
        p50 = float(np.mean(rtts))
        out["lockstep"] = {**ratio_verdict(b["window"]["ticks_per_s"], 1e6 / p50, LOCKSTEP_RATIO_TARGET),
                           "pingpong_p50_us": p50}
    c = res.get("realtime")
    if c:
        out["realtime_missed"] = miss_verdict(c.get("arm", {}), c.get("timer", {}))
    d = res.get("stack")
    if d:
        floor = (d.get("floor") or {}).get("total_pct")
        out["stack_cpu"] = {"value_pct": d["stack_total_pct"], "target_pct": STACK_CPU_TARGET_PCT,
                            "with_supervisor_pct": d["total_with_supervisor_pct"],
                            "ok": bool(d["stack_total_pct"] <= STACK_CPU_TARGET_PCT),
                            "ok_with_supervisor":
                                bool(d["total_with_supervisor_pct"] <= STACK_CPU_TARGET_PCT),
                            "floor_pct": floor,
                            "ratio_to_floor": d["stack_total_pct"] / floor if floor else None}
    return out


def _ok(b: bool) -> str:
    return "**met**" if b else "**not met**"


def _f(v: Any, nd: int = 0) -> str:
    if v is None:
        return "–"
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "–" if not np.isfinite(x) else f"{x:,.{nd}f}"


def _lat(d: Mapping[str, Any] | None, p50: str = "p50_us", p99: str = "p99_us", mx: str = "max_us") -> str:
    if not d:
        return "–"
    return f"p50 {_f(d.get(p50))} µs, p99 {_f(d.get(p99))} µs, max {_f(d.get(mx))} µs"


def _task_line(t: Mapping[str, Any]) -> str:
    if not t:
        return "no task summary"
    word = "succeeded" if t.get("success") else f"did not succeed ({t.get('state')}: {t.get('detail')})"
    return (f"{t.get('steps_succeeded')}/{t.get('steps_total')} steps, {word}, "
            f"{_f(t.get('duration_s'), 2)} s of task time")


def render_markdown(res: dict[str, Any]) -> str:
    """The markdown report of one run."""
    v = res["verdicts"]
    lines = [
        "# Planner benchmark: tick cost, closed loop with the real planner, the whole feeding stack",
        "",
        f"Measured {res['date_utc']} on {res['machine']} ({res['cpus']} CPUs, shared; load average at "
        f"start {res['load_avg_start']}, at end {res['load_avg_end']}; all CPUs "
        f"{res['machine_busy_pct_before']:.0f} % busy in the 2 s before the run, "
        f"{res['machine_busy_pct_during']:.0f} % during it, this benchmark included); python "
        f"{res['python']}, zenoh {res['zenoh']}"
        + (f"; {host_line(res['host'])}" if res.get("host") else "")
        + f". Produced by `python -m benchmarks.planner{' --quick' if res['quick'] else ''}`; method in "
        "the module docstring.",
        "",
        "## Targets",
        "",
        "| target | measured | verdict |",
        "|---|---|---|",
    ]
    if "lockstep" in v:
        x = v["lockstep"]
        lines.append(
            f"| (b) lockstep arm ticks/s ≥ {LOCKSTEP_RATIO_TARGET}× the raw zenoh ping-pong bound "
            f"(1 / RTT p50, same router and topology) | {_f(x['value'])} ticks/s vs bound "
            f"{_f(x['reference'])}/s "
            f"(RTT p50 {_f(x['pingpong_p50_us'])} µs): **{x['ratio']:.2f}×** | {_ok(x['ok'])} |")
    if "realtime_missed" in v:
        m = v["realtime_missed"]
        lines.append(
            f"| (c) realtime 500 Hz: arm missed ticks ≤ {MISS_RATIO_TARGET:.0f}× a bare 2 ms timer "
            f"loop's misses (same window) | arm {m['arm_missed']} of {m['arm_ticks']} ticks, timer "
            f"{m['timer_missed']} of {m['timer_deadlines']} deadlines: ratio of rates "
            f"**{_f(m['ratio'], 2)}** | {_ok(m['ok'])} |")
    if "stack_cpu" in v:
        s = v["stack_cpu"]
        lines.append(
            f"| (d) whole feeding stack (realtime) ≤ {STACK_CPU_TARGET_PCT:.0f} % of one core | "
            f"**{s['value_pct']:.1f} %** for the seven stack processes ({s['with_supervisor_pct']:.1f} % "
            f"with the supervisor's process)"
            + ("" if not s.get("floor_pct") else
               f"; the same traffic without the work (platform floor, same run): {s['floor_pct']:.1f} %, "
               f"the stack {s['ratio_to_floor']:.2f}× it")
            + f" | {_ok(s['ok'])}"
            + ("" if s["ok"] == s["ok_with_supervisor"] else
               f" (with the supervisor: {_ok(s['ok_with_supervisor'])})") + " |")
    a = res.get("tick_cost")
    if a:
        labels = {
            "total": "**total: `PlannerService._on_state`** (uninstrumented replays)",
            "decode": "decode (`ArmState.ParseFromString`)",
            "answer": "`PlannerService._answer` (checks, copies, step, encode)",
            "runner_step": "… `TaskRunner.step`",
            "controller": "… … PSM controller (`PSMController.step`)",
            "orientation": "… … orientation reference (`TaskRunner._orientation`)",
            "encode": "… encode (`ArmCommand.SerializeToString`)",
        }
        lines += [
            "",
            "## (a) Planner tick cost, in process",
            "",
            f"{a['states']} states of one feeding task ({a['sim_s']:.1f} s of sim time, task "
            f"{'succeeded' if a['task_success'] else 'did NOT succeed'}) replayed {a['replays']}× "
            f"into fresh planner services; commands differing from the recorded run: "
            f"{a['replay_mismatches']}.",
            "",
            "| part | p50 (µs) | p99 (µs) | max (µs) | mean (µs) | calls |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        rows = [("total", a["total"])] + [(k, a["parts"][k]) for k in
                                          ("decode", "answer", "runner_step", "controller",
                                           "orientation", "encode")]
        rows.append(("total_parts", a["parts"]["total"]))
        labels["total_parts"] = "(the same, instrumented replay: sum of the steps above + `put`)"
        if "total_cold" in a:
            rows.append(("total_cold", a["total_cold"]))
            labels["total_cold"] = (
                f"**total, caches cold** ({a['cold_flush_bytes'] // 2**20} MiB written before every "
                f"{a['cold_every']}th call, only those timed)")
        for k, p in rows:
            lines.append(f"| {labels[k]} | {_f(p['p50_us'], 1)} | {_f(p['p99_us'], 1)} | "
                         f"{_f(p['max_us'], 1)} | {_f(p['mean_us'], 1)} | {p['n']} |")
        lines += ["", "At 500 Hz a tick is 2,000 µs: the planner's share of it is the total's p50 / "
                  f"2,000 µs = {a['total']['p50_us'] / 2000 * 100:.1f} % of one core."]
        if "total_cold" in a:
            lines += ["", "In the closed loop (b, c) the arm's process runs between two states, so "
                      "the planner answers each state with its caches cold: the cold row "
                      f"({a['total_cold']['p50_us'] / a['total']['p50_us']:.1f}× the warm p50) is "
                      "closer to what a tick costs there than the warm replays."]
    b = res.get("lockstep")
    if b:
        w = b["window"]
        arm = b.get("arm", {})
        lines += [
            "",
            "## (b) Closed loop with the real planner, lockstep",
            "",
            f"Router + `psm plan` + `psm arm` (clock lockstep; arm and planner at SCHED_FIFO "
            f"{b['rt_priority']} / {b['planner_rt_priority']} as `configs/stack.toml` deploys them); the "
            "person step made static (`live = false`, goal `scene.person`): no camera or tracker.",
            "",
            "| figure | value |",
            "|---|---:|",
            f"| **arm ticks/s over the window** (planner status, {w['window_s']:.2f} s, "
            f"{w['ticks']} ticks) | "
            f"**{_f(w['ticks_per_s'])}** |",
            f"| arm's own count (`stats_file`): ticks / loop wall time (incl. its start and the stop) | "
            f"{_f(arm.get('ticks'))} / {_f(arm.get('wall_s'), 2)} s = {_f(arm.get('ticks_per_s'))}/s |",
            f"| lockstep timeouts (arm waited {0.5} s for an answer) | {_f(arm.get('lockstep_timeouts'))} |",
            f"| state→command at the arm | {_lat(arm.get('state_to_command_latency'))} |",
            f"| state→command in the planner (`planner.latency_us`) | "
            f"{_lat(b.get('planner_latency_us'), 'p50', 'p99', 'max')} |",
        ]
        for tag in ("before", "after"):
            p = b.get(f"pingpong_{tag}")
            if p:
                lines.append(f"| raw zenoh ping-pong {tag} the task, same router and topology: RTT | "
                             f"{_lat(p)}; {_f(p['round_trips_per_s'])} round trips/s; bound 1/p50 "
                             f"{_f(p['bound_per_s'])}/s |")
        cpu = b.get("cpu", {})
        lines += [
            f"| CPU over the task ({cpu.get('window_s', 0):.1f} s), % of one core | "
            + ", ".join(f"{n} {p:.1f}" for n, p in cpu.get("cpu_pct", {}).items()) + " |",
            f"| task | {_task_line(b.get('task', {}))} |",
        ]
    c = res.get("realtime")
    if c:
        arm = c.get("arm", {})
        t = c.get("timer", {})
        cpu = c.get("cpu", {})
        lines += [
            "",
            "## (c) Closed loop with the real planner, realtime 500 Hz",
            "",
            f"The same three processes, clock realtime, arm and planner at SCHED_FIFO {c['rt_priority']} / "
            f"{c['planner_rt_priority']}; a bare 2 ms timer loop in its own process over the arm's loop.",
            "",
            "| figure | value |",
            "|---|---:|",
            f"| arm: ticks, published per s | {_f(arm.get('ticks'))} in {_f(arm.get('wall_s'), 2)} s, "
            f"{_f(arm.get('published_per_s'), 1)}/s |",
            f"| arm: missed ticks (published > 1 dt late), skipped, re-anchored | "
            f"{_f(arm.get('missed_ticks'))}, "
            f"{_f(arm.get('skipped_ticks'))}, {_f(arm.get('reanchors'))} |",
            f"| arm: published missed ticks by cause: {MISS_CAUSES_HEAD} | "
            f"{miss_causes_text(arm.get('missed_by'))} |",
            f"| arm: late commands (answer > 1 dt after its state) | {_f(arm.get('late_commands'))} of "
            f"{_f(arm.get('answered_ticks'))} answered |",
            f"| arm: publication jitter | {_lat(arm.get('jitter'))} |",
            f"| bare timer: deadlines missed by > 2 ms (> 1 ms) | {_f(t.get('over_2ms'))} "
            f"({_f(t.get('over_1ms'))}) "
            f"of {_f(t.get('n'))}; lateness p50 {_f(t.get('p50_us'))} µs, max {_f(t.get('max_us'))} µs |",
            f"| **state→command latency at the arm** | {_lat(arm.get('state_to_command_latency'))} |",
            f"| **state→command in the planner** (`planner.latency_us`) | "
            f"{_lat(c.get('planner_latency_us'), 'p50', 'p99', 'max')} |",
            f"| CPU over the task ({cpu.get('window_s', 0):.1f} s), % of one core | "
            + ", ".join(f"{n} {p:.1f}" for n, p in cpu.get("cpu_pct", {}).items()) + " |",
            f"| task | {_task_line(c.get('task', {}))} |",
        ]
    d = res.get("stack")
    if d:
        cpu = d["cpu"]
        arm = d.get("arm", {})
        lines += [
            "",
            "## (d) The whole feeding stack, realtime, through `psm up`'s code",
            "",
            "`configs/stack.toml` (router, recorder, arm, synthetic camera, goal tracker, obstacle monitor, "
            f"planner) run by "
            f"`run_stack` until the planner finished ({d['reason']}, exit code {d['exit_code']}, "
            f"{d['wall_s']:.1f} s with start-up and shutdown). CPU over the {cpu['window_s']:.1f} s from "
            "every process up to the task's end, % of one core:",
            "",
            "| process | CPU % |",
            "|---|---:|",
        ]
        floor = d.get("floor") or {}
        fl = floor.get("cpu_pct") or {}
        if fl:
            lines[-2:] = ["| process | CPU % | platform floor: null service, CPU % |", "|---|---:|---:|"]
        for n in (*STACK_PROCESSES, "supervisor (benchmark process)"):
            if n in cpu["cpu_pct"]:
                lines.append(f"| {n} | {cpu['cpu_pct'][n]:.1f} |" + (f" {_f(fl.get(n), 1)} |" if fl else ""))
        lines += [
            f"| **stack total (seven processes)** | **{d['stack_total_pct']:.1f}** |"
            + (f" **{floor['total_pct']:.1f}** |" if fl else ""),
            f"| total with the supervisor | {d['total_with_supervisor_pct']:.1f} |" + (" |" if fl else ""),
            "",
            f"Task: {_task_line(d.get('task', {}))}. Arm: {_f(arm.get('published_per_s'), 1)} states/s, "
            f"missed ticks {_f(arm.get('missed_ticks'))} of {_f(arm.get('ticks'))}, late commands "
            f"{_f(arm.get('late_commands'))}; state→command at the arm "
            f"{_lat(arm.get('state_to_command_latency'))}; in the planner "
            f"{_lat(d.get('planner_latency_us'), 'p50', 'p99', 'max')}.",
        ]
        if fl:
            lines += [
                "",
                "Platform floor (`benchmarks.null_stack`, after the stack, "
                f"{floor['window_s']:.1f} s window): "
                "each process replaced by a null service on the same skeleton and topology that "
                "subscribes to what it subscribes to and publishes what it publishes, at the rates and with "
                "payloads of this run's recording (answers per input as the real process: a command and a "
                "prediction per arm state, the tracker's outputs per frame, a frame every n-th state), "
                f"doing no work: **{floor['total_pct']:.1f} %** of one core; the stack "
                f"{d['stack_total_pct'] / floor['total_pct']:.2f}× it. The stack's own work is the "
                f"difference, {d['stack_total_pct'] - floor['total_pct']:.1f} points.",
            ]
        elif floor.get("problem"):
            lines += ["", f"Platform floor: not measured ({floor['problem']})."]
        steps = (d.get("task") or {}).get("steps") or []
        if steps:
            lines += ["", "| step | outcome | duration s | pos err mm | peak speed × demo |",
                      "|---|---|---:|---:|---:|"]
            for s in steps:
                pe = s.get("position_error_m")
                lines.append(f"| {s['step']} | {s['outcome']} | {_f(s.get('duration_s'), 2)} | "
                             f"{_f(None if pe is None else 1e3 * pe, 1)} | "
                             f"{_f(s.get('peak_speed_ratio'), 2)} |")
    return "\n".join(lines) + "\n"


def write_report(res: dict[str, Any], out: Path = RESULTS) -> None:
    """Write ``planner.json`` and ``planner.md`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "planner.json").write_text(json.dumps(res, indent=2, default=float) + "\n")
    (out / "planner.md").write_text(render_markdown(res))


def main(argv: list[str] | None = None) -> int:
    """Run the four parts and write the report (or, with ``--timer-out``, be the timer loop)."""
    from benchmarks.peers import _cpu_times, machine_busy_pct

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 replay, fewer ping-pong round trips")
    ap.add_argument("--reps", type=int, default=None, help="replays for the tick cost (default 5; quick 1)")
    ap.add_argument("--round-trips", type=int, default=None,
                    help="raw ping-pong round trips before and after the lockstep task "
                    "(default 3000; quick 600)")
    ap.add_argument("--only", choices=("tick", "lockstep", "realtime", "stack"), action="append",
                    help="run only these parts (repeatable)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--no-write", action="store_true", help="print the report, write nothing")
    ap.add_argument("--timer-out", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--timer-max", type=float, default=TASK_TIMEOUT_S, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.timer_out is not None:
        return _timer_main(args.timer_out, args.timer_max)
    from importlib.metadata import version

    parts = args.only or ["tick", "lockstep", "realtime", "stack"]
    reps = args.reps or (1 if args.quick else 5)
    rts = args.round_trips or (600 if args.quick else 3000)
    res: dict[str, Any] = {
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
        "zenoh": version("eclipse-zenoh"), "quick": bool(args.quick), "host": host_info(),
        "load_avg_start": ", ".join(f"{x:.2f}" for x in os.getloadavg()),
        "machine_busy_pct_before": round(machine_busy_pct(2.0), 1),
    }
    busy0 = _cpu_times()
    t_run = time.monotonic()
    if "tick" in parts:
        print("(a) tick cost ...", flush=True)
        res["tick_cost"] = bench_tick_cost(reps)
        print(json.dumps(res["tick_cost"]["total"]), flush=True)
    with tempfile.TemporaryDirectory(prefix="planner-bench-") as tmp:
        for key, clock in (("lockstep", "lockstep"), ("realtime", "realtime")):
            if key in parts:
                print(f"({'b' if key == 'lockstep' else 'c'}) closed loop, {clock} ...", flush=True)
                wd = Path(tmp) / key
                wd.mkdir()
                res[key] = closed_loop(clock, wd, round_trips=rts if key == "lockstep" else 0,
                                       warmup=min(300, rts))
                print(json.dumps({"window": res[key]["window"],
                                  "task": _task_line(res[key]["task"])}), flush=True)
        if "stack" in parts:
            print("(d) whole feeding stack, realtime ...", flush=True)
            wd = Path(tmp) / "stack"
            wd.mkdir()
            res["stack"] = whole_stack(wd)
            print(json.dumps({"cpu": res["stack"]["cpu"], "total": res["stack"]["stack_total_pct"]}),
                  flush=True)
            print("(d) platform floor: the same traffic, null services ...", flush=True)
            res["stack"]["floor"] = stack_floor(wd / "run.mcap", Path(tmp) / "floor")
            print(json.dumps({k: res["stack"]["floor"].get(k) for k in ("cpu_pct", "total_pct",
                                                                         "problem")}), flush=True)
    busy1 = _cpu_times()
    res["wall_s"] = round(time.monotonic() - t_run, 1)
    res["machine_busy_pct_during"] = round(100.0 * (busy1[0] - busy0[0]) / max(1, busy1[1] - busy0[1]), 1)
    res["load_avg_end"] = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    res["verdicts"] = verdicts(res)
    text = render_markdown(res)
    if not args.no_write:
        write_report(res, args.out)
        print(f"wrote {args.out / 'planner.md'}", flush=True)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
