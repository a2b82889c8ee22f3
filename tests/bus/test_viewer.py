"""``psm view``: the live viewer, a Foxglove WebSocket server fed from the bus.

Integration: a router, ``psm view`` and a publisher of real messages (``tests.bus.stream_tool``:
a latched goal, arm states at 500 Hz, camera images at 30 Hz) on loopback; a WebSocket client
with the ``foxglove.sdk.v1`` sub-protocol checks the advertised channels (topic, schema name,
encoding, schema = the FileDescriptorSet), subscribes, decodes the message-data frames with the
project's protobuf classes (the bytes are the published ones, the log time is the stamp) and
measures the throttled rates. Unit: the throttle, the config, ``psm up --view``, the one-line
errors.
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import re
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from services.bus.messages import (
    ArmState,
    CompressedImage,
    Goal,
    file_descriptor_set,
)
from services.supervisor import free_port
from services.viewer.config import DEFAULT_MAX_RATE_HZ, ViewerSection
from services.viewer.service import _Stream

from .helpers import Proc, bus_args, one_error_line, port_open, run_psm, wait_for
from .pub_tool import goal, state

SUBPROTOCOL = "foxglove.sdk.v1"


# --------------------------------------------------------------------------------------------
# A minimal Foxglove WebSocket client
# --------------------------------------------------------------------------------------------


@dataclass
class Received:
    """What a client saw: advertised channels by id, and per topic (arrival monotonic time
    [s], log time [ns], payload) of every message-data frame."""

    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)
    messages: dict[str, list[tuple[float, int, bytes]]] = field(default_factory=dict)
    #: the server's status messages (text), in arrival order
    statuses: list[str] = field(default_factory=list)
    #: channels subscribed again after the server refused them as unknown (see _watch)
    resubscribed: list[int] = field(default_factory=list)

    def topic(self, topic: str) -> dict[str, Any]:
        return next(c for c in self.channels.values() if c["topic"] == topic)


async def _watch(port: int, seconds: float, out: Received,
                 until: Callable[[Received], bool] | None = None) -> None:
    """Connect, subscribe to every advertised channel, collect for ``seconds`` (or until
    ``until(out)``)."""
    import websockets

    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                  max_size=None) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not (until is not None and until(out)):
            try:
                frame = await asyncio.wait_for(ws.recv(), max(0.01, deadline - time.monotonic()))
            except TimeoutError:
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    out.server_info = msg
                elif msg["op"] == "advertise":
                    subs = []
                    for ch in msg["channels"]:
                        out.channels[ch["id"]] = ch
                        subs.append({"id": ch["id"], "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                elif msg["op"] == "status":
                    out.statuses.append(msg.get("message", ""))
                    # foxglove-sdk (0.30.3) queues a new channel's advertisement before it adds
                    # the channel to the client's table, so a subscription that arrives in between
                    # is refused as "Unknown channel ID" (docs/bus.md#live-view). A client that
                    # was advertised the channel subscribes again, as a robust client must.
                    m = re.fullmatch(r"Unknown channel ID: (\d+)", msg.get("message", ""))
                    if m and int(m.group(1)) in out.channels and len(out.resubscribed) < 100:
                        cid = int(m.group(1))
                        out.resubscribed.append(cid)
                        await ws.send(json.dumps(
                            {"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid}]}))
                continue
            assert frame[0] == 1, f"unexpected binary opcode {frame[0]}"
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            topic = out.channels[sub_id]["topic"]
            out.messages.setdefault(topic, []).append((time.monotonic(), log_time, bytes(frame[13:])))


def watch(port: int, seconds: float, until: Callable[[Received], bool] | None = None) -> Received:
    out = Received()
    asyncio.run(_watch(port, seconds, out, until))
    return out


def _rate_bound(stamps_ns: list[int], hz: float) -> tuple[int, float]:
    """(count, most allowed) of messages over the window of their publication stamps at
    ``hz``: the throttle lets at most window·hz + 1 through in the viewer's time; + 2 for the
    publisher's and the viewer's scheduling (a sample reaching the viewer late or early)."""
    window_s = (stamps_ns[-1] - stamps_ns[0]) / 1e9
    return len(stamps_ns), window_s * hz + 3


# --------------------------------------------------------------------------------------------
# Integration
# --------------------------------------------------------------------------------------------


def _start_viewer(procs: Callable[..., Proc], router: str, *extra: str) -> int:
    port = free_port()
    p = procs(["-m", "services.cli", "view", "--port", str(port), *bus_args(router),
               "--set", "status_period_s=0.2", *extra], "viewer")
    assert wait_for(lambda: port_open(port) or not p.alive(), 30.0) and p.alive(), p.stderr()
    assert wait_for(lambda: "Foxglove WebSocket server listening" in p.stderr() or not p.alive(), 30.0), \
        p.stderr()
    return port


@pytest.mark.integration
def test_the_viewer_forwards_the_bus_to_a_foxglove_client_throttled(
    procs: Callable[..., Proc], router: str
) -> None:
    port = _start_viewer(procs, router)
    pub = procs(["-m", "tests.bus.stream_tool", router, "--seconds", "4"], "stream")
    expected = ("psm/arm/state", "psm/goals/person", "psm/camera/cam0/image")
    seen = watch(port, 20.0, until=lambda r: not pub.alive() and all(t in r.messages for t in expected))
    assert pub.wait(10.0) == 0, pub.stderr()
    sent = json.loads(pub.stdout().strip().splitlines()[-1])
    assert sent["states"] > 1500 and sent["images"] > 90, sent
    assert all(t in seen.messages for t in expected), (
        {t: len(m) for t, m in seen.messages.items()}, sorted(c["topic"] for c in seen.channels.values()),
        seen.statuses)

    # Server: the SDK's, speaking foxglove.sdk.v1, named after the cell.
    assert seen.server_info["name"] == "psm psm"
    # One channel per key, the schema named by the sample's encoding, protobuf, with the
    # FileDescriptorSet of the type.
    for topic, schema in (("psm/arm/state", "psm.ArmState"), ("psm/goals/person", "psm.Goal"),
                          ("psm/camera/cam0/image", "foxglove.CompressedImage"),
                          ("psm/status/streamtool", "psm.ServiceStatus")):
        ch = seen.topic(topic)
        assert (ch["schemaName"], ch["encoding"], ch["schemaEncoding"]) == (schema, "protobuf", "protobuf")
        assert base64.b64decode(ch["schema"]) == file_descriptor_set(schema)
    assert len({c["topic"] for c in seen.channels.values()}) == len(seen.channels)

    # The payloads are the published bytes; the log time is the message's own stamp.
    states = seen.messages["psm/arm/state"]
    for _, log_time, payload in states:
        msg = ArmState.FromString(payload)
        assert payload == state(msg.tick).SerializeToString()
        assert log_time == msg.stamp_ns
    goals = seen.messages["psm/goals/person"]
    assert [Goal.FromString(p) for _, _, p in goals][:1] == [goal(0)]
    images = seen.messages["psm/camera/cam0/image"]
    for _, log_time, payload in images:
        img = CompressedImage.FromString(payload)
        assert img.format == "jpeg" and len(img.data) == 20_000
        assert log_time == img.timestamp.seconds * 1_000_000_000

    # The throttle: 500 Hz states arrive at <= 50 Hz, 30 Hz images at <= 10 Hz — and not far
    # below (the stream was not simply cut).
    n, most = _rate_bound([t for _, t, _ in states], DEFAULT_MAX_RATE_HZ["psm.ArmState"])
    assert 0.6 * (most - 3) <= n <= most, (n, most)
    arrivals_ns = [round(t * 1e9) for t, _, _ in images]  # the fake images repeat 8 stamps
    n, most = _rate_bound(arrivals_ns, DEFAULT_MAX_RATE_HZ["foxglove.CompressedImage"])
    assert 0.6 * (most - 3) <= n <= most, (n, most)

    # A client that connects later gets the latched goal when it subscribes.
    late = watch(port, 10.0, until=lambda r: "psm/goals/person" in r.messages)
    assert "psm/goals/person" in late.messages, (sorted(late.messages), late.statuses)
    assert [Goal.FromString(p) for _, _, p in late.messages["psm/goals/person"]] == [goal(0)]


@pytest.mark.integration
def test_a_rate_limit_of_zero_forwards_every_sample(procs: Callable[..., Proc], router: str) -> None:
    """The limit is what throttles (the test above would fail without it): unthrottled, the
    client gets the 500 Hz stream whole once it is subscribed."""
    port = _start_viewer(procs, router, "--set", 'viewer.max_rate_hz={"psm.ArmState"=0}')
    # Long enough for the client to subscribe on a loaded machine (the viewer advertises a
    # channel when its first sample arrives; the client subscribes to it then).
    pub = procs(["-m", "tests.bus.stream_tool", router, "--seconds", "6", "--image-hz", "1"], "stream")
    seen = watch(port, 30.0, until=lambda r: not pub.alive() and "psm/arm/state" in r.messages)
    assert pub.wait(10.0) == 0, pub.stderr()
    ticks = [ArmState.FromString(p).tick for _, _, p in seen.messages["psm/arm/state"]]
    assert len(ticks) > 1000
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks))), "lost or reordered samples"


# --------------------------------------------------------------------------------------------
# Errors: one line, exit code 2
# --------------------------------------------------------------------------------------------


def test_a_bad_config_value_is_one_error_line() -> None:
    result = run_psm("view", "--set", 'viewer.max_rate_hz={"psm.Nope"=5}', "--no-multicast")
    assert one_error_line(result, "psm view").startswith(
        "viewer.max_rate_hz: unknown message type 'psm.Nope' (known: foxglove.CompressedImage,")
    result = run_psm("view", "--port", "70000", "--no-multicast")
    assert one_error_line(result, "psm view") == (
        "viewer.port: Input should be less than or equal to 65535 (got 70000)")


def test_a_busy_port_is_one_error_line() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        result = run_psm("view", "--port", str(port), "--no-multicast")
    assert one_error_line(result, "psm view") == (
        f"cannot serve the Foxglove WebSocket on 127.0.0.1:{port}: address already in use")


# --------------------------------------------------------------------------------------------
# Units
# --------------------------------------------------------------------------------------------


def test_the_throttle_never_exceeds_its_rate_and_restarts_after_a_pause() -> None:
    st = _Stream("psm/arm/state", "", False, period_ns=20_000_000)  # 50 Hz
    # 500 Hz for 1 s, with jitter: at most 51 in any window of 1 s, and close to 50.
    times = [i * 2_000_000 + (i * 7919 % 1_500_000) for i in range(500)]
    passed = [t for t in times if st.admit(t)]
    assert 49 <= len(passed) <= 51
    assert all(b - a >= 10_000_000 for a, b in itertools.pairwise(passed))
    for start in range(0, 500_000_000, 5_000_000):
        assert sum(start <= t < start + 100_000_000 for t in passed) <= 6  # 100 ms: ≤ 5 + 1
    assert st.throttled == len(times) - len(passed)
    # A pause: the next sample passes at once.
    assert st.admit(5_000_000_000) and not st.admit(5_010_000_000) and st.admit(5_020_000_000)
    # Unthrottled.
    free = _Stream("psm/goals/x", "", True, period_ns=0)
    assert all(free.admit(t) for t in range(10))


class _SubscribingSample:
    """A ring sample whose key is read by the forwarding pass; reading the key of the sample
    with tick ``subscribe_at`` subscribes a client first (as the server's thread would, mid-pass)."""

    def __init__(self, viewer: Any, channel_id: int, tick: int, subscribe_at: int) -> None:
        self._viewer, self._channel_id, self.tick, self._at = viewer, channel_id, tick, subscribe_at
        self.encoding = "psm.ArmState"
        self.payload = SimpleNamespace(to_bytes=lambda: state(tick).SerializeToString())

    @property
    def key_expr(self) -> str:
        if self.tick == self._at:
            self._viewer.subscribed(self._channel_id, +1)
        return "psm/arm/state"


def test_a_client_subscribing_mid_batch_gets_the_stream_from_then_on_without_a_gap() -> None:
    """The forwarding pass takes a batch newest first; a subscription landing in the middle of
    it must not forward the batch's older samples (the client would see tick 0, then 5, 6…)."""
    import queue as queue_mod
    import threading

    from services.viewer.service import ViewerService

    logged: list[int] = []
    channel = SimpleNamespace(id=lambda: 7, log=lambda payload, log_time: logged.append(
        ArmState.FromString(payload).tick))
    viewer = ViewerService.__new__(ViewerService)
    st = _Stream("psm/arm/state", "psm.ArmState", False, period_ns=0)
    st.channel = channel
    viewer._streams, viewer._by_channel, viewer._early = {st.key: st}, {7: st}, {}
    viewer._lock, viewer._q = threading.Lock(), queue_mod.SimpleQueue()
    viewer.config = SimpleNamespace(queue_size=64)
    viewer.section = SimpleNamespace(log_time="receipt")
    viewer.svc = SimpleNamespace(counters=SimpleNamespace(add=lambda *a: None))

    def ring(ticks: range, subscribe_at: int) -> SimpleNamespace:
        items = iter([_SubscribingSample(viewer, 7, t, subscribe_at) for t in ticks])
        return SimpleNamespace(try_recv=lambda: next(items, None))

    viewer._rings = [ring(range(0, 5), subscribe_at=2)]  # subscribes while tick 2 is looked at
    viewer._drain()
    assert logged == []  # the newer ticks 3, 4 were passed over unsubscribed: none of the batch
    viewer._rings = [ring(range(5, 10), subscribe_at=-1)]
    viewer._drain()
    assert logged == [5, 6, 7, 8, 9]


def test_rate_limits_merge_with_the_defaults_and_name_bus_types() -> None:
    sec = ViewerSection(max_rate_hz={"psm.ArmState": 0, "psm.PlannerStatus": 5})
    assert sec.max_rate_hz == {**DEFAULT_MAX_RATE_HZ, "psm.ArmState": 0.0, "psm.PlannerStatus": 5.0}
    assert sec.period_ns("psm.ArmState") == 0
    assert sec.period_ns("psm.PlannerStatus") == 200_000_000
    assert sec.period_ns("foxglove.CompressedImage") == 100_000_000
    assert sec.period_ns("psm.Goal") == 0
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=">= 0 Hz"):
        ViewerSection(max_rate_hz={"psm.ArmState": -1})
    with pytest.raises(ValidationError, match="invalid key expression"):
        ViewerSection(key_exprs=["psm//x"])


