"""Access-control benchmark: the router's CPU with zenoh's access control and its denial log.

Run ``python -m benchmarks.acl`` (``--seconds 12`` per window, ``--rounds 3``; ``--quick``: 5 s,
one round). Writes ``benchmarks/results/acl.md`` and ``benchmarks/results/acl.json``.

Each window runs ``psm serve router`` on loopback and a load process with the stack's 500 Hz
control traffic through it, each session authenticated as its role: the arm publishes a
155-byte state every 2 ms; the obstacle monitor answers each state with a prediction, the
planner each prediction with a command, which the arm receives; a recorder session subscribes
to ``<prefix>/**``. Per tick that is 3 messages into the router and 7 out of it (10
access-control decisions). The cases differ only in the router's settings:

* ``no authentication`` — the router as before this issue;
* ``access control, denial log off`` — ``router.access_control`` with ``router.log_denials =
  false`` (zenoh's own enforcement only);
* ``access control + denial log`` — as deployed: zenoh's access-control target at TRACE, read
  and filtered by the router (``services/bus/acl_log.py``): every routed message is a log line
  that zenoh formats and the router drops.

The cases alternate round by round (the machine's load drifts); CPU = utime + stime of the
router from ``/proc`` over the window, % of one core; the table gives the median over rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from services.supervisor import ManagedProcess, cpu_seconds, free_port, psm_argv, wait_port

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

CASES: dict[str, dict[str, str]] = {
    "no authentication": {},
    "access control, denial log off": {"router.access_control": "true",
                                       "router.log_denials": "false"},
    "access control + denial log": {"router.access_control": "true"},
}
STATE_BYTES = 155
PERIOD_S = 0.002


def load(endpoint: str, prefix: str, secrets_dir: str, seconds: float) -> dict[str, int]:
    """The load process: the control loop's traffic for ``seconds`` (see the module
    docstring); ``secrets_dir`` ``""`` = no credentials. Prints ``READY`` when it starts."""
    import zenoh

    from services.bus.config import ServiceConfig, load_config
    from services.bus.credentials import password_file
    from services.bus.messages import Keys
    from services.bus.runtime import open_session

    keys = Keys(prefix)

    def session(role: str) -> Any:
        ov: dict[str, Any] = {"zenoh.mode": "client", "zenoh.connect": [endpoint],
                              "zenoh.multicast": False}
        if secrets_dir:
            ov.update({"zenoh.user": role,
                       "zenoh.password_file": str(password_file(secrets_dir, role))})
        return open_session(load_config(ServiceConfig, env={}, overrides=ov).zenoh)

    arm, monitor, planner, recorder = (session(r) for r in
                                       ("arm", "obstacle_monitor", "planner", "recorder"))
    qos = {"priority": zenoh.Priority.REAL_TIME, "express": True,
           "congestion_control": zenoh.CongestionControl.BLOCK}
    state = arm.declare_publisher(keys.arm_state.key, **qos)
    collision = monitor.declare_publisher(keys.collision.key, **qos)
    command = planner.declare_publisher(keys.arm_command.key, **qos)
    counts = {"states": 0, "commands": 0, "recorded": 0}

    def on_command(_s: Any) -> None:
        counts["commands"] += 1

    def on_any(_s: Any) -> None:
        counts["recorded"] += 1

    subs = [
        monitor.declare_subscriber(keys.arm_state.key, lambda s: collision.put(s.payload.to_bytes()[:40])),
        planner.declare_subscriber(keys.collision.key, lambda s: command.put(s.payload.to_bytes())),
        arm.declare_subscriber(keys.arm_command.key, on_command),
        recorder.declare_subscriber(keys.all.key, on_any),
    ]
    time.sleep(1.0)
    payload = bytes(STATE_BYTES)
    print("READY", flush=True)
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < seconds:
        state.put(payload)
        n += 1
        delay = t0 + n * PERIOD_S - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    counts["states"] = n
    time.sleep(0.5)
    for s in subs:
        s.undeclare()
    for s in (arm, monitor, planner, recorder):
        s.close()
    return counts


def run_case(name: str, seconds: float, workdir: Path, secrets_dir: Path) -> dict[str, Any]:
    """One window of case ``name``: the router's CPU and what the load process counted."""
    settings = dict(CASES[name])
    secured = bool(settings)
    if secured:
        settings["router.users_file"] = json.dumps(str(secrets_dir / "users.txt"))
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"bench{port}"
    sets = [a for k, v in settings.items() for a in ("--set", f"{k}={v}")]
    router = ManagedProcess("router", psm_argv(["serve", "router", "--listen", endpoint,
                                                "--no-multicast", "--prefix", prefix, *sets]),
                            workdir / f"router-{port}.log")
    loader = None
    try:
        wait_port(port, 30.0, router)
        loader = ManagedProcess(
            "load",
            [sys.executable, "-m", "benchmarks.acl", "--load", endpoint, prefix,
             str(secrets_dir) if secured else "", str(seconds)],
            workdir / f"load-{port}.log",
        )
        deadline = time.monotonic() + 60
        while "READY" not in loader.log_text() and time.monotonic() < deadline and loader.alive():
            time.sleep(0.05)
        if "READY" not in loader.log_text():
            raise RuntimeError(f"load did not start: {loader.log_tail()}")
        cpu0, t0 = cpu_seconds(router.pid), time.monotonic()
        if loader.wait(seconds + 60) is None:
            raise RuntimeError(f"load did not finish: {loader.log_tail()}")
        cpu1, t1 = cpu_seconds(router.pid), time.monotonic()
        counts = json.loads(loader.log_text().strip().splitlines()[-1])
    finally:
        if loader is not None:
            loader.stop()
        router.stop()
    log = router.log_text()
    lines = None
    for line in log.splitlines():
        if "access-control summary" in line and "zenoh_log_lines=" in line:
            lines = int(line.rsplit("zenoh_log_lines=", 1)[1].split()[0])
    assert cpu0 is not None and cpu1 is not None
    return {"cpu_pct": 100.0 * (cpu1 - cpu0) / (t1 - t0), "window_s": round(t1 - t0, 2),
            "denials_logged": log.count("access denied"), "zenoh_log_lines": lines, **counts}


