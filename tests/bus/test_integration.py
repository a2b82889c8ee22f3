"""Real processes on loopback (multicast off): router, recorder, replayer, echo, publisher."""

from __future__ import annotations

import json
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap_protobuf.decoder import DecoderFactory

from services.bus.log import LogReadError, read_log, read_metadata, read_samples
from services.bus.messages import ArmState, CompressedImage, Goal, Keys, ServiceStatus, encode
from services.bus.runtime import RawSample, Service

from .fixture_data import PATH as FIXTURE
from .fixture_data import fixture_samples
from .helpers import Proc, bus_args, client_config, wait_for
from .pub_tool import goal, image, state

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

BUS = ["-m", "services.bus.cli"]


def start_recorder(procs: Callable[..., Proc], router: str, out: Path, *extra: str) -> Proc:
    rec = procs([*BUS, "record", "-o", str(out), *bus_args(router), *extra], "recorder")
    assert wait_for(lambda: (out.exists() and out.stat().st_size > 0) or not rec.alive(), 15)
    assert rec.alive(), rec.stderr()
    return rec


def test_record_typed_messages_and_finalise_on_sigterm(procs, router, tmp_path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run.mcap"
    watcher = Service("watcher", client_config(router)).start()
    alive: dict[str, bool] = {}
    watcher.watch_liveliness(None, lambda name, up: alive.__setitem__(name, up))
    try:
        rec = start_recorder(procs, router, out)
        assert wait_for(lambda: alive.get("recorder") is True and alive.get("router") is True)
        n_states, n_goals, n_images = 3000, 5, 20
        pub = procs(["-m", "tests.bus.pub_tool", router, "--states", str(n_states),
                     "--goals", str(n_goals), "--images", str(n_images)], "pub")
        assert pub.wait(60) == 0, pub.stderr()
        assert json.loads(pub.stdout())["states"] == n_states
        time.sleep(0.5)
        rec.signal(signal.SIGTERM)
        assert rec.wait(20) == 0, rec.stderr()
        assert wait_for(lambda: alive.get("recorder") is False)
    finally:
        watcher.close()

    expected = {"psm/arm/state": n_states, "psm/goals/person": n_goals,
                "psm/camera/cam0/image": n_images}
    # 1. plain mcap library (seeking reader: needs the summary written at SIGTERM)
    with out.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None, "not finalised"
        assert summary.chunk_indexes, "no chunk index"
        counts: dict[str, int] = {}
        for _schema, channel, _msg, decoded in reader.iter_decoded_messages(
                topics=list(expected), log_time_order=False):
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            assert decoded.DESCRIPTOR.full_name.split(".")[-1] in (
                "ArmState", "Goal", "CompressedImage")
        assert counts == expected
        stats = summary.statistics
        by_topic = {summary.channels[c].topic: n for c, n in stats.channel_message_counts.items()}
        for topic, n in expected.items():
            assert by_topic[topic] == n
    # 2. the project's reader: typed, bytes unchanged, publish time = own stamp
    states = [(m, s) for t, m, s in read_log(out, topics=["psm/arm/state"])]
    assert [m.tick for m, _ in states] == list(range(n_states))
    assert all(m == state(m.tick) for m, _ in states)
    assert all(s == state(m.tick).stamp_ns for m, s in states)
    images = [m for _, m, _ in read_log(out, topics="psm/camera/*/image")]
    assert all(isinstance(m, CompressedImage) for m in images)
    assert [m.SerializeToString() for m in images] == [
        image(i).SerializeToString() for i in range(n_images)]
    goals = [m for _, m, _ in read_log(out, topics="psm/goals/*")]
    assert goals == [goal(i) for i in range(n_goals)]
    # 3. metadata record with config snapshot and version
    md = read_metadata(out)["psm.recorder"]
    assert json.loads(md["config"])["zenoh"]["connect"] == [router]
    assert md["project_version"]


def test_kill9_leaves_file_readable_up_to_last_chunk(procs, router, tmp_path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "killed.mcap"
    rec = start_recorder(procs, router, out, "--chunk-size", "8192", "--set",
                         "recorder.flush_interval_s=0.2")
    pub = procs(["-m", "tests.bus.pub_tool", router, "--states", "20000", "--rate", "4000"],
                "pub")
    assert wait_for(lambda: out.stat().st_size > 100_000 or not pub.alive(), 20)
    time.sleep(0.5)
    rec.signal(signal.SIGKILL)
    rec.wait(10)
    ticks = [m.tick for _, m, _ in read_log(out, topics=["psm/arm/state"])]
    assert len(ticks) > 1000
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks)))  # contiguous, in order
    with pytest.raises(LogReadError):
        list(read_log(out, strict=True))  # no footer: it really was killed
    with out.open("rb") as fh:  # plain mcap, non-seeking: the same messages before the cut
        n = 0
        try:
            for _s, ch, _m in NonSeekingReader(fh).iter_messages(log_time_order=False):
                n += ch.topic == "psm/arm/state"
        except Exception:
            pass
    assert n == len(ticks)


