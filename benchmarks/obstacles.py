"""Obstacle benchmark: the segment test (psm.obstacles) and the whole-arm clearance
(services.robot.clearance) for 1, 10 and 100 obstacles, against coal and python-fcl in the same run.

Run from the repository root::

    .venv/bin/python -m benchmarks.obstacles            # full run
    .venv/bin/python -m benchmarks.obstacles --quick    # few repetitions (smoke test)

Writes ``obstacles.md`` and ``obstacles.json`` into ``--out`` (default ``benchmarks/results``).

Method
------
- Scene: ``n`` obstacles (boxes, spheres, cylinders in turn; random orientation; edges/diameters
  4–30 cm) in the arm's workspace (x, y ∈ [−0.8, 0.8] m outside a 0.3 m radius around the base
  axis, z ∈ [0, 1] m), safety margin 2 cm, fixed seeds. Segment queries: random start/goal pairs in
  the same box (as the planner's EE → goal segments), the same queries for every peer.
- Segment test peers: ``psm`` = :func:`psm.obstacles.segment_check` (first hit along the segment,
  entry point, normal, stop axes); ``coal`` / ``fcl`` = a capsule of radius 1 nm along the segment
  against the same inflated shapes in a dynamic AABB tree manager (``collide`` with the default
  callback: a yes/no answer only, stopping at the first pair found). The capsules and their
  transforms are built before timing (this favours the peers). ``psm moving`` = the same test with
  20 % of the obstacles moving at 0.3 m/s over a 0.5 s horizon (swept copies).
- Clearance peers at random joint states within the limits: ``hull + broad phase`` =
  :meth:`ArmClearance.check` (exact per-link minimum on the convex hulls, cutoff ∞ or 0.3 m);
  ``hull brute`` = every (geometry, obstacle) pair on the hulls; ``BVH brute`` = every pair on the
  original BVH meshes with coal (the straightforward use of coal).
- Timing: ``time.perf_counter`` around each call, peers interleaved round by round so they see
  the same machine load; p50/p99 per call. Ratios are to the ``psm`` row measured in the same run.
- CPU per call: ``time.process_time`` over each peer's block of calls / calls (the wall times
  include the time other jobs of the shared machine held the core; the CPU time does not).
- Decimation: CPU of a 500 Hz monitor that checks every ``N`` ticks = CPU per check / (N · 2 ms);
  the extra clearance needed for the ``N − 1`` unchecked ticks plus stopping is
  ``v N dt + v² / (2 a)`` (``docs/obstacles.md``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from psm.obstacles import Obstacle, compile_obstacles, segment_check

#: Segment test target: per call with 100 obstacles [µs] (p50).
TARGET_SEGMENT_US = 50.0
#: Monitor target: CPU share of one core at 500 Hz with 10 obstacles.
TARGET_MONITOR_CPU = 0.20
MONITOR_RATE_HZ = 500.0
#: Speed and deceleration used for the decimation margin: the Panda's Cartesian limits
#: (1.7 m/s translation, 13 m/s² translational acceleration).
V_MAX_M_S = 1.7
A_MAX_M_S2 = 13.0
MARGIN_M = 0.02
COUNTS = (1, 10, 100)
DECIMATIONS = (1, 2, 5, 10, 25)


# ---------------------------------------------------------------------------- scenes (pure)
def make_obstacles(n: int, seed: int, moving_fraction: float = 0.0, speed: float = 0.0) -> list[Obstacle]:
    """``n`` obstacles in the arm's workspace (see the module doc); a ``moving_fraction`` of them
    moves at ``speed`` [m/s] in a random horizontal direction."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        while True:
            p = rng.uniform([-0.8, -0.8, 0.0], [0.8, 0.8, 1.0])
            if math.hypot(p[0], p[1]) > 0.3:
                break
        v = np.zeros(3)
        if rng.uniform() < moving_fraction:
            a = rng.uniform(0.0, 2.0 * math.pi)
            v = speed * np.array([math.cos(a), math.sin(a), 0.0])
        out.append(Obstacle(f"o{i}", ("box", "sphere", "cylinder")[i % 3], p,
                            Rotation.random(random_state=rng).as_quat(), rng.uniform(0.04, 0.3, 3), v))
    return out


