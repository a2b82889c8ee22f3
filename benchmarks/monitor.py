"""Obstacle-monitor benchmark: CPU of ``psm obstacles`` answering a 500 Hz arm, with 10 obstacles.

Run ``python -m benchmarks.monitor`` (``--seconds 15`` per case, ``--quick`` for 6 s). Writes
``benchmarks/results/monitor.md`` and ``benchmarks/results/monitor.json``.

Each case runs, through the supervisor of ``psm up``, a router, ``psm arm`` (realtime, 500 Hz,
SCHED_FIFO as deployed), the trivial controller ``services.arm.probe`` holding the arm still, and
``psm obstacles`` with ten obstacles (boxes, spheres, cylinders placed around the arm, all within
the clearance cutoff, none close enough for a protective stop: the worst case for the broad
phase) and a goal on ``<prefix>/planner/goal`` (so the segment test runs on every state). The
cases differ only in how often the whole-arm clearance is computed (``clearance_every`` 1, 5, 10
ticks) and one has it off. CPU is utime + stime from ``/proc`` over the window, % of one core.
The probe's CPU in the same run is the platform reference: a process on the same skeleton that
also receives every state and publishes one message per state, with no work in between.

Target: the monitor at 500 Hz with 10 obstacles ≤ 20 % of one core, with the clearance
decimated as the stack deploys it (``configs/stack.toml`` ``clearance_every``); the decimation is
made safe by the stopping-distance allowance of the protective stop (docs/obstacles.md).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from services.stack import DEFAULT_STACK, load_stack
from services.supervisor import Supervisor, cpu_seconds, free_port

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

#: Target: the monitor's CPU at 500 Hz with 10 obstacles, % of one core.
MONITOR_TARGET_PCT = 20.0

#: Ten obstacles around the arm at its ready pose (m, base frame), 6-45 cm from its links.
OBSTACLES: tuple[str, ...] = (
    '{id = "b0", shape = "box", position_m = [0.55, 0.30, 0.15], size_m = [0.10, 0.10, 0.30]}',
    '{id = "b1", shape = "box", position_m = [0.55, -0.30, 0.15], size_m = [0.10, 0.10, 0.30]}',
    '{id = "b2", shape = "box", position_m = [0.75, 0.00, 0.10], size_m = [0.10, 0.40, 0.20],'
    ' rpy_deg = [0, 0, 20]}',
    '{id = "s0", shape = "sphere", position_m = [0.30, 0.35, 0.55], size_m = [0.10, 0, 0]}',
    '{id = "s1", shape = "sphere", position_m = [0.30, -0.35, 0.55], size_m = [0.10, 0, 0]}',
    '{id = "s2", shape = "sphere", position_m = [0.45, 0.00, 0.75], size_m = [0.08, 0, 0]}',
    '{id = "c0", shape = "cylinder", position_m = [0.10, 0.40, 0.30], size_m = [0.08, 0, 0.60]}',
    '{id = "c1", shape = "cylinder", position_m = [0.10, -0.40, 0.30], size_m = [0.08, 0, 0.60]}',
    '{id = "c2", shape = "cylinder", position_m = [0.60, 0.00, 0.02], size_m = [0.30, 0, 0.04]}',
    '{id = "b3", shape = "box", position_m = [-0.45, 0.00, 0.40], size_m = [0.10, 0.60, 0.80]}',
)

CASES: dict[str, dict[str, Any]] = {
    "segment only": {"clearance": False},
    "clearance every tick": {"clearance": True, "clearance_every": 1},
    "clearance every 5 ticks": {"clearance": True, "clearance_every": 5},
    "clearance every 10 ticks": {"clearance": True, "clearance_every": 10},
}


def deployed_clearance_every() -> int:
    """``clearance_every`` of the shipped stack file."""
    cfg = load_stack(DEFAULT_STACK).configs["obstacle_monitor"]
    return int(cfg.obstacle_monitor.clearance_every)  # type: ignore[attr-defined]


def _stack_file(workdir: Path, endpoint: str, monitor: dict[str, Any], rt_priority: int) -> Path:
    """The case's stack file: router, probe, monitor (10 obstacles, ``monitor`` fields), arm."""
    from benchmarks.stack import stack_header

    fields = "".join(f"{k} = {json.dumps(v)}\n" for k, v in monitor.items())
    text = stack_header("monitor-benchmark", endpoint, workdir) + f"""[[stack.processes]]
name = "router"
command = ["serve", "router"]
[[stack.processes]]
name = "probe"
command = ["arm", "probe", "--pattern", "hold", "--rt-priority", "{rt_priority}"]
[[stack.processes]]
name = "monitor"
command = ["obstacles"]
[[stack.processes]]
name = "arm"
command = ["arm"]
[router]
listen = [{json.dumps(endpoint)}]
[arm]
dt_s = 0.002
rt_priority = {rt_priority}
[obstacle_monitor]
obstacles = [{", ".join(OBSTACLES)}]
{fields}"""
    path = workdir / "stack.toml"
    path.write_text(text)
    return path


