"""The feeding stack's platform floor: every process's bus traffic without its work.

The reference the whole feeding stack's CPU (``benchmarks.planner`` part d) is read against, in
the same run: what the stack's messages cost on this machine before any service does anything
with them. Each process of ``configs/stack.toml`` is replaced by a *null service*
(:func:`null_service_main`) on the same service skeleton (``services.bus.runtime.Service``:
session, liveliness token, ``ServiceStatus``) and the same bus topology (peers linked directly,
the real ``psm serve router`` for discovery), which

* subscribes to what the real process subscribes to (:func:`traffic`, after the access-control
  roles table :func:`services.bus.acl.roles`), each sample copied out of zenoh on its receive
  thread (:func:`services.bus.runtime.receive_thread_handler`) and dropped;
* publishes what the real process publishes, with the topic's QoS (``Service.publisher``) and a
  payload recorded from a real stack run (of each key the sample of median size, so the sizes
  are real: a 21 kB JPEG frame, a 0.4 kB arm state), either in answer to an input as the real
  process does (a command per arm state, a prediction per arm state, the tracker's four outputs
  per frame, a frame every n-th arm state) or at the rate the recording shows, by the wall
  clock.

The profile (:func:`traffic_profile`) is read from the recording of the real run: per key its
rate over the span of the planner's commands (the task), its encoding and its median-size
payload. One-off messages (the arm's model, the obstacle set, the scene, a gripper command)
are left out. The null services run at normal scheduling (the real arm and planner at
``SCHED_FIFO``).

    profile = traffic_profile(Path("run.mcap"))
    res = run_null_stack(profile, seconds=15.0, warmup_s=3.0, workdir=Path("/tmp/null"))
    res["cpu_pct"]          # per process, % of one core
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.bus.messages import Keys

#: The stack's processes (``configs/stack.toml`` names, the access-control roles).
PROCESSES = ("recorder", "arm", "camera", "goal_tracker", "obstacle_monitor", "planner")


@dataclass(frozen=True)
class Traffic:
    """One process's bus traffic, as key expressions of its cell: ``service``, the name of its
    liveliness token and status; ``subscribes``, what it subscribes to; ``answers``, what it
    publishes in answer to an input (output → (input, every n-th input; ``0``: n from the two
    recorded rates)); ``timed``, what it publishes at the recorded rate."""

    service: str
    subscribes: tuple[str, ...]
    answers: Mapping[str, tuple[str, int]]
    timed: tuple[str, ...] = ()


def traffic(keys: Keys) -> dict[str, Traffic]:
    """Each process's :class:`Traffic` in the cell ``keys``: its subscriptions and service name
    from :func:`services.bus.acl.roles` (the recorder's history selectors left out: its
    ``<prefix>/**`` covers them), its outputs from the services' code."""
    from services.bus.acl import roles

    table = roles(keys)
    k = keys

    def subs(role: str) -> tuple[str, ...]:
        topics = table[role].subscribes
        return (k.all.key,) if k.all in topics else tuple(t.key for t in topics)

    state, images = k.arm_state.key, k.camera_images_all.key
    outputs: dict[str, tuple[dict[str, tuple[str, int]], tuple[str, ...]]] = {
        "recorder": ({}, ()),
        "arm": ({}, (state, k.arm_transforms.key)),
        "camera": ({images: (state, 0)}, ()),
        "goal_tracker": ({t.key: (images, 1) for t in (k.goals_all, k.vision_faces, k.camera_annotations_all,
                                                        k.viz_goals_all)}, ()),
        "obstacle_monitor": ({k.collision.key: (state, 1)}, ()),
        "planner": ({k.arm_command.key: (state, 1)},
                    tuple(t.key for t in (k.planner_status, k.viz_plan, k.planner_goal, k.task_events))),
    }
    return {role: Traffic(table[role].services[0], subs(role), answers, timed)
            for role, (answers, timed) in outputs.items()}


def _matches(expr: str, key: str) -> bool:
    """Whether the concrete ``key`` lies in the key expression ``expr``."""
    import zenoh

    return bool(zenoh.KeyExpr(expr).intersects(zenoh.KeyExpr(key)))


def _outputs(t: Traffic) -> tuple[str, ...]:
    return (*t.answers, *t.timed)


def traffic_profile(recording: Path) -> dict[str, Any]:
    """``{"span_s", "keys": {key: {"encoding", "rate_hz", "payload_hex"}}}``: every key a
    recording of the stack holds that some process of :func:`traffic` publishes, the keys
    relative to the cell's prefix (read from the commands' key). Rates are counts over the span
    of the planner's commands (the task: every process active); the payload is the sample of
    median size."""
    from services.bus.log import read_samples

    times: dict[str, list[int]] = {}
    payloads: dict[str, list[bytes]] = {}
    encoding: dict[str, str] = {}
    for s in read_samples(recording, quiet=True):
        times.setdefault(s.topic, []).append(s.log_time_ns)
        payloads.setdefault(s.topic, []).append(s.payload)
        encoding[s.topic] = s.encoding
    command = Keys("cell").arm_command.key[len("cell"):]  # "/arm/command"
    prefix = next((key[: -len(command)] for key in times if key.endswith(command)), None)
    if prefix is None:
        raise ValueError(f"{recording}: no command stream to take the rates over")
    table = traffic(Keys(prefix))
    exprs = [e for t in table.values() for e in _outputs(t)]
    wanted = {key for key in times if any(_matches(e, key) for e in exprs)}
    missing = sorted(e for e in exprs if not any(_matches(e, key) for key in wanted))
    if missing:
        raise ValueError(f"{recording}: no sample of {', '.join(missing)}")
    t_cmd = times[prefix + command]
    t0, t1 = t_cmd[0], t_cmd[-1]
    if t1 <= t0:
        raise ValueError(f"{recording}: no command stream to take the rates over")
    span_s = (t1 - t0) * 1e-9
    keys = {}
    for key in sorted(wanted):
        median = sorted(payloads[key], key=len)[len(payloads[key]) // 2]
        keys[key[len(prefix) + 1 :]] = {
            "encoding": encoding[key],
            "rate_hz": sum(1 for t in times[key] if t0 <= t <= t1) / span_s,
            "payload_hex": median.hex(),
        }
    return {"span_s": span_s, "keys": keys}


def null_service_main(argv: list[str]) -> int:
    """One null service (``--role`` one of :data:`PROCESSES`, ``--profile`` a
    :func:`traffic_profile` JSON file; the bus flags of any service). Runs until SIGTERM."""
    from services.bus.config import ServiceConfig, add_config_arguments, config_from_args
    from services.bus.runtime import Service, ServiceApp, receive_thread_handler, run_service

    ap = argparse.ArgumentParser()
    ap.add_argument("--role", choices=PROCESSES, required=True)
    ap.add_argument("--profile", type=Path, required=True)
    ap.add_argument("--counts", type=Path, required=True, help="JSON file of the counts, at exit")
    add_config_arguments(ap)
    args = ap.parse_args(argv)
    cfg = config_from_args(ServiceConfig, args)
    profile = json.loads(args.profile.read_text())["keys"]
    service_name = traffic(Keys(cfg.prefix))[args.role].service

    class NullService(ServiceApp):
        name = service_name

        def __init__(self, config: ServiceConfig) -> None:
            super().__init__(config)
            self.received: dict[str, list[int]] = {}  # input key expression -> [count]
            self.published: dict[str, list[int]] = {}  # output key -> [count]
            self.loop_t0: float | None = None  # time.monotonic() at the loop's start [s]

        def setup(self, svc: Service) -> None:
            prefix = svc.keys.prefix
            mine = traffic(svc.keys)[args.role]

            def recorded(expr: str) -> list[str]:
                """The recorded keys in ``expr``, absolute."""
                return [f"{prefix}/{rel}" for rel in profile if _matches(expr, f"{prefix}/{rel}")]

            def publisher(key: str) -> tuple[Any, bytes, float, list[int]]:
                topic = svc.keys.topic_for_key(key)
                if topic is None:
                    raise SystemExit(f"null service: {key} is not a catalogue key")
                rel = profile[key[len(prefix) + 1 :]]
                return (svc.publisher(topic, key), bytes.fromhex(rel["payload_hex"]), rel["rate_hz"],
                        self.published.setdefault(key[len(prefix) + 1 :], [0]))

            state_rate = profile[svc.keys.arm_state.key[len(prefix) + 1 :]]["rate_hz"]
            by_input: dict[str, list[tuple[Any, bytes, int, list[int]]]] = {}
            for out, (inp, every) in mine.answers.items():
                for key in recorded(out):
                    pub, payload, rate, sent = publisher(key)
                    n = every or max(1, round(state_rate / rate))
                    by_input.setdefault(inp, []).append((pub, payload, n, sent))
            self.timed = [publisher(key) for expr in mine.timed for key in recorded(expr)]
            for inp in mine.subscribes:
                rel = inp[len(prefix) + 1 :]
                handler = self._handler(by_input.get(inp, []), self.received.setdefault(rel, [0]))
                svc.on_close(svc.session.declare_subscriber(inp, receive_thread_handler(handler)).undeclare)

        @staticmethod
        def _handler(outs: list[tuple[Any, bytes, int, list[int]]], n: list[int]) -> Any:
            def on_sample(sample: Any) -> None:
                sample.payload.to_bytes()
                n[0] += 1
                for pub, payload, every, sent in outs:
                    if n[0] % every == 0:
                        pub.put_bytes(payload)
                        sent[0] += 1

            return on_sample

        def loop(self, svc: Service) -> None:
            self.loop_t0 = time.monotonic()
            if not self.timed:
                svc.stop_event.wait()
                return
            t0 = self.loop_t0
            while not svc.stop_event.is_set():
                due = [t0 + (sent[0] + 1) / rate for _p, _b, rate, sent in self.timed]
                i = min(range(len(due)), key=due.__getitem__)
                wait = due[i] - time.monotonic()
                if wait > 0 and svc.stop_event.wait(wait):
                    return
                pub, payload, _rate, sent = self.timed[i]
                pub.put_bytes(payload)
                sent[0] += 1

        def teardown(self, svc: Service) -> None:
            loop_s = 0.0 if self.loop_t0 is None else time.monotonic() - self.loop_t0
            args.counts.write_text(json.dumps({
                "loop_s": round(loop_s, 3),
                "received": {k: v[0] for k, v in self.received.items()},
                "published": {k: v[0] for k, v in self.published.items()},
            }))

    return run_service(NullService(cfg))


def run_null_stack(profile: Mapping[str, Any], *, seconds: float, warmup_s: float,
                   workdir: Path) -> dict[str, Any]:
    """Start the real router and one null service per process of :data:`PROCESSES` on a fresh
    loopback port, in the stack's start order and each after the previous one is alive; from the
    last one alive, wait ``warmup_s``, measure each process's CPU over ``seconds``
    (``/proc/<pid>/stat``, % of one core), stop them in reverse order. Returns ``{"window_s",
    "cpu_pct", "total_pct", "alive_during_window", "counts", "ran_s", "logs_tail"}``: ``ran_s``
    [s] from the last one alive to the start of the stop (all of them alive); ``counts``, per
    null service, the samples it received per subscription and published per key over its whole
    run (start-up included) and ``loop_s`` [s], how long its loop ran (the timed keys' rates hold
    over that time)."""
    from benchmarks.stack import bus_flags, stack_header
    from services.stack import load_stack
    from services.supervisor import ManagedProcess, Supervisor, cpu_seconds, free_port

    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / "profile.json").write_text(json.dumps(profile))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stack_file = workdir / "router.toml"
    stack_file.write_text(stack_header("null stack", endpoint, workdir)
                          + '[[stack.processes]]\nname = "router"\ncommand = ["serve", "router"]\n\n'
                          + f"[router]\nlisten = [{json.dumps(endpoint)}]\n")
    sup = Supervisor(load_stack(stack_file), out=io.StringIO(), live=False)
    procs: dict[str, ManagedProcess] = {}
    try:
        sup.start()
        procs["router"] = sup.rows[0].proc
        bus = [*bus_flags(endpoint), "--log-level", "WARNING"]
        names = traffic(Keys(sup.cfg.prefix))
        for role in PROCESSES:  # each one after the previous is alive, as the supervisor starts a stack
            procs[role] = ManagedProcess(
                role, [sys.executable, "-m", "benchmarks.null_stack", "--role", role, "--profile",
                       str(workdir / "profile.json"), "--counts", str(workdir / f"null_{role}.json"),
                       *bus], workdir / f"null_{role}.log")
            sup.wait_alive(names[role].service, procs[role])
        t_start = time.monotonic()
        time.sleep(warmup_s)
        before = {n: cpu_seconds(p.pid) or 0.0 for n, p in procs.items()}
        t0 = time.monotonic()
        time.sleep(seconds)
        window = time.monotonic() - t0
        after = {n: cpu_seconds(p.pid) or 0.0 for n, p in procs.items()}
        alive = {n: p.poll() is None for n, p in procs.items()}
        ran_s = time.monotonic() - t_start
    finally:
        for name, proc in reversed(procs.items()):
            if name != "router":
                proc.stop(15)
        sup.shutdown()
    cpu = {n: round(100.0 * (after[n] - before[n]) / window, 1) for n in procs}
    logs = {n: (workdir / f"null_{n}.log").read_text(errors="replace")[-2000:]
            for n in PROCESSES if (workdir / f"null_{n}.log").exists()}
    counts = {n: json.loads((workdir / f"null_{n}.json").read_text())
              for n in PROCESSES if (workdir / f"null_{n}.json").exists()}
    return {
        "window_s": round(window, 2),
        "cpu_pct": cpu,
        "total_pct": round(sum(cpu.values()), 1),
        "alive_during_window": alive,
        "counts": counts,
        "ran_s": round(ran_s, 2),
        # A traceback or a one-line error of the service skeleton (zenoh's own log lines aside).
        "logs_tail": {n: t for n, t in logs.items() if "Traceback" in t or ": error:" in t},
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.null_stack --role ROLE --profile FILE [bus flags]``: one null
    service (started by :func:`run_null_stack`); ``python -m benchmarks.null_stack RUN.mcap``:
    the null stack of that recording's traffic, CPU printed as JSON."""
    argv = sys.argv[1:] if argv is None else argv
    if "--role" in argv:
        return null_service_main(argv)
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("recording", type=Path, help="a recording of the feeding stack (psm up --record)")
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    args = ap.parse_args(argv)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="null-stack-") as tmp:
        res = run_null_stack(traffic_profile(args.recording), seconds=args.seconds,
                             warmup_s=args.warmup, workdir=Path(tmp))
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