def test_replay_fixture_into_live_subscriber_and_recorder(procs, router, tmp_path) -> None:  # type: ignore[no-untyped-def]
    fixture = fixture_samples()
    fixture_keys = {k for k, *_ in fixture}
    out = tmp_path / "replayed.mcap"
    rec = start_recorder(procs, router, out)
    got: list[RawSample] = []
    lock = threading.Lock()
    sub_svc = Service("tester", client_config(router)).start()

    def on(raw: RawSample) -> None:
        with lock:
            got.append(raw)

    sub_svc.subscribe_raw("psm/**", on)
    try:
        time.sleep(0.5)
        rp = procs([*BUS, "replay", str(FIXTURE), "--include-commands", "--wait-subscribers", "5",
                    *bus_args(router)], "replay")
        assert rp.wait(60) == 0, rp.stderr()
        assert wait_for(lambda: sum(r.key in fixture_keys for r in got) >= len(fixture), 5)
    finally:
        sub_svc.close()
    live = [r for r in got if r.key in fixture_keys]
    assert [(r.key, r.encoding, r.payload) for r in live] == [
        (k, e, p) for k, e, p, _ in fixture]
    # recorded timing preserved: the span of receive times matches the recorded span
    span_rec = (fixture[-1][3] - fixture[0][3]) / 1e9
    span_live = (live[-1].recv_ns - live[0].recv_ns) / 1e9
    assert 0.8 * span_rec <= span_live <= span_rec + 0.5
    rec.signal(signal.SIGTERM)
    assert rec.wait(20) == 0, rec.stderr()
    recorded = [(s.topic, s.encoding, s.payload) for s in read_samples(out, strict=True)
                if s.topic in fixture_keys]
    assert recorded == [(k, e, p) for k, e, p, _ in fixture]


def test_replay_filter_remap_fast(procs, router) -> None:  # type: ignore[no-untyped-def]
    got: list[RawSample] = []
    svc = Service("tester", client_config(router)).start()
    svc.subscribe_raw("sim/**", got.append)
    try:
        time.sleep(0.5)
        t0 = time.monotonic()
        rp = procs([*BUS, "replay", str(FIXTURE), "--as-fast-as-possible", "--topics",
                    "psm/arm/**", "--remap-prefix", "psm=sim", "--wait-subscribers", "5",
                    *bus_args(router)], "replay")
        assert rp.wait(60) == 0, rp.stderr()
        assert wait_for(lambda: len(got) >= 40, 5)
        elapsed = time.monotonic() - t0
    finally:
        svc.close()
    expected = [(k.replace("psm/", "sim/", 1), p) for k, _, p, _ in fixture_samples()
                if k.startswith("psm/arm/") and k != "psm/arm/command"]
    assert [(r.key, r.payload) for r in got] == expected  # no command: not asked for
    assert elapsed < 30


def test_garbage_and_wrong_encodings_are_counted_and_survived(procs, router) -> None:  # type: ignore[no-untyped-def]
    k = Keys()
    echo = procs([*BUS, "echo", *bus_args(router), "--set", "status_period_s=0.2"], "echo")
    statuses: list[ServiceStatus] = []
    svc = Service("tester", client_config(router)).start()
    svc.subscribe(k.status("echo"), lambda m, _key: statuses.append(m))
    try:
        assert wait_for(lambda: bool(statuses), 15), echo.stderr()
        bad = 0
        session = svc.session
        good_payload, good_enc = encode(ArmState(stamp_ns=9, tick=9))
        goal_payload, goal_enc = encode(Goal(stamp_ns=1, name="x"))
        for topic in k.catalogue("x"):
            enc = topic.encoding
            session.put(topic.key, b"\xff\xff\xff\xff\xff", encoding=enc)  # malformed bytes
            session.put(topic.key, b"hello", encoding="text/plain")  # unknown encoding
            session.put(topic.key, b"\x08\x01", encoding="application/protobuf;psm.Nope")
            bad += 3
            wrong = goal_enc if topic.msg_type is not Goal else good_enc
            session.put(topic.key, goal_payload if wrong == goal_enc else good_payload,
                        encoding=wrong)  # a valid message of the wrong type for the key
            bad += 1
        session.put(k.arm_state.key, good_payload, encoding=good_enc)

        def settled() -> bool:
            return bool(statuses) and statuses[-1].received >= bad + 1
        assert wait_for(settled, 10), statuses[-1] if statuses else None
        last = statuses[-1]
        assert last.rejected == bad
        assert last.received - last.rejected >= 1
        assert echo.alive()
        assert wait_for(lambda: "psm/arm/state psm.ArmState" in echo.stdout(), 5)
        err = echo.stderr()
        assert "rejected sample" in err and "malformed" in err
    finally:
        svc.close()
    echo.signal(signal.SIGTERM)
    assert echo.wait(20) == 0


