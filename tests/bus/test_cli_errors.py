"""One error line (``psm <command>: error: ...``, exit code 2) for bus failures, through the
real ``psm`` entry point: unreachable router, busy port, invalid key expressions, damaged
recordings given to ``psm replay``, and a recorder retry after a failed start."""

from __future__ import annotations

import signal
import socket
import threading
import time
from pathlib import Path

import pytest

from services.bus.log import read_samples
from services.bus.runtime import RawSample, Service
from services.supervisor import free_port

from .fixture_data import PATH as FIXTURE
from .helpers import bus_args, client_config, one_error_line, run_psm, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def test_unreachable_router_is_one_line_naming_the_endpoint() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    r = run_psm("echo", "--mode", "client", "--connect", ep, "--no-multicast")
    msg = one_error_line(r, "psm echo")
    assert msg.startswith(f"cannot connect to {ep} (client mode)"), msg
    # a nested command prints its whole path
    r = run_psm("camera", "synth", "--mode", "client", "--connect", ep, "--no-multicast")
    assert one_error_line(r, "psm camera synth").startswith(f"cannot connect to {ep}")


def test_listen_port_in_use_is_one_line() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        ep = f"tcp/127.0.0.1:{busy.getsockname()[1]}"
        r = run_psm("serve", "router", "--listen", ep, "--no-multicast")
    msg = one_error_line(r, "psm serve router")
    assert msg == f"cannot listen on {ep} (router mode): address already in use", msg


def test_invalid_key_expressions_are_one_line_naming_the_key(tmp_path: Path) -> None:
    r = run_psm("echo", "bad//key", "--no-multicast")
    msg = one_error_line(r, "psm echo")
    assert msg.startswith("invalid key expression 'bad//key': empty chunks"), msg
    out = tmp_path / "k.mcap"
    r = run_psm("record", "-o", str(out), "-k", "psm/*x", "--no-multicast")
    assert one_error_line(r, "psm record").startswith("invalid key expression 'psm/*x'")
    assert not out.exists()
    r = run_psm("replay", str(FIXTURE), "--exclude", "psm/a#b", "--no-multicast")
    assert one_error_line(r, "psm replay").startswith("invalid key expression 'psm/a#b'")


def _truncated_copy(tmp_path: Path) -> Path:
    """The fixture cut in the middle of its data (complete chunks before the cut)."""
    data = FIXTURE.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 4])
    return cut


def test_replay_of_damaged_files(router: str, tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"this is not an mcap file\n" * 10)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    head_only = tmp_path / "head.mcap"
    head_only.write_bytes(FIXTURE.read_bytes()[:600])  # header, no complete chunk
    cut = _truncated_copy(tmp_path)
    readable = [s for s in read_samples(cut, quiet=True) if s.topic != "psm/arm/command"]
    assert 0 < len(readable) < 47
    got: list[RawSample] = []
    lock = threading.Lock()
    svc = Service("tester", client_config(router)).start()

    def on(raw: RawSample) -> None:
        with lock:
            got.append(raw)

    svc.subscribe_raw("psm/**", on)
    try:
        time.sleep(0.5)
        for path, expect in ((garbage, "not an MCAP file"), (empty, "empty file"),
                             (head_only, "truncated recording (no footer): 0 messages")):
            r = run_psm("replay", str(path), "--as-fast-as-possible", *bus_args(router))
            msg = one_error_line(r, "psm replay")
            assert msg.startswith(f"{path}: {expect}"), msg
        time.sleep(0.3)
        with lock:
            assert [g for g in got if not g.key.startswith("psm/status/")] == []
        # truncated after complete chunks: what is readable is replayed, then exit code 2
        r = run_psm("replay", str(cut), "--as-fast-as-possible", "--wait-subscribers", "5",
                    *bus_args(router))
        msg = one_error_line(r, "psm replay")
        assert "truncated recording (no footer)" in msg
        assert msg.endswith(f"replayed {len(readable)} messages up to there"), msg
        assert wait_for(lambda: sum(not g.key.startswith("psm/status/") for g in got)
                        >= len(readable), 10)
    finally:
        svc.close()
    replayed = [(g.key, g.payload) for g in got if not g.key.startswith("psm/status/")]
    assert replayed == [(s.topic, s.payload) for s in readable]


def test_record_retry_after_failed_start_needs_no_overwrite(procs, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    out = tmp_path / "retry.mcap"
    args = ["record", "-o", str(out), "--mode", "client", "--connect", ep, "--no-multicast",
            "--set", "status_period_s=0.2"]
    r = run_psm(*args)
    assert one_error_line(r, "psm record").startswith(f"cannot connect to {ep}")
    assert not out.exists() and list(tmp_path.iterdir()) == []
    from .helpers import port_open

    router = procs(["-m", "services.cli", "serve", "router", "--listen", ep, "--no-multicast"],
                   "router")
    assert wait_for(lambda: port_open(port) or not router.alive(), 15), router.stderr()
    rec = procs(["-m", "services.cli", *args], "recorder")
    assert wait_for(lambda: (out.exists() and out.stat().st_size > 0) or not rec.alive(), 15)
    assert rec.alive(), rec.stderr()
    time.sleep(1.0)
    rec.signal(signal.SIGTERM)
    assert rec.wait(20) == 0, rec.stderr()
    assert any(s.topic.startswith("psm/status/") for s in read_samples(out, strict=True))