def make_segments(k: int, seed: int) -> np.ndarray:
    """``(k, 2, 3) [m]`` start/goal pairs in the workspace box."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.8, -0.8, 0.0], [0.8, 0.8, 1.0], size=(k, 2, 3))


def inflated_dims(o: Obstacle, margin: float) -> tuple[str, tuple[float, ...]]:
    """Constructor arguments of the inflated obstacle as a coal/fcl shape (full box edges; sphere
    radius; cylinder radius and full length), with :func:`psm.obstacles.compile_obstacles`'s
    inflation (half extents + margin)."""
    if o.shape == "box":
        return "box", tuple(float(s) + 2.0 * margin for s in o.size)
    if o.shape == "sphere":
        return "sphere", (0.5 * float(o.size[0]) + margin,)
    return "cylinder", (0.5 * float(o.size[0]) + margin, float(o.size[2]) + 2.0 * margin)


def capsule_pose(start: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Rotation ``(3, 3)``, centre ``(3,)`` and length of a capsule (axis local z) on the segment."""
    d = goal - start
    L = float(np.linalg.norm(d))
    if L == 0.0:
        return np.eye(3), start.copy(), 0.0
    rot, _ = Rotation.align_vectors([d / L], [[0.0, 0.0, 1.0]])
    return rot.as_matrix(), 0.5 * (start + goal), L


# ---------------------------------------------------------------------------- statistics (pure)
def summarize(times_s: Sequence[float]) -> dict[str, float]:
    """min/p50/p99/mean [µs] and count of per-call times [s] (the minimum is the cost without
    interference from other jobs)."""
    a = np.asarray(times_s, dtype=float) * 1e6
    return {"min_us": float(a.min()), "p50_us": float(np.percentile(a, 50)),
            "p99_us": float(np.percentile(a, 99)), "mean_us": float(a.mean()), "n": int(a.size)}


def cpu_fraction(cost_us: float, rate_hz: float, decimation: int) -> float:
    """Share of one core spent by a check of ``cost_us`` run every ``decimation`` ticks at ``rate_hz``."""
    return cost_us * 1e-6 * rate_hz / decimation


def stop_margin_m(v: float, a: float, dt: float, decimation: int) -> float:
    """Clearance to keep [m] when the check runs every ``decimation`` ticks of ``dt`` [s]: the
    distance covered at ``v`` [m/s] between two checks plus the braking distance at ``a`` [m/s²]."""
    return v * decimation * dt + v * v / (2.0 * a)


def decimation_table(cost_us: float, rate_hz: float = MONITOR_RATE_HZ, v: float = V_MAX_M_S,
                     a: float = A_MAX_M_S2,
                     decimations: Sequence[int] = DECIMATIONS) -> list[dict[str, float]]:
    """Per decimation ``N``: CPU share, check period [ms] and stop margin [m]."""
    dt = 1.0 / rate_hz
    return [{"N": n, "period_ms": 1e3 * n * dt, "cpu": cpu_fraction(cost_us, rate_hz, n),
             "margin_m": stop_margin_m(v, a, dt, n)} for n in decimations]


def recommend_decimation(table: list[dict[str, float]], target_cpu: float = TARGET_MONITOR_CPU,
                         headroom: float = 2.0) -> int:
    """The smallest ``N`` whose CPU share is within the target with ``headroom`` (×) to spare."""
    for row in table:
        if row["cpu"] * headroom <= target_cpu:
            return int(row["N"])
    return int(table[-1]["N"])


def verdict(value: float, target: float) -> str:
    """"met" if ``value ≤ target`` else "missed"."""
    return "met" if value <= target else "missed"