def test_cli_errors_are_one_line(procs, tmp_path) -> None:  # type: ignore[no-untyped-def]
    blocker = tmp_path / "file"
    blocker.write_text("")
    p = procs([*BUS, "record", "-o", str(blocker / "x.mcap"), "--no-multicast"], "rec_bad")
    assert p.wait(30) == 2
    lines = p.stderr().strip().splitlines()
    assert len(lines) == 1 and "cannot create directory" in lines[0], lines
    p = procs(["-m", "services.cli", "record", "-o", str(tmp_path / "y.mcap")], "rec_env",
              env={"PSM_ZENOH__MODE": "x"})
    assert p.wait(30) == 2
    assert p.stderr() == (
        "psm record: error: zenoh.mode (from $PSM_ZENOH__MODE): "
        "Input should be 'peer', 'client' or 'router' (got 'x')\n")
    assert not (tmp_path / "y.mcap").exists()


def test_latched_goal_reaches_late_recorder_and_late_subscriber(procs, router, tmp_path) -> None:  # type: ignore[no-untyped-def]
    k = Keys()
    pub_svc = Service("goalpub", client_config(router)).start()
    try:
        gp = pub_svc.publisher(k.goal("person"))
        gp.put(goal(1))  # before anyone listens
        time.sleep(0.3)
        # a late-joining typed subscriber gets it from the publisher's cache
        late: list[Goal] = []
        sub_svc = Service("late", client_config(router)).start()
        sub_svc.subscribe(k.goals_all, lambda m, _key: late.append(m))
        assert wait_for(lambda: late == [goal(1)], 10), late
        # and so does a late recorder, exactly once, followed by live goals in order
        out = tmp_path / "late.mcap"
        rec = start_recorder(procs, router, out)
        time.sleep(1.5)
        gp.put(goal(2))
        assert wait_for(lambda: late == [goal(1), goal(2)], 10), late
        time.sleep(0.5)
        rec.signal(signal.SIGTERM)
        assert rec.wait(20) == 0, rec.stderr()
        sub_svc.close()
    finally:
        pub_svc.close()
    goals = [m for _, m, _ in read_log(out, topics="psm/goals/*", strict=True)]
    assert goals == [goal(1), goal(2)]


def test_slow_handler_drops_are_counted_and_session_keeps_flowing(router) -> None:  # type: ignore[no-untyped-def]
    k = Keys()
    a = Service("slowsub", client_config(router)).start()
    b = Service("fastpub", client_config(router)).start()
    try:
        got_fast: list[int] = []
        release = threading.Event()
        slow_calls: list[int] = []

        def slow(m: ServiceStatus, _key: str) -> None:
            slow_calls.append(m.seq)
            release.wait(5)

        a.subscribe(k.task_events, slow, queue_size=5)
        a.subscribe(k.arm_state, lambda m, _key: got_fast.append(m.tick))
        time.sleep(0.5)
        from services.bus.messages import TaskEvent

        ev = b.publisher(k.task_events)
        st = b.publisher(k.arm_state)
        for i in range(50):
            ev.put(TaskEvent(stamp_ns=1, seq=i))
        for i in range(20):
            st.put(ArmState(stamp_ns=1, tick=i))
        # the blocked handler does not stop other streams of the same session
        assert wait_for(lambda: len(got_fast) == 20, 10), got_fast
        assert wait_for(lambda: a.counters.dropped > 0, 5)
        release.set()
        assert wait_for(lambda: len(slow_calls) + a.counters.dropped == 50, 10)
        assert a.status_message().dropped == a.counters.dropped
    finally:
        release.set()
        b.close()
        a.close()


