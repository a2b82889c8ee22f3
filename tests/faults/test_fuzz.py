"""A flood of malformed messages on every key of the running shipped stack (realtime, real
processes on loopback): random bytes, wrong encodings, messages of the wrong type, valid types
with NaN / inf / 1e308, jumping ticks, stale and future stamps (``tests/faults/fuzz_tool.py``).
The stack holds (an obstacle around the hand: a protective stop), so the arm is at rest and
anything that moved it would show. No service dies or counts an error, the arm never moves, each
service that reads the bus counts what it rejected by reason on its status, the recorder records
every sample bytes unchanged, and once the flood is over and the obstacle removed the task goes
on: nothing the flood sent was kept."""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
from stack_helpers import (
    LOAD_TOLERANT,
    ROOT,
    StackWatch,
    record_fault,
    up_args,
    up_port,
    wait_stack_up,
)

from services.supervisor import ManagedProcess, psm_argv

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

#: A sphere around the hand at the arm's ready pose: the whole-arm clearance is negative from
#: the start, so the planner holds (protective stop) with the arm at rest.
BLOCK = '{id = "block", shape = "sphere", position_m = [0.307, 0.0, 0.487], size_m = [0.12, 0, 0]}'
#: The services that read the bus, and what each reads.
READERS = ("arm", "planner", "obstacle_monitor", "goal_tracker", "camera_synth")
#: Keys only the fuzzer publishes on: the recorder must have every sample of them.
FUZZ_ONLY = ("goals/cam0", "viz/goals/cam0", "status/person", "status/cam0", "camera/person/image")
#: Every key gets every kind of bad input this many times (about 5 s at 2000 samples/s), and
#: the same samples whatever the machine's load (the fuzzer is seeded); at most FUZZ_MAX_S.
FUZZ_CYCLES = 80
FUZZ_MAX_S = 60.0


