"""The recorder's disk fills up (a small tmpfs, mounted here as root; skipped with the reason
when mounting is not permitted): it stops writing with one clear error, the file ends validly
(summary, indexes and footer: a seeking reader opens it) up to its last complete chunk, no
reserve file is left behind, and the ``psm record`` process stays up, DEGRADED with the reason.
"""

from __future__ import annotations

import os
import re
import signal
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from stack_helpers import mount_tmpfs, unmount

from services.bus.log import read_log
from services.bus.messages import ArmState, Keys, ServiceStatus, encode
from services.bus.recorder import SUMMARY_RESERVE_MIN, McapSink, RecorderError
from services.bus.runtime import Service

from .helpers import bus_args, client_config, wait_for

K = Keys()


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Callable[[str], Path]]:
    """``small_disk("1m")``: a directory on a tmpfs of that size, unmounted at the end."""
    mounted: list[Path] = []

    def make(size: str) -> Path:
        path = tmp_path / f"disk{len(mounted)}"
        mount_tmpfs(path, size)
        mounted.append(path)
        return path

    yield make
    for path in mounted:
        unmount(path)


def _fill(sink: McapSink, payload_bytes: int) -> tuple[int, str]:
    """Write ArmStates (``payload_bytes`` of incompressible joint values each) until the sink
    refuses; returns how many were accepted and its error."""
    rng = os.urandom
    for i in range(1_000_000):
        q = [int.from_bytes(rng(4), "little") / 7.0 for _ in range(payload_bytes // 9)]
        payload, enc = encode(ArmState(stamp_ns=1000 + i, tick=i, q=q))
        try:
            sink.write(K.arm_state.key, enc, payload, 10_000 + i)
        except RecorderError as exc:
            return i, str(exc)
    raise AssertionError("the disk never filled up")


@pytest.mark.parametrize(("chunk_size", "payload"), [(64 * 1024, 2000), (1024, 200)])
def test_a_full_disk_ends_the_file_validly(small_disk, chunk_size: int, payload: int) -> None:  # type: ignore[no-untyped-def]
    disk = small_disk("1m")
    path = disk / "run.mcap"
    sink = McapSink(path, chunk_size=chunk_size, compression="none", metadata={"config": "{}"})
    accepted, error = _fill(sink, payload)
    assert error.startswith(f"disk full (No space left on device): stopped recording to {path} after ")
    assert "the file is finalised (summary, indexes, footer) after its last complete chunk" in error
    assert "\n" not in error
    with pytest.raises(RecorderError, match="disk full"):  # and on every later write
        sink.write(K.arm_state.key, *encode(ArmState(tick=1))[::-1], 1)
    sink.close()  # nothing more to do
    ticks = [m.tick for _k, m, _t in read_log(path, strict=True)]  # finalised: strict reading
    written = int(re.search(r"after (\d+) messages", error).group(1))  # type: ignore[union-attr]
    lost = int(re.search(r"; (\d+) messages of the open chunk", error).group(1))  # type: ignore[union-attr]
    assert ticks == list(range(written)) and written == sink.message_count
    # The refused message is in the file (the reserve could not grow after its chunk) or in the
    # open chunk that was dropped; nothing else is missing.
    assert written + lost == accepted + 1 and lost <= chunk_size // (payload // 2) + 1
    assert sorted(p.name for p in disk.iterdir()) == ["run.mcap"]  # the reserve is gone
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics.message_count == written
    if chunk_size == 1024:  # hundreds of chunk indexes: the reserve grew beyond its minimum
        assert 2 * len(summary.chunk_indexes) * 90 > SUMMARY_RESERVE_MIN


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_psm_record_on_a_full_disk_stays_up_degraded(small_disk, procs, router) -> None:  # type: ignore[no-untyped-def]
    disk = small_disk("2m")
    out = disk / "rec.mcap"
    statuses: list[ServiceStatus] = []
    watcher = Service("watcher", client_config(router)).start()
    watcher.subscribe(K.status("recorder"), lambda m, _key: statuses.append(m))
    try:
        rec = procs(["-m", "services.bus.cli", "record", "-o", str(out), *bus_args(router),
                     "--set", "recorder.min_free_mb=0", "--set", 'recorder.compression="none"',
                     "--set", "status_period_s=0.2"], "recorder")
        assert wait_for(lambda: bool(statuses) or not rec.alive(), 30), rec.stderr()
        pub = procs(["-m", "tests.bus.pub_tool", router, "--images", "100"], "pub")  # 4 MB
        assert pub.wait(60) == 0, pub.stderr()
        degraded = ServiceStatus.DEGRADED
        assert wait_for(lambda: bool(statuses) and statuses[-1].state == degraded, 10), statuses[-1:]
        assert rec.alive()
        assert statuses[-1].last_error.startswith("disk full (No space left on device)")
        errors = [ln for ln in rec.stderr().splitlines() if " ERROR " in ln]
        assert len(errors) == 1 and "disk full" in errors[0], rec.stderr()
        rec.signal(signal.SIGTERM)
        assert rec.wait(30) == 1, rec.stderr()  # the recording is not whole: exit code 1
    finally:
        watcher.close()
    images = [m for _k, m, _t in read_log(out, topics="psm/camera/*/image", strict=True)]
    assert 10 < len(images) < 100
    assert sorted(p.name for p in disk.iterdir()) == ["rec.mcap"]
