"""The clock sampler (the synthetic camera on the arm's clock) can never block the control loop.

The arm's state is a control stream: reliable, blocking under congestion. A subscriber that stops
reading (a stalled process, a camera host cut off) fills the router's queue towards it, and the
router then blocks the publisher's link for zenoh's ``wait_before_close`` (5 s) before closing the
stalled link: the control loop stalls with it. The router sends the state to the clock sampler's
session (:func:`~services.bus.messages.clock_sampler_zid`) droppable instead
(:func:`~services.bus.messages.clock_sampler_qos`).

Here, on loopback: a router with the project's rules, a subscriber process stopped with SIGSTOP,
and a publisher putting the arm's state with the control stream's QoS. With the sampler's id the
publisher never waits; with another id it is blocked for seconds (the control case shows the test
measures what it claims).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.bus.messages import QOS_CONTROL, Keys, clock_sampler_qos, clock_sampler_zid
from services.supervisor import free_port

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

ROOT = Path(__file__).resolve().parents[2]
PREFIX = "clk"

#: The subscriber: a client session with the given id, reading the arm's state until stopped.
SUBSCRIBER = """
import sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:%d"]' % int(sys.argv[1]))
conf.insert_json5("scouting/multicast/enabled", "false")
if sys.argv[2]:
    conf.insert_json5("id", '"%s"' % sys.argv[2])
s = zenoh.open(conf)
n = [0]
sub = s.declare_subscriber(sys.argv[3], lambda sample: n.__setitem__(0, n[0] + 1))
print("ready", flush=True)
t0 = time.monotonic()
while time.monotonic() - t0 < 60:
    time.sleep(0.05)
"""


def _router(port: int) -> object:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("qos/network", json.dumps(clock_sampler_qos(Keys(PREFIX))))
    return zenoh.open(conf)


def _longest_put_while_stopped(sampler_id: str) -> float:
    """Longest ``put`` [s] of 16 kB arm states over 8 s while the subscriber with zenoh id
    ``sampler_id`` ('' = random) is stopped."""
    import zenoh

    port = free_port()
    router = _router(port)
    key = Keys(PREFIX).arm_state.key
    proc = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, str(port), sampler_id, key],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )
    pub_session = None
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        pub_session = zenoh.open(conf)
        pub = pub_session.declare_publisher(
            key,
            congestion_control=getattr(zenoh.CongestionControl, QOS_CONTROL.congestion),
            priority=getattr(zenoh.Priority, QOS_CONTROL.priority),
            express=QOS_CONTROL.express,
            reliability=zenoh.Reliability.RELIABLE,
        )
        payload = bytes(16_384)
        for _ in range(50):  # the subscription reaches the router
            pub.put(payload)
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGSTOP)
        longest, t_end = 0.0, time.monotonic() + 8.0
        while time.monotonic() < t_end:
            t0 = time.monotonic()
            pub.put(payload)
            longest = max(longest, time.monotonic() - t0)
        return longest
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
        proc.wait(10)
        if pub_session is not None:
            pub_session.close()
        router.close()  # type: ignore[attr-defined]


def test_a_stopped_clock_sampler_never_blocks_the_arm_state() -> None:
    assert _longest_put_while_stopped(clock_sampler_zid(PREFIX)) < 0.5


def test_a_stopped_subscriber_of_another_id_blocks_it_for_seconds() -> None:
    """The control case: the same subscriber without the sampler's id blocks the publisher
    (zenoh's wait_before_close, 5 s, before the router closes the stalled link)."""
    assert _longest_put_while_stopped("") > 2.0


def test_the_stacks_sessions_carry_the_rule_and_the_camera_the_id() -> None:
    """The arm (sending to a peer) and the router (routing to clients) have the rule for their
    prefix; the shipped stack's synthetic camera, on the arm's clock, has the sampler's id."""
    from types import SimpleNamespace

    from services.arm.service import ArmService
    from services.bus.router import RouterConfig
    from services.goal_tracker.service import SyntheticCameraService
    from services.stack import load_stack

    stack = load_stack(ROOT / "configs" / "stack.toml", overrides={"prefix": "cell2"})
    rules = clock_sampler_qos(Keys("cell2"))
    assert rules[0]["key_exprs"] == ["cell2/arm/state"]
    router = next(p for p in stack.processes if p.is_router)
    router_cfg = stack.configs[router.name]
    assert isinstance(router_cfg, RouterConfig) and router_cfg.session_extra()["qos/network"] == rules
    # The services' methods on their configs alone: building an ArmService would give this
    # process the arm's real-time priority (and every process it starts after).
    arm = SimpleNamespace(config=stack.configs["arm"])
    assert ArmService.zenoh_extra(arm) == {"qos/network": rules}  # type: ignore[arg-type]
    cam_cfg = stack.configs["camera"]
    camera = SimpleNamespace(config=cam_cfg, sec=cam_cfg.goal_tracker)  # type: ignore[attr-defined]
    assert SyntheticCameraService.zenoh_extra(camera) == {"id": clock_sampler_zid("cell2")}  # type: ignore[arg-type]
    assert clock_sampler_zid("cell2") != clock_sampler_zid("psm")
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_a_second_clock_sampler_on_a_prefix_is_refused_with_an_error_naming_its_id() -> None:
    """zenoh refuses a second session with the id of one already connected, as if nothing had
    answered: the error says which id, and why it is fixed."""
    from services.bus.config import ZenohConfig
    from services.bus.errors import BusError
    from services.bus.runtime import open_session

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_session(ZenohConfig(mode="router", listen=[endpoint], multicast=False))
    client = ZenohConfig(mode="client", connect=[endpoint], multicast=False)
    zid = clock_sampler_zid(PREFIX)
    first = open_session(client, {"id": zid})
    try:
        with pytest.raises(BusError, match=f"as zenoh id {zid}: a session with this id is already connected"):
            open_session(client, {"id": zid})
        open_session(client).close()  # another id connects
    finally:
        first.close()
        router.close()
