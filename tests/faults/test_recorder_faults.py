"""The recorder's faults in the running shipped stack (realtime, real processes on loopback):

* killed with SIGKILL mid-task: its file is readable up to its last complete chunk, which is at
  most about ``flush_interval_s`` before the kill; no other service notices (no error, no new
  DEGRADED state, the control loop's rates unchanged) and the task completes — the stack does
  not require the recorder (``required = false``);
* its disk fills up (the recording on a 2 MB tmpfs): it stops writing with one error line and
  DEGRADED with the reason on its status, stays up, its file ends validly (summary and footer)
  at its last complete chunk, and the rest of the stack completes the task.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from stack_helpers import (
    LOAD_TOLERANT,
    ROOT,
    StackWatch,
    check_task,
    mount_tmpfs,
    record_fault,
    unmount,
    up_args,
    up_port,
    wait_planner,
    wait_stack_up,
)

from services.supervisor import ManagedProcess, psm_argv

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(300)]

#: The other processes' services.
OTHERS = ("router", "arm", "camera_synth", "goal_tracker", "obstacle_monitor", "planner")
WINDOW_NS = 3_000_000_000


def _degraded(status: Any) -> str:
    """Why a status is DEGRADED, ``""`` if it is not. The realtime arm's missed ticks on a loaded
    machine are its own, not a reaction to the fault."""
    from services.bus.messages import ServiceStatus

    if status.state != ServiceStatus.DEGRADED or status.last_error.startswith("realtime:"):
        return ""
    return status.last_error


def _run(tmp_path: Path, *sets: str, fault: Any) -> tuple[int | None, str, dict[str, Any]]:
    """Run the stack to its end with ``fault(up, watch, port)`` applied once the planner moves;
    returns the supervisor's exit code, its log and what ``fault`` returned, plus the other
    services' statuses before and after (``before``, ``after``) and the control loop's rates."""
    args = up_args(tmp_path, "realtime", *LOAD_TOLERANT, *sets)
    port = up_port(args)
    up = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    watch: StackWatch | None = None
    try:
        deadline = time.monotonic() + 120
        wait_stack_up(up, deadline)
        watch = StackWatch(port, f"feed{port}")
        wait_planner(port, deadline, min_step=0)
        watch.wait(lambda: all(s in watch.status for s in OTHERS), 10, "statuses")  # type: ignore[union-attr]
        time.sleep(WINDOW_NS * 1e-9)
        before = {s: watch.status[s] for s in OTHERS}
        t_fault = time.time_ns()
        out = fault(up, watch, port)
        time.sleep(WINDOW_NS * 1e-9)
        t_after = time.time_ns()
        after = {s: watch.status[s] for s in OTHERS}
        out.update(
            before=before, after=after,
            state_rate=(watch.rate(watch.states, t_fault - WINDOW_NS, t_fault),
                        watch.rate(watch.states, t_after - WINDOW_NS, t_after)),
            command_rate=(watch.rate(watch.commands, t_fault - WINDOW_NS, t_fault),
                          watch.rate(watch.commands, t_after - WINDOW_NS, t_after)),
            fault_ns=t_fault,
        )
        rc = up.wait(150)
    finally:
        if watch is not None:
            watch.close()
        up.stop()
    return rc, up.log_text(), out


def _nobody_noticed(out: dict[str, Any]) -> None:
    for name in OTHERS:
        b, a = out["before"][name], out["after"][name]
        assert a.errors == b.errors, (name, a.last_error)
        assert not _degraded(a), (name, a.last_error)
    (s0, s1), (c0, c1) = out["state_rate"], out["command_rate"]
    assert s1 > 0.9 * s0 and c1 > 0.9 * c0, (out["state_rate"], out["command_rate"])


def test_the_recorder_killed_leaves_its_file_readable_and_nobody_notices(tmp_path: Path) -> None:
    from services.bus.log import LogReadError, read_log, scan_log

    def kill(up: ManagedProcess, _watch: StackWatch, _port: int) -> dict[str, Any]:
        from stack_helpers import started_pids

        killed_ns = time.time_ns()
        os.kill(started_pids(up.log_text())["recorder"], signal.SIGKILL)
        return {"killed_ns": killed_ns}

    rc, log, out = _run(tmp_path, fault=kill)
    # The stack went on: the task completed; psm up reports the recorder's exit at the end.
    assert rc == 1 and "recorder exited with code -9; it is not required" in log, log
    assert "psm up: error: recorder exited with -9" in log
    check_task(json.loads((tmp_path / "run" / "summary.json").read_text()), log)
    _nobody_noticed(out)
    # The file: no footer, readable to its last complete chunk.
    recording = tmp_path / "run.mcap"
    with pytest.raises(LogReadError):
        list(read_log(recording, strict=True))
    scan = scan_log(recording)
    states = [int(m.stamp_ns) for k, m, _t in read_log(recording) if k.endswith("/arm/state")]
    assert states and scan.messages > 1000
    lag_s = (out["killed_ns"] - states[-1]) * 1e-9
    assert lag_s < 1.0 + 0.5, lag_s  # flush_interval_s (1 s), and the kill's own moment
    record_fault("recorder_sigkill", {
        "test": "test_the_recorder_killed_leaves_its_file_readable_and_nobody_notices",
        "fault": "recorder killed (SIGKILL) mid-task",
        "messages_readable": scan.messages,
        "last_recorded_before_the_kill_s": lag_s,
        "other_services_errors": 0,
        "arm_state_rate_before_after_hz": out["state_rate"],
        "command_rate_before_after_hz": out["command_rate"],
        "task_success": True,
    })


def test_the_recorders_disk_full_stops_the_recording_not_the_stack(tmp_path: Path) -> None:
    from services.bus.log import read_log, scan_log
    from services.bus.messages import ServiceStatus

    disk = tmp_path / "disk"
    mount_tmpfs(disk, "2m")
    try:
        recording = disk / "run.mcap"

        def fill(_up: ManagedProcess, watch: StackWatch, _port: int) -> dict[str, Any]:
            # 2 MB of camera frames and states take a few seconds: full by now, or soon.
            watch.wait(lambda: watch.status["recorder"].state == ServiceStatus.DEGRADED, 60,
                       "the recorder does not report the full disk")
            return {"recorder_status": watch.status["recorder"]}

        rc, log, out = _run(tmp_path, f'recorder.output="{recording}"', "recorder.min_free_mb=0",
                            fault=fill)
        rec_log = (tmp_path / "run" / "recorder.log").read_text()
        names = sorted(p.name for p in disk.iterdir())
        scan = scan_log(recording)
        states = sum(1 for k, _m, _t in read_log(recording, strict=True) if k.endswith("/arm/state"))
    finally:
        unmount(disk)
    # The recorder stayed up to the end, with one error line; exit code 1 (not whole).
    assert rc == 1 and "psm up: error: recorder exited with 1" in log, log
    assert "recorder exited with code" not in log  # it never died
    errors = [ln for ln in rec_log.splitlines() if " ERROR " in ln]
    assert len(errors) == 1 and "disk full (No space left on device)" in errors[0], rec_log[-3000:]
    status = out["recorder_status"]
    assert status.last_error.startswith("disk full") and "finalised" in status.last_error
    # The file ends validly; the reserve is gone.
    assert names == ["run.mcap"] and scan.problem == "" and states > 0
    # The rest of the stack noticed nothing and did the task.
    check_task(json.loads((tmp_path / "run" / "summary.json").read_text()), log)
    _nobody_noticed(out)
    record_fault("recorder_disk_full", {
        "test": "test_the_recorders_disk_full_stops_the_recording_not_the_stack",
        "fault": "recorder's disk full (2 MB tmpfs)",
        "error_line": errors[0].split(": ", 1)[1].split(" suppressed=")[0].replace(str(disk), "<tmpfs>"),
        "messages_in_the_finalised_file": scan.messages,
        "file_valid": True,
        "other_services_errors": 0,
        "arm_state_rate_before_after_hz": out["state_rate"],
        "command_rate_before_after_hz": out["command_rate"],
        "task_success": True,
    })