def ratio(value: float, reference: float) -> float:
    """``value / reference`` (inf if the reference is 0)."""
    return value / reference if reference > 0.0 else math.inf


# ---------------------------------------------------------------------------- peers
def _fcl_available() -> tuple[Any, str]:
    try:
        import fcl  # type: ignore[import-not-found]
    except ImportError as exc:
        return None, f"not installed ({exc})"
    from importlib.metadata import version
    return fcl, version("python-fcl")


def _coal_segment_peer(obstacles: list[Obstacle], segs: np.ndarray) -> Callable[[int], bool]:
    import coal

    make = {"box": coal.Box, "sphere": coal.Sphere, "cylinder": coal.Cylinder}
    manager = coal.DynamicAABBTreeCollisionManager()
    keep = []
    for o in obstacles:
        kind, dims = inflated_dims(o, MARGIN_M)
        obj = coal.CollisionObject(make[kind](*dims), coal.Transform3s(o.rotation, o.position))
        keep.append(obj)
        manager.registerObject(obj)
    manager.setup()
    queries = []
    for s, g in segs:
        R, c, L = capsule_pose(s, g)
        obj = coal.CollisionObject(coal.Capsule(1e-9, L), coal.Transform3s(R, c))
        obj.computeAABB()
        queries.append(obj)
    cb = coal.CollisionCallBackDefault()

    def run(k: int) -> bool:
        cb.data.result.clear()
        cb.data.done = False
        manager.collide(queries[k], cb)
        return bool(cb.data.result.isCollision())

    run.keep = (keep, queries, manager)  # type: ignore[attr-defined]
    return run


def _fcl_segment_peer(fcl: Any, obstacles: list[Obstacle], segs: np.ndarray) -> Callable[[int], bool]:
    make = {"box": fcl.Box, "sphere": fcl.Sphere, "cylinder": fcl.Cylinder}
    manager = fcl.DynamicAABBTreeCollisionManager()
    objs = []
    for o in obstacles:
        kind, dims = inflated_dims(o, MARGIN_M)
        objs.append(fcl.CollisionObject(make[kind](*dims), fcl.Transform(o.rotation, o.position)))
    manager.registerObjects(objs)
    manager.setup()
    queries = []
    for s, g in segs:
        R, c, L = capsule_pose(s, g)
        queries.append(fcl.CollisionObject(fcl.Capsule(1e-9, L), fcl.Transform(R, c)))
    request = fcl.CollisionRequest()

    def run(k: int) -> bool:
        data = fcl.CollisionData(request=request)
        manager.collide(queries[k], data, fcl.defaultCollisionCallback)
        return bool(data.result.is_collision)

    run.keep = (objs, queries, manager)  # type: ignore[attr-defined]
    return run


def _time_interleaved(peers: dict[str, Callable[[int], Any]], k: int, rounds: int) -> tuple[
        dict[str, list[float]], dict[str, list[Any]], dict[str, float]]:
    """Run every peer on queries ``0..k−1``, ``rounds`` times, peers interleaved per round.

    Returns the wall time of every call [s], the first round's answers and the CPU time of this
    process per call [s] (``time.process_time``: what the calls cost a core, without the time
    other jobs held it)."""
    times: dict[str, list[float]] = {name: [] for name in peers}
    answers: dict[str, list[Any]] = {name: [] for name in peers}
    cpu: dict[str, float] = dict.fromkeys(peers, 0.0)
    for r in range(rounds):
        for name, fn in peers.items():
            c0 = time.process_time()
            for i in range(k):
                t0 = time.perf_counter()
                out = fn(i)
                times[name].append(time.perf_counter() - t0)
                if r == 0:
                    answers[name].append(out)
            cpu[name] += time.process_time() - c0
    return times, answers, {name: c / (k * rounds) for name, c in cpu.items()}