def write_report(res: dict[str, Any], out: Path = RESULTS) -> None:
    """``acl.md`` + ``acl.json``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "acl.json").write_text(json.dumps(res, indent=2))
    base_runs = res["cases"]["no authentication"]
    lines = [
        "# Access-control benchmark: the router's CPU at the stack's 500 Hz control traffic",
        "",
        f"{res['date']} · {res['machine']} · {res['cpus']} CPUs · load average "
        f"{res['loadavg']} at start · {res['rounds']} round(s) of {res['seconds']:g} s windows · "
        "`python -m benchmarks.acl` (method: module docstring). Router CPU = utime + stime from "
        "`/proc/<pid>/stat`, % of one core, median over rounds (all rounds in brackets).",
        "",
        "| case | router CPU % | − no authentication, same round (median) | zenoh log lines "
        "per tick | commands / states |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, s in res["summary"].items():
        runs = res["cases"][name]
        rounds = ", ".join(f"{c['cpu_pct']:.1f}" for c in runs)
        diff = statistics.median(
            c["cpu_pct"] - b["cpu_pct"] for c, b in zip(runs, base_runs, strict=True)
        )
        rate = "—" if s["log_lines_per_tick"] is None else f"{s['log_lines_per_tick']:.1f}"
        lines.append(f"| {name} | {s['cpu_pct']:.1f} ({rounds}) | {diff:+.1f} | {rate} | "
                     f"{s['answered']:.3f} |")
    lines += [
        "",
        f"Denials logged: {sum(s['denials_logged'] for s in res['summary'].values())} (every "
        "session did only what its role allows). Log lines per tick: zenoh's access-control "
        "trace over the router's life (one line per decision, 10 decisions per tick, plus the "
        "handshakes and the permission caches), divided by the ticks of the window; the "
        "router's filter reads each line and drops the allowed ones.",
    ]
    (out / "acl.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    """Run every case (or, with ``--load``, be the load process) and write the report."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="one round of 5 s windows")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--load", nargs=4, metavar=("ENDPOINT", "PREFIX", "SECRETS", "SECONDS"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.load:
        endpoint, prefix, secrets_dir, seconds = args.load
        print(json.dumps(load(endpoint, prefix, secrets_dir, float(seconds))), flush=True)
        return 0
    from services.bus.credentials import write_secrets

    seconds, rounds = (5.0, 1) if args.quick else (args.seconds, args.rounds)
    res: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "loadavg": " ".join(f"{x:.2f}" for x in os.getloadavg()),
        "seconds": seconds,
        "rounds": rounds,
        "cases": {name: [] for name in CASES},
    }
    with tempfile.TemporaryDirectory(prefix="psm-acl-bench-") as tmp:
        work = Path(tmp)
        secrets_dir = write_secrets(work / "secrets").out_dir
        for r in range(rounds):
            for name in CASES:
                print(f"round {r + 1}: {name} ...", flush=True)
                c = run_case(name, seconds, work, secrets_dir)
                res["cases"][name].append(c)
                print(json.dumps(c), flush=True)
    res["summary"] = {}
    for name, runs in res["cases"].items():
        lines = [c["zenoh_log_lines"] / c["states"] for c in runs if c["zenoh_log_lines"]]
        res["summary"][name] = {
            "cpu_pct": statistics.median(c["cpu_pct"] for c in runs),
            "log_lines_per_tick": statistics.median(lines) if lines else None,
            "answered": statistics.median(c["commands"] / max(1, c["states"]) for c in runs),
            "denials_logged": sum(c["denials_logged"] for c in runs),
        }
    write_report(res, args.out)
    print((args.out / "acl.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
