"""The pure parts of the planner benchmark (benchmarks/planner.py): statistics, the status
window, the verdicts on synthetic numbers, the generated task and stack files, the report; and
a short in-process tick-cost replay (no bus, a second of sim time)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from benchmarks.planner import (
    COLD_EVERY,
    LOCKSTEP_RATIO_TARGET,
    MISS_RATIO_TARGET,
    STACK_CPU_TARGET_PCT,
    bench_stack_file,
    cpu_window,
    miss_verdict,
    percentiles,
    pingpong_bound,
    ratio_verdict,
    record_stream,
    render_markdown,
    replay_parts,
    replay_total,
    status_window,
    verdicts,
)
from services.stack import load_stack
from services.tasks.feeding import DEFAULT_FEEDING_CONFIG, static_person_task


def test_percentiles_and_the_pingpong_bound() -> None:
    p = percentiles([100.0] * 99 + [1000.0])
    assert p["p50_us"] == 100.0 and p["max_us"] == 1000.0 and p["n"] == 100
    assert math.isnan(percentiles([])["p50_us"])
    b = pingpong_bound([250.0] * 10)
    assert b["bound_per_s"] == pytest.approx(4000.0)


def test_the_status_window_skips_the_start_and_ends_before_done() -> None:
    samples = [(0.0, 0, "IDLE")]
    samples += [(0.1 * i, 100 * i, "RUNNING") for i in range(1, 31)]  # 1000 ticks/s
    samples += [(3.2, 5000, "DONE"), (3.3, 9999, "DONE")]
    w = status_window(samples, skip_s=0.5)
    assert w["ticks_per_s"] == pytest.approx(1000.0)
    assert w["window_s"] == pytest.approx(2.4)  # first answered tick at 0.1 s: from 0.6 s to 3.0 s
    assert math.isnan(status_window([(0.0, 0, "IDLE")])["ticks_per_s"])


def test_ratio_and_miss_verdicts() -> None:
    ok = ratio_verdict(1600.0, 3000.0, LOCKSTEP_RATIO_TARGET)
    assert ok["ratio"] == pytest.approx(1600 / 3000) and ok["ok"]
    assert not ratio_verdict(1400.0, 3000.0, LOCKSTEP_RATIO_TARGET)["ok"]
    arm = {"missed_ticks": 4, "published_ticks": 9000, "skipped_ticks": 1000}
    m = miss_verdict(arm, {"over_2ms": 2, "n": 10000})
    assert m["ratio"] == pytest.approx(2.0) and m["ok"]  # 4e-4 vs 2e-4: exactly the target
    assert not miss_verdict({**arm, "missed_ticks": 5}, {"over_2ms": 2, "n": 10000})["ok"]
    assert miss_verdict({**arm, "missed_ticks": 0}, {"over_2ms": 0, "n": 10000})["ratio"] == 0.0
    only_arm = miss_verdict(arm, {"over_2ms": 0, "n": 10000})
    assert only_arm["ratio"] == math.inf and not only_arm["ok"]
    assert MISS_RATIO_TARGET == 2.0


def test_cpu_window_ends_at_the_last_sample_with_every_process_alive() -> None:
    samples = [
        (0.0, {"a": 1.0, "b": 2.0}),
        (1.0, {"a": 1.5, "b": 2.1}),
        (2.0, {"a": 2.0, "b": 2.2}),
        (3.0, {"a": None, "b": 2.3}),  # a is gone
    ]
    w = cpu_window(samples)
    assert w["window_s"] == 2.0
    assert w["cpu_pct"] == {"a": 50.0, "b": 10.0}
    assert cpu_window([])["cpu_pct"] == {}


def test_the_bench_stack_file_is_a_valid_stack(tmp_path: Path) -> None:
    task = tmp_path / "task.toml"
    task.write_text(static_person_task(DEFAULT_FEEDING_CONFIG.read_text()))
    arm = {"dt_s": 0.002, "start_pose": "ready", "rt_priority": 50, "watch_services": ["planner"]}
    path = tmp_path / "stack.toml"
    path.write_text(bench_stack_file(endpoint="tcp/127.0.0.1:7999", prefix="pb7999", clock="lockstep",
                                     workdir=tmp_path, task_file=task, arm=arm, planner_rt=50))
    st = load_stack(path)
    assert [p.name for p in st.processes] == ["router", "planner", "arm"]
    assert st.config.clock == "lockstep" and st.config.prefix == "pb7999"
    a = st.configs["arm"].arm  # type: ignore[attr-defined]
    assert a.rt_priority == 50 and a.watch_services == ["planner"]
    assert a.stats_file == str(tmp_path / "arm_stats.json")
    p = st.configs["planner"].planner  # type: ignore[attr-defined]
    assert p.task_file == str(task) and p.exit_when_done and p.rt_priority == 50


def _result() -> dict[str, Any]:
    lat = {"p50": 190.0, "p99": 300.0, "max": 2000.0, "n": 8000}
    arm_rt = {"ticks": 8000, "wall_s": 16.0, "published_per_s": 500.0, "missed_ticks": 1,
              "published_ticks": 8000, "skipped_ticks": 0, "late_commands": 30, "answered_ticks": 7990,
              "state_to_command_latency": {"p50_us": 650.0, "p99_us": 1100.0, "max_us": 5000.0}}
    task = {"success": True, "steps_succeeded": 5, "steps_total": 5, "duration_s": 15.7, "steps": [
        {"step": "grasp_spoon", "outcome": "reached", "success": True, "duration_s": 4.1,
         "position_error_m": 0.0, "peak_speed_ratio": 1.08}]}
    pp = {**pingpong_bound([320.0] * 100), "round_trips_per_s": 3000.0}
    res: dict[str, Any] = {
        "date_utc": "2026-01-01T00:00:00Z", "machine": "x86_64", "cpus": 2, "python": "3.11",
        "zenoh": "1.0", "quick": True, "load_avg_start": "0", "load_avg_end": "0",
        "machine_busy_pct_before": 0.0, "machine_busy_pct_during": 50.0,
        "tick_cost": {"states": 100, "sim_s": 0.2, "replays": 1, "replay_mismatches": 0,
                      "task_success": True,
                      "total": percentiles([50.0] * 10),
                      "total_cold": percentiles([125.0] * 10),
                      "cold_flush_bytes": 64 * 2**20, "cold_every": 7,
                      "parts": {k: percentiles([10.0] * 10) for k in (
                          "decode", "answer", "runner_step", "controller", "orientation", "encode",
                          "total")}},
        "lockstep": {"rt_priority": 50, "planner_rt_priority": 50,
                     "window": {"ticks_per_s": 1100.0, "window_s": 6.5, "ticks": 7150, "samples": 130},
                     "arm": {"ticks": 8700, "wall_s": 7.9, "ticks_per_s": 1100.0, "lockstep_timeouts": 0},
                     "planner_latency_us": lat, "pingpong_before": pp, "pingpong_after": pp,
                     "cpu": {"window_s": 7.8, "cpu_pct": {"router": 15.0, "planner": 37.0, "arm": 58.0}},
                     "task": task},
        "realtime": {"rt_priority": 50, "planner_rt_priority": 50, "arm": arm_rt,
                     "timer": {"n": 8000, "over_2ms": 1, "over_1ms": 5, "p50_us": 90.0, "max_us": 2100.0},
                     "planner_latency_us": lat, "cpu": {"window_s": 16.0, "cpu_pct": {"arm": 29.0}},
                     "task": task},
        "stack": {"exit_code": 0, "wall_s": 25.0, "reason": "planner finished",
                  "cpu": {"window_s": 18.0, "cpu_pct": {"router": 11.0, "arm": 32.0, "planner": 23.0,
                                                        "supervisor (benchmark process)": 1.0}},
                  "stack_total_pct": 66.0, "total_with_supervisor_pct": 67.0, "task": task,
                  "planner_latency_us": lat, "arm": arm_rt,
                  "floor": {"window_s": 15.0, "total_pct": 40.0,
                            "cpu_pct": {"router": 0.1, "arm": 11.0, "planner": 10.0}}},
    }
    res["verdicts"] = verdicts(res)
    return res


def test_verdicts_and_report_on_synthetic_numbers() -> None:
    res = _result()
    v = res["verdicts"]
    assert v["lockstep"]["ratio"] == pytest.approx(1100.0 / (1e6 / 320.0)) and not v["lockstep"]["ok"]
    assert v["realtime_missed"]["ratio"] == pytest.approx(1.0) and v["realtime_missed"]["ok"]
    assert v["stack_cpu"]["ok"] and v["stack_cpu"]["target_pct"] == STACK_CPU_TARGET_PCT
    md = render_markdown(res)
    assert "0.35×" in md and "**not met**" in md and "**met**" in md
    for heading in ("(a) Planner tick cost", "(b) Closed loop", "(c) Closed loop",
                    "(d) The whole feeding stack"):
        assert heading in md
    assert "66.0 %" in md
    assert "**total, caches cold** (64 MiB written before every 7th call" in md
    assert "(2.5× the warm p50)" in md
    # The platform floor of the same run beside each process and in the verdict.
    assert v["stack_cpu"]["floor_pct"] == 40.0 and v["stack_cpu"]["ratio_to_floor"] == pytest.approx(1.65)
    assert "| arm | 32.0 | 11.0 |" in md and "**40.0**" in md and "the stack 1.65× it" in md


def test_a_short_recorded_stream_replays_byte_for_byte() -> None:
    rec = record_stream(max_sim_s=0.4)
    assert len(rec["replies"]) == 200
    times, mismatches = replay_total(rec)
    assert mismatches == 0 and len(times) == 200 and all(t > 0 for t in times)
    parts = replay_parts(rec)
    for k in ("decode", "answer", "runner_step", "controller", "orientation", "encode", "total"):
        assert len(parts[k]) == 200, k
    # The cold replay answers every state as recorded and times every COLD_EVERY-th one.
    cold, mismatches = replay_total(rec, cold_every=COLD_EVERY)
    assert mismatches == 0 and len(cold) == -(-200 // COLD_EVERY) and all(t > 0 for t in cold)