def bench_segments(n: int, k: int, rounds: int, fcl: Any) -> dict[str, Any]:
    obstacles = make_obstacles(n, seed=100 + n)
    segs = make_segments(k, seed=7)
    compiled = compile_obstacles(obstacles, MARGIN_M)
    moving = compile_obstacles(make_obstacles(n, seed=100 + n, moving_fraction=0.2, speed=0.3), MARGIN_M)
    peers: dict[str, Callable[[int], Any]] = {
        "psm": lambda i: segment_check(segs[i, 0], segs[i, 1], compiled).collision,
        "psm moving (H = 0.5 s)":
            lambda i: segment_check(segs[i, 0], segs[i, 1], moving, horizon_s=0.5).collision,
        "coal (capsule, AABB tree)": _coal_segment_peer(obstacles, segs),
    }
    if fcl is not None:
        peers["fcl (capsule, AABB tree)"] = _fcl_segment_peer(fcl, obstacles, segs)
    for fn in peers.values():  # warm up (caches, lazy initialisation)
        for i in range(min(k, 50)):
            fn(i)
    times, answers, cpu = _time_interleaved(peers, k, rounds)
    stats = {name: summarize(t) | {"cpu_us": 1e6 * cpu[name]} for name, t in times.items()}
    ref = answers["psm"]
    agree = {name: float(np.mean([a == b for a, b in zip(ans, ref, strict=True)]))
             for name, ans in answers.items() if not name.startswith("psm")}
    return {"obstacles": n, "queries": k, "rounds": rounds, "hit_rate": float(np.mean(ref)),
            "stats": stats, "agreement_with_psm": agree}


#: The obstacle monitor's check: the smallest distance and its link only (``per_link=False``).
SMALLEST_ONLY = "hull + broad phase, smallest only (cutoff ∞; the monitor's)"


def bench_clearance(n: int, k: int, rounds: int, bvh_k: int) -> dict[str, Any]:
    from services.robot.clearance import ArmClearance
    from services.robot.model import RobotModel

    robot = RobotModel.load()
    obstacles = make_obstacles(n, seed=200 + n)
    rng = np.random.default_rng(3)
    Q = rng.uniform(robot.limits.lower, robot.limits.upper, size=(k, robot.n))
    exact = ArmClearance(robot, margin_m=MARGIN_M, cutoff_m=math.inf)
    cut = ArmClearance(robot, margin_m=MARGIN_M, cutoff_m=0.3)
    bvh = ArmClearance(robot, margin_m=MARGIN_M, cutoff_m=math.inf, convex=False)
    for a in (exact, cut, bvh):
        a.set_obstacles(obstacles)
    peers: dict[str, Callable[[int], Any]] = {
        "hull + broad phase (cutoff ∞)": lambda i: exact.check(Q[i]),
        SMALLEST_ONLY: lambda i: exact.check(Q[i], per_link=False),
        "hull + broad phase (cutoff 0.3 m)": lambda i: cut.check(Q[i]),
        "hull brute": lambda i: exact.check_brute(Q[i]),
    }
    for fn in peers.values():
        for i in range(min(k, 10)):
            fn(i)
    times, answers, cpu = _time_interleaved(peers, k, rounds)
    bvh_times, bvh_answers, bvh_cpu = _time_interleaved(
        {"BVH brute (coal)": lambda i: bvh.check_brute(Q[i])}, bvh_k, 1)
    times.update(bvh_times)
    cpu.update(bvh_cpu)
    stats = {name: summarize(t) | {"cpu_us": 1e6 * cpu[name]} for name, t in times.items()}
    ref = answers["hull + broad phase (cutoff ∞)"]
    brute = answers["hull brute"]
    max_dev = max(float(np.max(np.abs(a.per_link - b.per_link))) for a, b in zip(ref, brute, strict=True))
    meshes = bvh_answers["BVH brute (coal)"]
    mesh_minus_hull = [b.min_distance_m - a.min_distance_m for a, b in zip(ref, meshes, strict=False)]
    pairs = float(np.mean([r.pairs_evaluated for r in ref]))
    alone = answers[SMALLEST_ONLY]
    alone_dev = max(abs(a.min_distance_m - b.min_distance_m) if math.isfinite(b.min_distance_m) else 0.0
                    for a, b in zip(alone, brute, strict=True))
    return {"obstacles": n, "states": k, "rounds": rounds, "bvh_states": bvh_k,
            "geometries": exact.n_geometries,
            "stats": stats, "broad_vs_brute_max_abs_m": max_dev, "pairs_evaluated_mean": pairs,
            "smallest_only_pairs_mean": float(np.mean([r.pairs_evaluated for r in alone])),
            "smallest_only_vs_brute_max_abs_m": alone_dev,
            "mesh_minus_hull_min_m": float(np.mean(mesh_minus_hull)) if mesh_minus_hull else math.nan}


