"""The realtime arm's clock: sim time locked to the wall clock (UNIX epoch), missed ticks
stepped through and published current, DEGRADED while it happens; lockstep starts at 0.

In process (no router: a peer session with multicast off and no endpoints), so the arm's own
loop is observed directly; its step is slowed artificially to make ticks miss."""

from __future__ import annotations

import itertools
import threading
import time
from typing import Any

import pytest

from services.arm.config import ArmConfig, ArmSection
from services.arm.service import ArmService
from services.bus.config import ZenohConfig
from services.bus.messages import ServiceStatus


def _arm(clock: str = "realtime", **arm: Any) -> ArmService:
    cfg = ArmConfig(
        zenoh=ZenohConfig(mode="peer", multicast=False, gossip=False),
        log_level="ERROR",
        clock=clock,
        arm=ArmSection(**arm),
    )
    return ArmService(cfg)


def _after_setup(arm: ArmService, fn: Any) -> None:
    """Call ``fn()`` once the arm has declared its publishers (to install spies on them)."""
    setup = arm.setup

    def wrapped(svc: Any) -> None:
        setup(svc)
        fn()

    arm.setup = wrapped  # type: ignore[method-assign]


def _run_in_thread(svc: ArmService) -> threading.Thread:
    th = threading.Thread(target=svc.run, daemon=True)
    th.start()
    return th


def test_realtime_stamps_are_epoch_and_a_stall_is_caught_up() -> None:
    svc = _arm(dt_s=0.002, max_ticks=600, transforms_rate_hz=30.0)
    sim = svc.sim
    stamps: list[tuple[int, int]] = []
    transforms: list[int] = []

    def spies() -> None:
        put_state = svc._state_pub.put_bytes

        def spy_state(payload: bytes) -> None:
            from services.bus.messages import ArmState

            msg = ArmState.FromString(payload)
            stamps.append((msg.tick, msg.stamp_ns))
            put_state(payload)

        assert svc._tf_pub is not None
        put_tf = svc._tf_pub.put

        def spy_tf(msg: Any) -> None:
            ts = msg.transforms[0].timestamp
            transforms.append(ts.seconds * 1_000_000_000 + ts.nanos)
            put_tf(msg)

        svc._state_pub.put_bytes = spy_state  # type: ignore[method-assign]
        svc._tf_pub.put = spy_tf  # type: ignore[method-assign]

    _after_setup(svc, spies)
    step = sim.step
    stalled = {"done": False}

    def slow_step() -> Any:
        # At tick 200 the process "stops" for 200 ms (a step that cannot be computed in time).
        if sim.tick == 200 and not stalled["done"]:
            stalled["done"] = True
            time.sleep(0.2)
        return step()

    sim.step = slow_step  # type: ignore[method-assign]
    wall0 = time.time_ns()
    th = _run_in_thread(svc)
    th.join(30)
    assert not th.is_alive()
    wall1 = time.time_ns()
    st = svc.stats
    dt_ns = 2_000_000
    origin = sim.time_origin_ns
    # Realtime sim time is UNIX time: tick k is stamped origin + k·dt, origin = start time.
    assert wall0 - 1e9 < origin < wall1
    assert all(stamp == origin + tick * dt_ns for tick, stamp in stamps)
    # The stall was stepped through (not published one by one) and the arm re-locked: the last
    # state's sim time is within a few ticks of the wall clock when it was published.
    assert st.skipped_ticks >= 90, st.summary()
    assert st.missed_ticks >= st.skipped_ticks
    assert st.reanchors == 0
    ticks = [t for t, _ in stamps]
    assert ticks == sorted(ticks) and max(b - a for a, b in itertools.pairwise(ticks)) >= 90
    assert sim.tick == 600
    elapsed = (wall1 - origin) * 1e-9
    assert elapsed == pytest.approx(600 * 0.002, abs=0.25)
    # Transforms carry the sim time of the state they show (a tick on the 2 ms grid).
    assert transforms and all((t - origin) % dt_ns == 0 for t in transforms)


def test_degraded_status_is_set_and_cleared() -> None:
    from services.bus.runtime import Service

    bus = Service("arm", _arm().config)
    try:
        assert bus.status_message().state != ServiceStatus.DEGRADED
        bus.state = ServiceStatus.RUNNING
        bus.set_degraded("realtime: 5 ticks missed")
        msg = bus.status_message()
        assert msg.state == ServiceStatus.DEGRADED
        assert msg.last_error == "realtime: 5 ticks missed"
        bus.set_degraded(None)
        assert bus.status_message().state == ServiceStatus.RUNNING
    finally:
        bus.close()