def test_psm_up_view_adds_the_viewer_after_the_router_not_required() -> None:
    from services.bus.config import ConfigError
    from services.stack import DEFAULT_STACK, load_stack
    from services.viewer.config import ViewerConfig

    plain = load_stack(DEFAULT_STACK, env={}, overrides={"viewer.port": 9001})
    assert "viewer" not in [p.name for p in plain.processes]  # the shipped stack runs without it
    stack = load_stack(DEFAULT_STACK, env={}, overrides={"viewer.port": 9001}, view=True)
    names = [p.name for p in stack.processes]
    assert names[:2] == ["router", "viewer"] and names[2:] == [p.name for p in plain.processes][1:]
    spec = stack.processes[1]
    assert spec.command == ["view"] and not spec.required and spec.restart == "no"
    assert spec.needs == ["router"]
    cfg = stack.configs["viewer"]
    assert isinstance(cfg, ViewerConfig) and cfg.viewer.port == 9001
    with pytest.raises(ConfigError, match=r"viewer\.max_rate_hz: unknown message type"):
        load_stack(DEFAULT_STACK, env={}, overrides={"viewer.max_rate_hz": {"x": 1}})


def test_psm_up_view_refuses_a_second_viewer(tmp_path: Path) -> None:
    from services.stack import DEFAULT_STACK

    text = DEFAULT_STACK.read_text() + '\n[[stack.processes]]\nname = "viewer"\ncommand = ["view"]\n'
    path = tmp_path / "stack.toml"
    path.write_text(text.replace("[router]\n", "[viewer]\nport = 9002\n\n[router]\n", 1))
    result = run_psm("up", str(path), "--check")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().endswith("planner, viewer")
    result = run_psm("up", str(path), "--check", "--view")
    assert one_error_line(result, "psm up") == (
        "stack.processes: --view adds a process 'viewer' running 'psm view'; the stack file "
        "already has one")


def test_psm_up_check_with_view_lists_the_viewer() -> None:
    result = run_psm("up", "--check", "--view")
    assert result.returncode == 0, result.stderr
    assert "processes: router, viewer, recorder," in result.stdout
