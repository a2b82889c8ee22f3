"""``psm up``: the supervisor starts a stack in order, reports a process that dies with its
log's tail and stops everything, and leaves no process behind — also when it is SIGKILLed."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.supervisor import ManagedProcess, free_port, psm_argv

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]


def _header(port: int, tmp_path: Path, startup_timeout_s: float = 40.0) -> str:
    """The bus settings and ``[stack]`` table of a lockstep test stack on ``port``."""
    return f"""
prefix = "psmtest{port}"
clock = "lockstep"
log_level = "INFO"
status_period_s = 0.2
[zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:{port}"]
multicast = false
[stack]
name = "test"
startup_timeout_s = {startup_timeout_s}
stop_timeout_s = 10.0
run_dir = "{tmp_path / 'run'}"
"""


def _stack(tmp_path: Path, extra: str = "", arm: str = "", procs: dict[str, str] | None = None) -> Path:
    """A lockstep stack of router, recorder and arm; ``procs``: more lines of a process's
    ``[[stack.processes]]`` entry by its name (e.g. a restart policy)."""
    more = procs or {}
    port = free_port()
    text = _header(port, tmp_path) + f"""[[stack.processes]]
name = "router"
command = ["serve", "router"]
{more.get("router", "")}
[[stack.processes]]
name = "recorder"
command = ["record"]
{more.get("recorder", "")}
[[stack.processes]]
name = "arm"
command = ["arm"]
{more.get("arm", "")}
{extra}
[router]
listen = ["tcp/127.0.0.1:{port}"]
[recorder]
output = "{tmp_path / 'run.mcap'}"
[arm]
dt_s = 0.002
{arm}
"""
    path = tmp_path / "stack.toml"
    path.write_text(text)
    return path


def _up(stack: Path, *args: str, tmp_path: Path) -> ManagedProcess:
    return ManagedProcess("up", psm_argv(["up", str(stack), *args]), tmp_path / "up.log", cwd=ROOT)


@contextlib.contextmanager
def _running(stack: Path, *args: str, tmp_path: Path) -> Iterator[ManagedProcess]:
    """``psm up`` of ``stack`` for the block; stopped (and reaped) whatever the block does."""
    up = _up(stack, *args, tmp_path=tmp_path)
    try:
        yield up
    finally:
        up.stop()


def _run(stack: Path, *args: str, tmp_path: Path, timeout_s: float = 120.0) -> tuple[int | None, str]:
    """Run ``psm up`` of ``stack`` to its end: its exit code and its output."""
    with _running(stack, *args, tmp_path=tmp_path) as up:
        rc = up.wait(timeout_s)
    return rc, up.log_text()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie waiting for its (gone) parent counts as gone
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _child_pids(log: str) -> dict[str, int]:
    out = {}
    for line in log.splitlines():
        if line.startswith("started ") and "(pid " in line:
            name = line.split()[1]
            out[name] = int(line.rsplit("(pid ", 1)[1].split(")")[0])
    return out


def _wait_for(pred, timeout_s: float) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.1)
    return bool(pred())


def test_up_runs_the_stack_for_a_duration_and_summarises(tmp_path: Path) -> None:
    from services.bus.log import read_log

    rc, log = _run(_stack(tmp_path), "--duration", "4", "--clock", "lockstep", "--no-live", tmp_path=tmp_path)
    assert rc == 0, log
    assert set(_child_pids(log)) == {"router", "recorder", "arm"}
    for name in ("router", "recorder", "arm"):
        assert any(line.lstrip("│ ").startswith(name) for line in log.splitlines()), log
    assert "recording:" in log and "ran 4 s" in log
    assert not any(_alive(pid) for pid in _child_pids(log).values())
    topics = {topic for topic, _msg, _stamp in read_log(tmp_path / "run.mcap")}
    assert any(k.endswith("/arm/state") for k in topics), topics


def test_a_process_that_dies_stops_the_stack_with_its_log(tmp_path: Path) -> None:
    # The arm's model cannot be loaded: the arm exits during start-up with one error line.
    rc, log = _run(_stack(tmp_path, arm='urdf = "/nonexistent/robot.urdf"'), "--no-live", tmp_path=tmp_path)
    assert rc == 1, log
    assert "psm up: error: arm exited during start-up (exit code 2)" in log, log
    assert "psm arm: error:" in log and "robot.urdf" in log  # the tail of the arm's log
    assert not any(_alive(pid) for pid in _child_pids(log).values()), log


def test_sigkill_of_the_supervisor_leaves_no_orphan(tmp_path: Path) -> None:
    with _running(_stack(tmp_path), "--no-live", tmp_path=tmp_path) as up:
        assert _wait_for(lambda: len(_child_pids(up.log_text())) == 3, 90), up.log_text()
        pids = _child_pids(up.log_text())
        assert all(_alive(p) for p in pids.values())
        os.kill(up.pid, signal.SIGKILL)
        up.wait(10)
        assert _wait_for(lambda: not any(_alive(p) for p in pids.values()), 30), {
            n: _alive(p) for n, p in pids.items()
        }


def test_sigterm_stops_in_reverse_order(tmp_path: Path) -> None:
    with _running(_stack(tmp_path), "--no-live", tmp_path=tmp_path) as up:
        assert _wait_for(lambda: len(_child_pids(up.log_text())) == 3, 90), up.log_text()
        time.sleep(1.0)
        up.signal(signal.SIGTERM)
        rc = up.wait(60)
    log = up.log_text()
    assert rc == 0, log
    assert "signal SIGTERM" in log
    # the recorder stopped after the arm: its file holds the arm's last state
    assert (tmp_path / "run.mcap").stat().st_size > 0


def test_a_bad_stack_file_is_one_error_line(tmp_path: Path) -> None:
    path = _stack(tmp_path, arm="lockstep_timeout_s = -1")
    r = subprocess.run(psm_argv(["up", str(path)]), capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "psm up: error: arm.lockstep_timeout_s: Input should be greater than 0 (got -1) (process 'arm')"
    ], r.stderr
    assert sys.executable  # the command ran with this interpreter


def _wait_pid(up: ManagedProcess, name: str, not_pid: int, timeout_s: float) -> int:
    """The PID of the latest start of ``name`` once it differs from ``not_pid`` (0: none)."""
    _wait_for(lambda: _child_pids(up.log_text()).get(name, not_pid) != not_pid, timeout_s)
    return _child_pids(up.log_text()).get(name, 0)


def test_a_process_with_a_restart_policy_is_restarted_up_to_max_restarts(tmp_path: Path) -> None:
    stack = _stack(tmp_path, procs={"arm": 'restart = "on-failure"\nmax_restarts = 1'})
    with _running(stack, "--no-live", tmp_path=tmp_path) as up:
        first = _wait_pid(up, "arm", 0, 90)
        assert first, up.log_text()
        os.kill(first, signal.SIGKILL)
        second = _wait_pid(up, "arm", first, 60)
        assert second and second != first and _alive(second), up.log_text()
        assert up.alive()
        os.kill(second, signal.SIGKILL)  # the second failure: max_restarts = 1 is used up
        rc = up.wait(60)
    log = up.log_text()
    assert rc == 1, log
    assert "arm exited with code -9; restarting it (1/1)" in log, log
    assert "psm up: error: arm died again after 1 restarts (max_restarts)" in log, log
    # the restarted arm's output follows the first one's in the same log
    assert (tmp_path / "run" / "arm.log").read_text().count("arm running") == 2
    assert not any(_alive(pid) for pid in (first, second))


def test_a_process_that_is_not_required_may_exit_and_the_stack_goes_on(tmp_path: Path) -> None:
    stack = _stack(tmp_path, procs={"recorder": "required = false"})
    with _running(stack, "--no-live", tmp_path=tmp_path) as up:
        assert _wait_for(lambda: len(_child_pids(up.log_text())) == 3, 90), up.log_text()
        os.kill(_child_pids(up.log_text())["recorder"], signal.SIGKILL)
        assert _wait_for(lambda: "it is not required, the stack goes on" in up.log_text(), 20)
        time.sleep(1.0)
        assert up.alive(), up.log_text()
        up.signal(signal.SIGTERM)
        rc = up.wait(60)
    log = up.log_text()
    assert rc == 1 and "psm up: error: recorder exited with -9" in log, log
    assert "signal SIGTERM" in log  # stopped by the signal, not by the recorder's exit


def test_a_process_that_ends_the_stack_cannot_restart_always(tmp_path: Path) -> None:
    path = _stack(tmp_path, procs={"arm": 'ends_stack = true\nrestart = "always"'})
    r = subprocess.run(psm_argv(["up", str(path)]), capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 2
    assert "restart: a process with ends_stack = true cannot restart 'always'" in r.stderr, r.stderr


def _allowed_cpus(pid: int) -> set[str]:
    """``Cpus_allowed_list`` of every thread of ``pid``."""
    out = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/status") as fh:
            out |= {line.split(":", 1)[1].strip() for line in fh if line.startswith("Cpus_allowed_list")}
    return out


def test_a_process_with_a_cpu_affinity_runs_every_thread_on_those_cpus(tmp_path: Path) -> None:
    cpu = max(os.sched_getaffinity(0))
    stack = _stack(tmp_path, procs={"arm": f"cpu_affinity = [{cpu}]"})
    with _running(stack, "--duration", "6", "--clock", "lockstep", "--no-live", tmp_path=tmp_path) as up:
        assert _wait_for(lambda: "arm" in _child_pids(up.log_text()), 60), up.log_text()
        pids = _child_pids(up.log_text())
        time.sleep(2.0)  # the arm's session is open: Zenoh's threads exist
        assert len(os.listdir(f"/proc/{pids['arm']}/task")) > 3
        assert _allowed_cpus(pids["arm"]) == {str(cpu)}
        if len(os.sched_getaffinity(0)) > 1:  # the others keep every CPU
            assert _allowed_cpus(pids["router"]) != {str(cpu)}
        rc = up.wait(120)
    assert rc == 0, up.log_text()


def test_a_cpu_the_machine_does_not_have_is_one_error_line_before_anything_starts(tmp_path: Path) -> None:
    rc, log = _run(_stack(tmp_path, procs={"recorder": "cpu_affinity = [4095]"}), "--no-live",
                   tmp_path=tmp_path, timeout_s=60)
    assert rc == 1, log
    assert "psm up: error: stack.processes[1].cpu_affinity: CPU 4095 is not available here" in log, log
    assert not _child_pids(log), log


def test_wait_alive_names_a_process_that_exits_or_never_declares_its_token(tmp_path: Path) -> None:
    import io

    from services.stack import load_stack
    from services.supervisor import StackFailureError, Supervisor

    port = free_port()
    stack = tmp_path / "router.toml"
    stack.write_text(_header(port, tmp_path) + f"""[[stack.processes]]
name = "router"
command = ["serve", "router"]
[router]
listen = ["tcp/127.0.0.1:{port}"]
""")
    sup = Supervisor(load_stack(stack), out=io.StringIO(), live=False)
    quitter = sleeper = None
    try:
        sup.start()  # the router, within the stack's start-up timeout (~2 s of imports on a slow host)
        sup.cfg.stack.startup_timeout_s = 1.5  # the bound of the waits below
        quitter = ManagedProcess("quitter", [sys.executable, "-c", "print('no token'); raise SystemExit(3)"],
                                 tmp_path / "quitter.log")
        with pytest.raises(StackFailureError, match=r"quitter exited during start-up[^\n]*\n.*no token"):
            sup.wait_alive("quitter", quitter)
        sleeper = ManagedProcess("sleeper", [sys.executable, "-c", "import time; time.sleep(30)"],
                                 tmp_path / "sleeper.log")
        t0 = time.monotonic()
        with pytest.raises(StackFailureError, match="sleeper did not declare its liveliness token 'nap'"):
            sup.wait_alive("nap", sleeper)
        assert time.monotonic() - t0 < 5.0
    finally:
        for p in (quitter, sleeper):
            if p is not None:
                p.stop(5)
        sup.shutdown()


def test_the_task_summary_is_never_cut_short_on_a_narrow_output() -> None:
    """``psm up``'s closing tables on an 80-column pipe (a CI log): every step name and every
    figure printed whole, not ``back_to_…``."""
    import io

    from services.supervisor import summary_console, task_table

    steps = [
        {"step": name, "outcome": "reached", "duration_s": 2.875, "position_error_m": 0.0038,
         "velocity_error_mps": 0.0296, "peak_speed_mps": 0.2764, "peak_speed_ratio": 0.99,
         "peak_accel_mps2": 2.34, "max_orientation_error_deg": error}
        for name, error in (("grasp_spoon", 0.00436), ("back_to_neutral", 0.0), ("reach_person", 12.34))
    ]
    task = {"task": "feeding", "state": "done", "detail": "", "success": True, "steps_succeeded": 3,
            "steps_total": 3, "duration_s": 17.03, "steps": steps,
            "planner": {"latency_us": {"p50": 190.0, "p99": 615.0, "max": 3069.0, "n": 8778}}}
    out = io.StringIO()
    table = task_table(task)
    summary_console(out, [table]).print(table)
    text = out.getvalue()
    for cell in ("back_to_neutral", "grasp_spoon", "reach_person", "2.88", "3.8", "29.6", "0.276",
                 "vel err mm/s", "orient err °", "p99 615 µs", "0.0044", "12.3"):
        assert cell in text, text
    assert "…" not in text, text


def test_the_arm_line_says_where_the_missed_ticks_lost_their_time() -> None:
    from services.supervisor import arm_line

    arm = {"clock": "realtime", "ticks": 10_000, "ticks_per_s": 500.0, "missed_ticks": 4,
           "missed_by": {"wake": 2, "lock": 0, "step": 1, "skipped": 1}, "late_commands": 7,
           "jitter": {"p99_us": 180.0}, "state_to_command_latency": {"p50_us": 210.0, "p99_us": 640.0}}
    line = arm_line(arm)
    assert ("missed 4 (asleep past the deadline / waiting for the step lock / stepping and "
            "publishing: 2 / 0 / 1; 1 skipped), late commands 7, publication jitter p99 180 µs") in line
    # No miss: nothing to attribute; a statistics file without the causes: the count alone.
    assert "missed 0, late commands" in arm_line({**arm, "missed_ticks": 0})
    assert "missed 4, late commands" in arm_line({k: v for k, v in arm.items() if k != "missed_by"})
    assert "lockstep timeouts 0" in arm_line({"clock": "lockstep", "ticks": 5, "lockstep_timeouts": 0})