def test_replay_as_fast_as_possible_keeps_recorded_order(procs, router) -> None:  # type: ignore[no-untyped-def]
    fixture = [f for f in fixture_samples() if f[0] != "psm/arm/command"]
    keys = {k for k, *_ in fixture}
    got: list[RawSample] = []
    svc = Service("tester", client_config(router)).start()
    svc.subscribe_raw("psm/**", got.append)
    try:
        time.sleep(0.5)
        rp = procs([*BUS, "replay", str(FIXTURE), "--as-fast-as-possible", "--wait-subscribers",
                    "5", *bus_args(router)], "replay")
        assert rp.wait(60) == 0, rp.stderr()
        assert wait_for(lambda: sum(r.key in keys for r in got) >= len(fixture), 5)
    finally:
        svc.close()
    assert [(r.key, r.encoding, r.payload) for r in got if r.key in keys] == [
        (k, e, p) for k, e, p, _ in fixture]


def _check_in_order_delivery(a: Service, b: Service, delivery: str, n: int = 500) -> None:
    """``b`` publishes ``n`` ArmStates; ``a``'s subscription (``delivery``) gets all, in order."""
    k = Keys()
    got: list[int] = []
    a.subscribe(k.arm_state, lambda m, _key: got.append(m.tick), delivery=delivery)
    pub = b.publisher(k.arm_state)

    def route_ready() -> bool:  # matching status alone can be true before the route is
        pub.put(ArmState(stamp_ns=1, tick=1_000_000))
        return 1_000_000 in got
    assert wait_for(route_ready, 10, period_s=0.05)
    time.sleep(0.2)
    got.clear()
    for i in range(n):
        pub.put(ArmState(stamp_ns=i + 1, tick=i))
    assert wait_for(lambda: len(got) == n, 10), len(got)
    assert got == list(range(n))


@pytest.mark.parametrize("delivery", ["queue", "channel", "inline"])
def test_every_delivery_gets_all_messages_in_order(router, delivery) -> None:  # type: ignore[no-untyped-def]
    a = Service("sub", client_config(router)).start()
    b = Service("pub", client_config(router)).start()
    try:
        _check_in_order_delivery(a, b, delivery)
        with pytest.raises(ValueError, match="delivery must be"):
            a.subscribe(Keys().arm_state, lambda m, _key: None, delivery="bogus")
    finally:
        b.close()
        a.close()


def _native_thread_name() -> str:
    """The OS name of the calling thread (``/proc/self/task/<tid>/comm``)."""
    return Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip()


def test_inline_delivery_runs_on_zenohs_receive_thread(router) -> None:  # type: ignore[no-untyped-def]
    """``"inline"``: the handler runs on Zenoh's receive thread itself (named ``rx-<n>``), not on
    a worker of the subscription nor on zenoh-python's callback thread (which a bare callable
    or ``indirect=True`` would use: a thread named after the process, ``python``)."""
    a = Service("sub", client_config(router)).start()
    b = Service("pub", client_config(router)).start()
    names: list[str] = []
    try:
        k = Keys()
        a.subscribe(k.arm_state, lambda _m, _key: names.append(_native_thread_name()), delivery="inline")
        pub = b.publisher(k.arm_state)

        def arrived() -> bool:
            pub.put(ArmState(stamp_ns=1, tick=1))
            return bool(names)
        assert wait_for(arrived, 10, period_s=0.05)
    finally:
        b.close()
        a.close()
    assert all(n.startswith("rx-") for n in names), names


def test_inline_delivery_keeps_one_python_thread_state_per_receive_thread(router) -> None:  # type: ignore[no-untyped-def]
    """zenoh-python creates and destroys a Python thread state for every sample it hands to a
    callback on its (Rust) receive thread; ``"inline"`` delivery keeps the first one for the
    thread's life: a ``threading.local`` set in the handler is still set at the next sample,
    so at most one fresh state per receive thread is seen over many samples."""
    a = Service("sub", client_config(router)).start()
    b = Service("pub", client_config(router)).start()
    local = threading.local()
    seen = {"samples": 0, "fresh": 0}

    def handler(_m: ArmState, _key: str) -> None:
        seen["samples"] += 1
        if not getattr(local, "mark", False):
            local.mark = True
            seen["fresh"] += 1

    try:
        k = Keys()
        a.subscribe(k.arm_state, handler, delivery="inline")
        pub = b.publisher(k.arm_state)

        def arrived() -> bool:
            pub.put(ArmState(stamp_ns=1, tick=1))
            return seen["samples"] > 0
        assert wait_for(arrived, 10, period_s=0.05)
        for tick in range(2, 202):
            pub.put(ArmState(stamp_ns=tick, tick=tick))
            time.sleep(0.0005)
        assert wait_for(lambda: seen["samples"] >= 201, 10, period_s=0.02)
    finally:
        b.close()
        a.close()
    # zenoh's receive pool has a few threads; without the kept state every sample is fresh
    assert 1 <= seen["fresh"] <= 8, seen