def _publish_goal(endpoint: str, stop_at: float) -> None:
    """Publish the planner's goal (latched key) every 0.2 s until ``stop_at`` (monotonic)."""
    import zenoh

    from services.bus.messages import Goal, Keys, encode

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        msg = Goal(name="person", valid=True, frame_id="base")
        msg.position.x, msg.position.y, msg.position.z = 0.35, 0.5, 0.45
        payload, encoding = encode(msg)
        pub = session.declare_publisher(Keys("psm").planner_goal.key, encoding=zenoh.Encoding(encoding))
        while time.monotonic() < stop_at:
            pub.put(payload)
            time.sleep(0.2)
    finally:
        session.close()


def run_case(name: str, seconds: float, warmup_s: float, rt_priority: int) -> dict[str, Any]:
    """One case: start, warm up, measure CPU over ``seconds``, stop."""
    import threading

    with tempfile.TemporaryDirectory(prefix="monitor-bench-") as tmp:
        workdir = Path(tmp)
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        sup = Supervisor(load_stack(_stack_file(workdir, endpoint, CASES[name], rt_priority)),
                         out=io.StringIO(), live=False)
        sup.start()
        try:
            stop_at = time.monotonic() + warmup_s + seconds + 5.0
            goal = threading.Thread(target=_publish_goal, args=(endpoint, stop_at), daemon=True)
            goal.start()
            time.sleep(warmup_s)
            pids = {row.name: row.proc.pid for row in sup.rows}
            before = {n: cpu_seconds(p) or 0.0 for n, p in pids.items()}
            t0 = time.monotonic()
            time.sleep(seconds)
            window = time.monotonic() - t0
            after = {n: cpu_seconds(p) or 0.0 for n, p in pids.items()}
            alive = all(row.proc.poll() is None for row in sup.rows)
        finally:
            sup.shutdown()
        log = (workdir / "monitor.log").read_text(errors="replace")
    stats: dict[str, Any] = {}
    for line in log.splitlines():
        if "obstacle monitor stopped" in line:
            stats["log"] = line.split("obstacle monitor stopped", 1)[1].strip()
    cpu = {n: round(100.0 * (after[n] - before[n]) / window, 1) for n in pids}
    return {"cpu_pct": cpu, "window_s": round(window, 2), "alive": alive, "monitor_log": stats,
            "settings": CASES[name]}


def write_report(res: dict[str, Any], out: Path = RESULTS) -> None:
    """``monitor.md`` + ``monitor.json``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "monitor.json").write_text(json.dumps(res, indent=2))
    lines = [
        "# Obstacle-monitor benchmark: CPU at 500 Hz with 10 obstacles",
        "",
        f"{res['date']} · {res['machine']} · {res['cpus']} CPUs · {res['seconds']:g} s windows after "
        f"{res['warmup_s']:g} s warm-up · `python -m benchmarks.monitor` (method: module docstring). "
        "CPU = utime + stime from `/proc/<pid>/stat`, % of one core.",
        "",
        "| case | monitor | probe (same traffic, no work) | monitor / probe | arm | router |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, c in res["cases"].items():
        cpu = c["cpu_pct"]
        ratio = cpu["monitor"] / cpu["probe"] if cpu.get("probe") else float("nan")
        lines.append(f"| {name} | {cpu['monitor']:.1f} | {cpu['probe']:.1f} | {ratio:.2f} | "
                     f"{cpu['arm']:.1f} | {cpu['router']:.1f} |")
    v = res["verdict"]
    lines += [
        "",
        "| target | measured | verdict |",
        "|---|---|---|",
        f"| monitor at 500 Hz, 10 obstacles, clearance every {v['clearance_every']} ticks (as deployed) "
        f"≤ {MONITOR_TARGET_PCT:g} % of one core | {v['cpu_pct']:.1f} % | "
        f"**{'met' if v['ok'] else 'not met'}** |",
        "",
        "The clearance check is decimated; the protective stop adds the distance the arm's fastest "
        "point can cover before the next check and while braking (docs/obstacles.md), so the "
        "decimation does not let the arm come closer than `clearance_stop_m`.",
    ]
    (out / "monitor.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    """Run every case and write the report."""
    from benchmarks.stack import deployed_rt_priority

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--warmup", type=float, default=4.0)
    ap.add_argument("--quick", action="store_true", help="6 s windows")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    seconds = 6.0 if args.quick else args.seconds
    rt = deployed_rt_priority()
    res: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "seconds": seconds,
        "warmup_s": args.warmup,
        "rt_priority": rt,
        "obstacles": len(OBSTACLES),
        "cases": {},
    }
    for name in CASES:
        print(f"case {name} ...", flush=True)
        res["cases"][name] = run_case(name, seconds, args.warmup, rt)
        print(json.dumps(res["cases"][name]["cpu_pct"]), flush=True)
    every = deployed_clearance_every()
    key = next((k for k, c in CASES.items() if c.get("clearance_every") == every), None)
    cpu = res["cases"][key]["cpu_pct"]["monitor"] if key else float("nan")
    res["verdict"] = {"clearance_every": every, "cpu_pct": cpu, "target_pct": MONITOR_TARGET_PCT,
                      "ok": cpu <= MONITOR_TARGET_PCT}
    write_report(res, args.out)
    print((args.out / "monitor.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
