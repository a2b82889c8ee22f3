"""The stack benchmark's missed-tick verdict: the rounds' counts pooled, each round's arm
against the timer loop of its own window."""

from __future__ import annotations

from typing import Any

import pytest

from benchmarks.stack import LATENCY_SUFFIX, PINNED_SUFFIX, _pooled_lines, pooled_miss_ratio


def _scenario(missed: int, published: int, skipped: int, by: dict[str, int], timer: int) -> dict[str, Any]:
    return {"arm": {"missed_ticks": missed, "published_ticks": published, "skipped_ticks": skipped,
                    "missed_by": {**by, "skipped": skipped}},
            "timer": {"over_2ms": timer, "deadlines": 10_000}}


def test_the_missed_tick_target_pools_the_rounds_each_against_its_own_timer() -> None:
    res: dict[str, Any] = {"rt_priority": 80, "scenarios": {
        "stack": _scenario(5, 9_990, 0, {"wake": 5, "lock": 0, "step": 0}, 0),  # alone: inf
        "stack" + LATENCY_SUFFIX: _scenario(3, 9_998, 2, {"wake": 1, "lock": 0, "step": 0}, 2),
        "stack" + PINNED_SUFFIX: _scenario(2, 10_000, 0, {"wake": 1, "lock": 1, "step": 0}, 18),
        "stack_normal": _scenario(30, 9_990, 10, {"wake": 20, "lock": 0, "step": 0}, 4),
        "arm": _scenario(99, 9_901, 0, {"wake": 99, "lock": 0, "step": 0}, 0),  # another scenario
    }}
    p = pooled_miss_ratio(res, "stack")
    assert p is not None
    assert (p["rounds"], p["arm_missed"], p["arm_ticks"]) == (3, 10, 29_990)
    assert (p["timer_missed"], p["timer_deadlines"]) == (20, 30_000)
    assert p["ratio"] == pytest.approx((10 / 29_990) / (20 / 30_000))
    assert p["ok"]
    assert p["arm_missed_by"] == {"wake": 7, "lock": 1, "step": 0, "skipped": 2}
    n = pooled_miss_ratio(res, "stack_normal")
    assert n is not None and n["rounds"] == 1 and not n["ok"]  # 30/10,000 against 4/10,000
    assert pooled_miss_ratio(res, "platform") is None

    res["missed_ticks_pooled"], res["missed_ticks_pooled_normal_scheduling"] = p, n
    text = "\n".join(_pooled_lines(res))
    fifo = "| SCHED_FIFO 80 (deployed) | 10 | 29990 | 7 / 1 / 0, 2 skipped | 20 | 30000 | 0.50 | **met** |"
    assert fifo in text
    assert "| normal | 30 | 10000 | 20 / 0 / 0, 10 skipped | 4 | 10000 | 7.50 | **not met** |" in text