def test_missed_ticks_make_the_arm_degraded_then_it_recovers(monkeypatch: pytest.MonkeyPatch) -> None:
    import services.arm.service as mod

    # DEGRADED until 100 ms pass without a missed tick (a loaded machine misses ticks of its
    # own now and then: the hold is short so that a quiet 100 ms comes well within the run).
    monkeypatch.setattr(mod, "DEGRADED_HOLD_NS", 100_000_000)
    svc = _arm(dt_s=0.002, max_ticks=700)
    sim = svc.sim
    step = sim.step
    seen: list[tuple[int, int]] = []

    def slow_step() -> Any:
        if sim.tick == 100:
            time.sleep(0.05)
        if sim.tick > 100:
            seen.append((sim.tick, svc.svc.status_message().state))
        return step()

    sim.step = slow_step  # type: ignore[method-assign]
    th = _run_in_thread(svc)
    th.join(30)
    assert not th.is_alive()
    first_degraded = next(t for t, st in seen if st == ServiceStatus.DEGRADED)
    assert first_degraded <= 130  # once the 25 ticks of the 50 ms stall are stepped through
    assert any(st == ServiceStatus.RUNNING for t, st in seen if t > first_degraded)  # recovered
    assert svc.stats.skipped_ticks >= 20


def test_a_missed_tick_is_attributed_to_the_largest_part_of_its_lateness() -> None:
    from services.arm.stats import MISS_RECORDS, LoopStats, miss_causes_text

    st = LoopStats()
    st.add_miss(7, 3_000_000, 10_000, 50_000)  # asleep past the deadline
    st.add_miss(8, 100_000, 4_000_000, 50_000)  # waiting for the step lock
    st.add_miss(9, 100_000, 10_000, 2_500_000)  # stepping
    assert st.missed_ticks == 3
    out = st.summary()
    assert out["missed_by"] == {"wake": 1, "lock": 1, "step": 1, "skipped": 0}
    assert out["misses"][0] == {"tick": 7, "wake_us": 3000.0, "lock_us": 10.0, "step_us": 50.0}
    assert miss_causes_text(out["missed_by"]) == "1 / 1 / 1" and miss_causes_text(None) == "–"
    for k in range(10, 10 + 2 * MISS_RECORDS):
        st.add_miss(k, 3_000_000, 0, 0)
    latest = range(10 + MISS_RECORDS, 10 + 2 * MISS_RECORDS)
    assert [m["tick"] for m in st.summary()["misses"]] == list(latest)
    assert st.summary()["missed_by"]["wake"] == 1 + 2 * MISS_RECORDS


def test_the_realtime_arm_says_where_a_missed_tick_lost_its_time() -> None:
    """A step of 20 ms on the loop's thread is a miss of cause ``step``; the step lock held for
    40 ms by another thread (as Zenoh's thread holds it while it steps a command) is a miss of
    cause ``lock``. (A loaded machine may add misses of cause ``wake``: only lower bounds; the
    stalls are long so that a late wake-up cannot outweigh them.)"""
    svc = _arm(dt_s=0.002, max_ticks=500)
    sim = svc.sim
    step = sim.step

    def slow_step() -> Any:
        if sim.tick == 100:
            time.sleep(0.020)
        return step()

    def hold_the_lock() -> None:
        deadline = time.monotonic() + 20.0
        while sim.tick < 300 and time.monotonic() < deadline:
            time.sleep(0.001)
        with svc._lock:
            time.sleep(0.040)

    sim.step = slow_step  # type: ignore[method-assign]
    holder = threading.Thread(target=hold_the_lock, daemon=True)
    holder.start()
    th = _run_in_thread(svc)
    th.join(30)
    holder.join(5)
    assert not th.is_alive()
    out = svc.stats.summary()
    assert out["missed_by"]["step"] >= 1 and out["missed_by"]["lock"] >= 1, out["missed_by"]
    assert any(m["step_us"] >= 20_000 for m in out["misses"]), out["misses"]
    assert any(m["lock_us"] >= 20_000 for m in out["misses"]), out["misses"]
    assert out["missed_ticks"] == sum(out["missed_by"][c] for c in ("wake", "lock", "step")) \
        + out["skipped_ticks"]


def test_lockstep_sim_time_starts_at_zero() -> None:
    svc = _arm(clock="lockstep", dt_s=0.002, lockstep_timeout_s=0.05)
    stamps: list[int] = []

    def spies() -> None:
        put_state = svc._state_pub.put_bytes

        def spy_state(payload: bytes) -> None:
            from services.bus.messages import ArmState

            stamps.append(ArmState.FromString(payload).stamp_ns)
            put_state(payload)

        svc._state_pub.put_bytes = spy_state  # type: ignore[method-assign]

    _after_setup(svc, spies)
    th = _run_in_thread(svc)
    time.sleep(1.0)  # no planner: state 0 is re-offered, sim time does not run
    svc.svc.stop()
    th.join(30)
    assert not th.is_alive()
    assert svc.sim.time_origin_ns == 0
    assert stamps and set(stamps) == {0}


def test_the_arm_holds_the_cpu_wake_up_latency_while_it_runs() -> None:
    import os
    import struct

    from services.threads import CPU_DMA_LATENCY

    if not os.access(CPU_DMA_LATENCY, os.W_OK):
        pytest.skip(f"{CPU_DMA_LATENCY} is not writable here (root is needed)")

    def current() -> int:
        with open(CPU_DMA_LATENCY, "rb") as f:
            return int(struct.unpack("=i", f.read(4))[0])

    before = current()
    svc = _arm(dt_s=0.002, max_ticks=100, cpu_latency_us=3)
    assert svc._cpu_latency.held and current() <= 3
    th = _run_in_thread(svc)
    th.join(30)
    assert not th.is_alive()
    assert not svc._cpu_latency.held and current() == before