def test_a_fuzz_flood_on_every_key_moves_nothing_and_is_counted(tmp_path: Path) -> None:
    from services.bus.log import read_samples
    from services.bus.messages import ObstacleCommand, PlannerStatus, encode

    args = up_args(tmp_path, "realtime", *LOAD_TOLERANT, f"obstacle_monitor.obstacles=[{BLOCK}]")
    port = up_port(args)
    prefix = f"feed{port}"
    endpoint = f"tcp/127.0.0.1:{port}"
    up = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    watch: StackWatch | None = None
    try:
        pids = wait_stack_up(up, time.monotonic() + 120)
        watch = StackWatch(port, prefix)
        w = watch
        w.wait(lambda: w.planner is not None and w.planner.state == PlannerStatus.HOLDING
               and "protective stop" in w.planner.detail, 30, "the planner does not hold")
        w.wait(lambda: all(s in w.status for s in READERS), 10, "statuses")
        before = {name: w.status[name] for name in READERS}
        n_states = len(w.states)
        fuzz = ManagedProcess(
            "fuzz", [sys.executable, "-m", "tests.faults.fuzz_tool", endpoint, "--prefix", prefix,
                     "--cycles", str(FUZZ_CYCLES), "--duration", str(FUZZ_MAX_S), "--rate", "2000",
                     "--sent-log", str(tmp_path / "sent.tsv")],
            tmp_path / "fuzz.log", cwd=ROOT)
        try:
            assert fuzz.wait(90) == 0, fuzz.log_text()
        finally:
            fuzz.stop()
        sent = json.loads(fuzz.log_text().strip().splitlines()[-1])
        assert sent["cycles_done"] == FUZZ_CYCLES, sent["cycles_done"]
        time.sleep(2.0)  # the last statuses
        after = {name: w.status[name] for name in READERS}
        during = w.states[n_states:]
        # No process died (the supervisor would have said so, and restarted or stopped).
        assert up.alive() and all(_alive(pid) for pid in pids.values()), up.log_text()
        assert "exited" not in up.log_text(), up.log_text()
        # The arm never moved, and the planner still holds for the obstacle.
        assert len(during) > 0.5 * 500 * sent["seconds"], (len(during), sent["seconds"])
        max_dq = max(d for _t, d, _v in during)
        max_speed = max(v for _t, _d, v in during)
        assert max_dq < 1e-4 and max_speed < 1e-4, (max_dq, max_speed)
        # Predictions may have fallen behind meanwhile (the planner holds for that too); the
        # monitor's protective stop is what holds it again once they are back.
        w.wait(lambda: w.planner.state == PlannerStatus.HOLDING and "protective stop" in w.planner.detail,
               10, "the planner does not hold for the obstacle after the flood")
        # Each reader counted what it rejected, by reason, and no handler failed.
        rejected: dict[str, dict[str, int]] = {}
        for name in READERS:
            b, a = before[name], after[name]
            assert a.errors == b.errors, (name, a.last_error)
            by = {k: v - b.rejected_by_reason.get(k, 0) for k, v in a.rejected_by_reason.items()}
            rejected[name] = {k: v for k, v in sorted(by.items()) if v}
            assert a.rejected - b.rejected == sum(by.values()) > 0, name
            assert len(rejected[name]) >= 3, (name, rejected[name])
        assert {"tick", "stamp", "malformed", "type"} <= set(rejected["arm"]), rejected["arm"]
        assert {"tick", "stamp", "non_finite", "encoding"} <= set(rejected["planner"]), rejected["planner"]
        # The flood is over: with the obstacle removed (a valid command) the task goes on.
        cmd = ObstacleCommand(action=ObstacleCommand.REMOVE, id="block", source="test")
        payload, encoding = encode(cmd)
        removed_ns = time.time_ns()
        w.session.put(w.keys.obstacles_command.key, payload, encoding=encoding)
        w.wait(lambda: w.planner.state == PlannerStatus.RUNNING and w.planner.speed_mps > 0.05, 20,
               "the task does not go on")
        moving = [t for t, _d, v in w.states if t > removed_ns and v > 0.05]
        up.signal(15)
        rc = up.wait(60)
    finally:
        if watch is not None:
            watch.close()
        up.stop()
    assert rc == 0, up.log_text()
    # Nothing failed on a receive thread either (an exception there is only printed).
    for log in (tmp_path / "run").glob("*.log"):
        assert "Traceback" not in log.read_text(), log
    # The recorder recorded every fuzzed sample, bytes unchanged (it judges nothing).
    assert sent["flushed_s"] is not None, "the fuzzer's last samples never reached the router"
    keys = [f"{prefix}/{k}" for k in FUZZ_ONLY]
    got: Counter[tuple[str, str]] = Counter(
        (s.topic, hashlib.blake2b(s.payload, digest_size=16).hexdigest())
        for s in read_samples(tmp_path / "run.mcap", topics=keys, strict=True))
    lines = [ln.split("\t") for ln in (tmp_path / "sent.tsv").read_text().splitlines()]
    want: Counter[tuple[str, str]] = Counter((k, d) for k, _kind, _e, d, _n in lines if k in keys)
    kind_of = {(k, d): (kind, e, int(n)) for k, kind, e, d, n in lines}
    recorded, published = sum(got.values()), sum(want.values())
    missing = [(x[0], *kind_of[x]) for x in (want - got).elements()]
    # Nothing the recorder did not receive was written, and it received (nearly) all: with the
    # machine's CPU saturated, zenoh has been seen to lose a few large samples (3-6 KB, up to
    # 0.25 %, the last ones of the flood) on the way from the fuzzer to the recorder; every
    # such loss is listed in the fault record (docs/faults.md).
    assert not (got - want) and published > 0, list(got - want)[:10]
    assert len(missing) <= 0.005 * published, (recorded, published, missing[:10])
    record_fault("fuzz", {
        "test": "test_a_fuzz_flood_on_every_key_moves_nothing_and_is_counted",
        "fault": (f"fuzz flood on every catalogue key ({sent['keys']} keys, each kind "
                  f"{FUZZ_CYCLES}×, {sent['seconds']:.1f} s)"),
        "fuzz_published": sent["published"],
        "fuzz_rate_per_s": sent["published"] / sent["seconds"],
        "arm_max_joint_speed_rad_s": max_dq,
        "arm_max_ee_speed_mps": max_speed,
        "services_died": 0,
        "handler_errors": 0,
        "rejected_by_reason": rejected,
        "recorder_recorded_of_published": [recorded, published],
        "recorder_missing": [list(m) for m in missing],
        "fuzzer_flush_s": sent["flushed_s"],
        "task_went_on_after_s": (moving[0] - removed_ns) * 1e-9 if moving else None,
    })


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as fh:
        return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