# ---------------------------------------------------------------------------- report
def render_markdown(report: dict[str, Any]) -> str:
    m = report["machine"]
    lines = [
        "# Obstacle benchmark",
        "",
        f"Run {m['date_utc']} on {m['cpus']} CPUs ({m['machine']}, {m['platform']}), Python {m['python']}, "
        f"coal {m['coal']}, python-fcl {m['fcl']}. Command: `{m['command']}`. 1-min load average "
        f"before/after: {m['load_before']} / {m['load_after']} (the machine is shared with other jobs).",
        "",
        f"Safety margin {MARGIN_M * 100:.0f} cm. Per-call wall time; peers interleaved round by round. "
        "Ratios: peer time / psm time, same run.",
        "",
        "## Segment test",
        "",
        "| obstacles | peer | min µs | p50 µs | p99 µs | CPU µs/call | ratio p50 | agrees with psm "
        "| hit rate |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for case in report["segments"]:
        ref = case["stats"]["psm"]["p50_us"]
        for name, s in case["stats"].items():
            agree = case["agreement_with_psm"].get(name)
            lines.append(f"| {case['obstacles']} | {name} | {s['min_us']:.1f} | {s['p50_us']:.1f} | "
                         f"{s['p99_us']:.1f} | {s['cpu_us']:.1f} | {ratio(s['p50_us'], ref):.2f} | "
                         f"{'—' if agree is None else f'{100 * agree:.1f} %'} | "
                         f"{100 * case['hit_rate']:.0f} % |")
    lines += [
        "",
        "coal and fcl answer only *whether* the capsule touches an obstacle (and stop at the first pair "
        "found); psm also returns the first obstacle along the segment, the entry point and normal, and "
        "the stop axes. Disagreements are segments that graze an inflated surface within the capsule's "
        "1 nm radius or the solvers' tolerances.",
        "",
        "## Whole-arm clearance",
        "",
        "| obstacles | method | min µs | p50 µs | p99 µs | CPU µs/call | ratio p50 |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for case in report["clearance"]:
        ref = case["stats"]["hull + broad phase (cutoff ∞)"]["p50_us"]
        for name, s in case["stats"].items():
            lines.append(f"| {case['obstacles']} | {name} | {s['min_us']:.1f} | {s['p50_us']:.1f} | "
                         f"{s['p99_us']:.1f} | {s['cpu_us']:.1f} | {ratio(s['p50_us'], ref):.2f} |")
    lines += ["", "| obstacles | geometries | exact pairs per check (broad phase, mean): per link / "
              "smallest only | max deviation from brute force: per link / smallest | "
              "mean (mesh − hull) min distance |",
              "|---:|---:|---:|---:|---:|"]
    for case in report["clearance"]:
        lines.append(f"| {case['obstacles']} | {case['geometries']} | {case['pairs_evaluated_mean']:.1f} / "
                     f"{case['smallest_only_pairs_mean']:.1f} of {case['geometries'] * case['obstacles']} | "
                     f"{case['broad_vs_brute_max_abs_m']:.1e} / "
                     f"{case['smallest_only_vs_brute_max_abs_m']:.1e} m | "
                     f"{1e3 * case['mesh_minus_hull_min_m']:.1f} mm |")
    d = report["decimation"]
    lines += [
        "",
        f"## Monitor decimation (500 Hz, 10 obstacles, check CPU {d['cost_us']:.0f} µs, wall p99 "
        f"{d['cost_p99_us']:.0f} µs)",
        "",
        f"Stop margin = v N dt + v²/(2a) with v = {V_MAX_M_S} m/s, a = {A_MAX_M_S2} m/s².",
        "",
        "| N | period ms | CPU of one core | stop margin m |",
        "|---:|---:|---:|---:|",
    ]
    for row in d["table"]:
        lines.append(f"| {row['N']} | {row['period_ms']:.0f} | {100 * row['cpu']:.1f} % | "
                     f"{row['margin_m']:.3f} |")
    lines += ["", f"Recommended: N = {d['recommended']} (CPU within the target with 2× headroom for the p99 "
              "and a loaded machine).", "", "## Targets", "", "| target | value | verdict |",
              "|---|---:|---|"]
    for t in report["targets"]:
        lines.append(f"| {t['name']} | {t['value']} | **{t['verdict']}** |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few repetitions (smoke test)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    import coal

    fcl, fcl_version = _fcl_available()
    load_before = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    seg_k, seg_rounds = (60, 1) if args.quick else (1000, 3)
    cl_k, cl_rounds = (6, 1) if args.quick else (200, 3)
    segments = [bench_segments(n, seg_k, seg_rounds, fcl) for n in COUNTS]
    clearance = []
    for n in COUNTS:
        bvh_k = 2 if args.quick else (30 if n < 100 else 8)
        clearance.append(bench_clearance(n, cl_k, cl_rounds, bvh_k))
    ten = next(c for c in clearance if c["obstacles"] == 10)["stats"][SMALLEST_ONLY]  # the monitor's check
    table = decimation_table(ten["cpu_us"])
    rec = recommend_decimation(table)
    seg100 = next(c for c in segments if c["obstacles"] == 100)["stats"]["psm"]["p50_us"]
    rec_cpu = next(r["cpu"] for r in table if r["N"] == rec)
    targets = [
        {"name": "segment test, 100 obstacles, p50 ≤ 50 µs", "value": f"{seg100:.1f} µs",
         "verdict": verdict(seg100, TARGET_SEGMENT_US)},
        {"name": f"whole-arm clearance alone at 500 Hz, 10 obstacles, every N = {rec} ticks, ≤ 20 % of a "
                 "core (the monitor process as a whole: results/monitor.md)",
         "value": f"{100 * rec_cpu:.1f} %", "verdict": verdict(rec_cpu, TARGET_MONITOR_CPU)},
    ]
    report = {
        "machine": {"date_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "cpus": os.cpu_count(),
                    "machine": platform.machine(), "platform": platform.platform(),
                    "python": platform.python_version(), "coal": coal.__version__, "fcl": fcl_version,
                    "command": "python -m benchmarks.obstacles" + (" --quick" if args.quick else ""),
                    "load_before": load_before,
                    "load_after": ", ".join(f"{x:.2f}" for x in os.getloadavg())},
        "params": {"margin_m": MARGIN_M, "v_max_m_s": V_MAX_M_S, "a_max_m_s2": A_MAX_M_S2,
                   "segment_queries": seg_k, "segment_rounds": seg_rounds, "clearance_states": cl_k,
                   "clearance_rounds": cl_rounds},
        "segments": segments,
        "clearance": clearance,
        "decimation": {"cost_us": ten["cpu_us"], "cost_p99_us": ten["p99_us"], "table": table,
                       "recommended": rec},
        "targets": targets,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "obstacles.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    md = render_markdown(report)
    (args.out / "obstacles.md").write_text(md, encoding="utf-8")
    sys.stdout.write(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
