"""The time rule of recordings (docs/bus.md, "Time in recordings"): ``publish_time`` is the
message's own stamp on every channel, 0 included; only a message without a stamp field gets
the receive time; ``log_time`` is always the recorder's receive time. A real recorder process
on loopback records messages stamped 0, 1 and 2 ms."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from services.bus.messages import ArmState, CompressedImage, FrameTransforms, Keys
from services.bus.runtime import Service

from .helpers import bus_args, client_config, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

STAMPS_NS = [0, 1_000_000, 2_000_000]


def _image(ns: int) -> CompressedImage:
    img = CompressedImage(frame_id="cam0", format="jpeg", data=b"\xff\xd8" * 8)
    img.timestamp.FromNanoseconds(ns)
    return img


def _transforms(ns: int) -> FrameTransforms:
    tf = FrameTransforms()
    for child in ("link1", "link2"):
        t = tf.transforms.add(parent_frame_id="base", child_frame_id=child)
        t.timestamp.FromNanoseconds(ns)
    return tf


def test_publish_time_is_the_own_stamp_zero_included(procs, router, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "time.mcap"
    rec = procs(["-m", "services.cli", "record", "-o", str(out), "--no-history",
                 *bus_args(router)], "recorder")
    assert wait_for(lambda: (out.exists() and out.stat().st_size > 0) or not rec.alive(), 15)
    assert rec.alive(), rec.stderr()
    k = Keys()
    svc = Service("stamper", client_config(router)).start()
    try:
        pubs = {"state": svc.publisher(k.arm_state), "image": svc.publisher(k.camera_image("cam0")),
                "tf": svc.publisher(k.arm_transforms)}
        assert wait_for(lambda: all(p.has_subscribers for p in pubs.values()), 10)
        time.sleep(0.5)
        t_before = time.time_ns()
        for ns in STAMPS_NS:
            pubs["state"].put(ArmState(stamp_ns=ns, tick=ns // 1_000_000, sim_time_ns=ns))
            pubs["image"].put(_image(ns))
            pubs["tf"].put(_transforms(ns))
            svc.session.put("psm/raw/text", b"no stamp here", encoding="text/plain")
            time.sleep(0.01)
        time.sleep(0.5)
        t_after = time.time_ns()
    finally:
        svc.close()
    rec.signal(signal.SIGTERM)
    assert rec.wait(20) == 0, rec.stderr()
    got: dict[str, list[tuple[int, int]]] = {}
    with out.open("rb") as fh:
        for _s, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            if "/status/" not in channel.topic:
                got.setdefault(channel.topic, []).append((msg.publish_time, msg.log_time))
    for key in (k.arm_state.key, k.camera_image("cam0").key, k.arm_transforms.key):
        assert [p for p, _ in got[key]] == STAMPS_NS, key  # the own stamps, 0 included
    for key, times in got.items():
        logs = [lt for _, lt in times]
        assert logs == sorted(logs) and all(t_before <= lt <= t_after for lt in logs), key
    # no stamp field at all: publish_time falls back to the receive time
    assert [p for p, lt in got["psm/raw/text"]] == [lt for _, lt in got["psm/raw/text"]]
