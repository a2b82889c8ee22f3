"""The feeding stack's platform floor (benchmarks/null_stack.py): the traffic profile read from a
recording (rates over the task, median payloads, a missing key named), and a short null stack on
loopback that carries that traffic: every null service up, the answers one per input as the real
processes give them, the timed keys at their rates."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from benchmarks.null_stack import PROCESSES, run_null_stack, traffic, traffic_profile
from experiments.harness import TraceWriter
from services.bus.messages import Keys

#: The keys the stack's processes publish (the camera's and the tracker's under their names).
WANTED = sorted({e[3:].replace("camera/*", "camera/cam0").replace("/*", "/person")
                 for t in traffic(Keys("pt")).values() for e in (*t.answers, *t.timed)})
RATES = {"arm/state": 500.0, "arm/command": 500.0, "collision": 500.0, "planner/status": 20.0,
         "viz/plan": 20.0, "planner/goal": 10.0, "task/events": 10.0, "arm/transforms": 25.0}


def _recording(path: Path, skip: str = "") -> None:
    """2 s of stack traffic under prefix ``pt``: arm states over 0-2 s, every other key over the
    task, 0.5-1.5 s (commands included), at :data:`RATES` (30 Hz for the camera's and the
    tracker's keys); the planner's status grows in size over the run."""
    keys = Keys("pt")
    with TraceWriter(path) as w:
        for rel in WANTED:
            if rel == skip:
                continue
            rate = RATES.get(rel, 30.0)
            lo, hi = (0.0, 2.0) if rel == "arm/state" else (0.5, 1.5)
            topic = keys.topic_for_key(f"pt/{rel}")
            assert topic is not None and topic.msg_type is not None, rel
            n = round((hi - lo) * rate)
            for i in range(n + 1):
                msg = topic.msg_type()
                if rel == "planner/status":
                    msg.detail = "x" * i  # sizes grow: the median is the middle one
                w.write(f"pt/{rel}", msg, round((lo + i / rate) * 1e9))


def test_the_profile_takes_each_rate_over_the_task_and_the_median_payload(tmp_path: Path) -> None:
    _recording(tmp_path / "run.mcap")
    prof = traffic_profile(tmp_path / "run.mcap")
    assert prof["span_s"] == pytest.approx(1.0)
    rates = {k: v["rate_hz"] for k, v in prof["keys"].items()}
    assert set(rates) == set(WANTED)
    assert rates["arm/state"] == pytest.approx(501.0)  # only the states within the task count
    assert rates["planner/status"] == pytest.approx(21.0) and rates["vision/faces"] == pytest.approx(31.0)
    from services.bus.messages import PlannerStatus

    status = PlannerStatus.FromString(bytes.fromhex(prof["keys"]["planner/status"]["payload_hex"]))
    assert len(status.detail) == 10
    assert prof["keys"]["collision"]["encoding"] == "application/protobuf;psm.CollisionPrediction"


def test_a_recording_without_a_key_is_refused_naming_it(tmp_path: Path) -> None:
    _recording(tmp_path / "run.mcap", skip="viz/plan")
    with pytest.raises(ValueError, match="no sample of pt/viz/plan"):
        traffic_profile(tmp_path / "run.mcap")


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_a_null_stack_carries_the_recorded_traffic(tmp_path: Path) -> None:
    _recording(tmp_path / "run.mcap")
    prof = traffic_profile(tmp_path / "run.mcap")
    res: dict[str, Any] = run_null_stack(prof, seconds=2.0, warmup_s=1.0, workdir=tmp_path / "null")
    assert all(res["alive_during_window"].values()), res
    assert not res["logs_tail"], res["logs_tail"]
    assert set(res["cpu_pct"]) == {"router", *PROCESSES} and res["total_pct"] > 0.0
    c = res["counts"]
    assert set(c) == set(PROCESSES)
    states = c["arm"]["published"]["arm/state"]
    state_hz = prof["keys"]["arm/state"]["rate_hz"]
    assert states >= 0.9 * state_hz * res["ran_s"]
    # Answers: one command and one prediction per state received, a frame every n-th state (a
    # sample being answered when the counts are written at shutdown is counted as received only).
    # Every service is alive before the window and the stop starts with the last one started.
    for role, out in (("planner", "arm/command"), ("obstacle_monitor", "collision")):
        got = c[role]["received"]["arm/state"]
        assert got >= 0.9 * state_hz * res["ran_s"], (role, c[role])
        assert got - 1 <= c[role]["published"][out] <= got, (role, c[role])
    every = round(state_hz / prof["keys"]["camera/cam0/image"]["rate_hz"])
    assert every == 16  # 501 / 31 Hz
    images = c["camera"]["published"]["camera/cam0/image"]
    assert 0 <= c["camera"]["received"]["arm/state"] // every - images <= 1
    frames = c["goal_tracker"]["received"]["camera/*/image"]
    assert frames >= 0.9 * state_hz / every * res["ran_s"]
    assert frames - 1 <= c["goal_tracker"]["published"]["goals/person"] <= frames
    assert c["arm"]["received"]["arm/command"] >= 0.9 * c["planner"]["published"]["arm/command"]
    # The recorder, alive first and stopped last, sees every sample the others publish; the
    # planner's timed status goes out at its recorded rate (about 21 Hz) over the time its loop ran,
    # which covers the CPU window (its loop starts just after its token, a moment after the stack's
    # clock ``ran_s`` starts, and ends when it is stopped first, after the window).
    published = sum(n for role in PROCESSES if role != "recorder" for n in c[role]["published"].values())
    assert c["recorder"]["received"]["**"] >= 0.99 * published
    status_hz = prof["keys"]["planner/status"]["rate_hz"]
    loop_s = c["planner"]["loop_s"]
    assert res["window_s"] < loop_s < res["ran_s"] + 1.0
    assert 0.8 * status_hz * loop_s <= c["planner"]["published"]["planner/status"] <= status_hz * loop_s + 1