def test_low_latency_transport_peers_exchange_every_message_in_order() -> None:
    """``zenoh.low_latency`` on both ends (as for the arm<->planner loop): the config reaches
    Zenoh (QoS off, which Zenoh requires) and a peer-to-peer link delivers everything in order."""
    from services.bus.config import ServiceConfig, load_config
    from services.bus.runtime import zenoh_config
    from services.supervisor import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    base = {"zenoh.multicast": False, "zenoh.gossip": False, "zenoh.low_latency": True,
            "status_period_s": 0.2}
    cfg_a = load_config(ServiceConfig, env={}, overrides={**base, "zenoh.listen": [endpoint]})
    cfg_b = load_config(ServiceConfig, env={}, overrides={**base, "zenoh.connect": [endpoint]})
    conf = zenoh_config(cfg_a.zenoh)
    assert json.loads(conf.get_json("transport/unicast/lowlatency")) is True
    assert json.loads(conf.get_json("transport/unicast/qos/enabled")) is False
    a = Service("sub", cfg_a).start()
    b = Service("pub", cfg_b).start()
    try:
        _check_in_order_delivery(a, b, "inline")
    finally:
        b.close()
        a.close()


def test_latest_delivery_takes_only_the_newest_sample_on_the_callers_thread(router) -> None:  # type: ignore[no-untyped-def]
    """``"latest"``: nothing runs until ``take()``; then the callback runs once, on the caller's
    thread, with the newest sample; the ones it replaced are neither received nor dropped."""
    a = Service("sub", client_config(router)).start()
    b = Service("pub", client_config(router)).start()
    k = Keys()
    got: list[tuple[int, str]] = []
    try:
        sub = a.subscribe(
            k.arm_state, lambda m, _key: got.append((m.tick, threading.current_thread().name)),
            delivery="latest",
        )
        pub = b.publisher(k.arm_state)

        def route_ready() -> bool:
            pub.put(ArmState(stamp_ns=1, tick=1_000_000))
            time.sleep(0.02)
            return sub.take()
        assert wait_for(route_ready, 10, period_s=0.05)
        got.clear()
        assert not sub.take()  # nothing new
        received = sub.received
        for i in range(200):
            pub.put(ArmState(stamp_ns=i + 1, tick=i))
        time.sleep(0.5)  # all 200 have arrived (loopback): only the newest is kept
        assert sub.take()
        assert got == [(199, threading.current_thread().name)]
        assert sub.received - received == 1 and sub.dropped == 0
        assert not sub.take()
        with pytest.raises(RuntimeError, match="latest"):
            a.subscribe(k.arm_state, lambda m, _key: None).take()
        sub.close()
        assert not sub.take()
    finally:
        b.close()
        a.close()


def test_a_new_peer_reaches_every_peer_with_its_first_sample(router) -> None:  # type: ignore[no-untyped-def]
    """The stack's processes are peers linked directly; the router forwards nothing between
    them. A peer whose session :func:`open_session` returns has linked to every peer already on
    the router (``wait_for_peer_links``), so the first sample it publishes reaches all of them:
    a restarted planner's first command is recorded."""
    from services.bus.config import ServiceConfig, load_config
    from services.bus.runtime import open_session

    def peer_cfg() -> ServiceConfig:
        return load_config(ServiceConfig, env={}, overrides={
            "zenoh.mode": "peer", "zenoh.connect": [router], "zenoh.listen": ["tcp/127.0.0.1:0"],
            "zenoh.multicast": False})

    listeners = [open_session(peer_cfg().zenoh) for _ in range(3)]
    got: list[list[int]] = [[] for _ in listeners]
    subs = [s.declare_subscriber("first/sample", lambda smp, g=g: g.append(int(smp.payload.to_string())))
            for s, g in zip(listeners, got, strict=True)]
    time.sleep(0.5)  # the subscriptions are declared to every peer
    try:
        for n in range(5):
            newcomer = open_session(peer_cfg().zenoh)
            assert len(list(newcomer.info.peers_zid())) >= len(listeners)
            newcomer.put("first/sample", str(n))
            assert wait_for(lambda n=n: all(n in g for g in got), 3.0), (n, got)
            newcomer.close()
    finally:
        for sub in subs:
            sub.undeclare()
        for s in listeners:
            s.close()
