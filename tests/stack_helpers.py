"""Helpers of the tests that run the shipped stack with ``psm up`` on loopback (the feeding, the
obstacle and the fault tests): arguments on a free port and prefix with everything written under
the test's directory, a client session on the stack's router, the PIDs the supervisor reports, a
kill mid-motion and the end-effector speeds of a recording."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.supervisor import ManagedProcess, free_port, psm_argv

ROOT = Path(__file__).resolve().parents[1]
STACK = ROOT / "configs" / "stack.toml"
STEPS = ["grasp_spoon", "back_to_neutral", "reach_bowl", "scoop", "reach_person"]


#: ``--set`` of the realtime stack tests that run a task to its end: the planner takes the
#: monitor's predictions up to 0.5 s old (the shipped 0.02 s is 10 ticks; a 2-core machine
#: loaded by other jobs delays predictions that much at times, and each time the arm brakes:
#: often enough, a step times out). Their scenes have no obstacle in the arm's way. Likewise
#: the arm's command watchdog: 0.1 s instead of 0.02 s (the arm brakes at once anyway when the
#: planner's liveliness token goes).
LOAD_TOLERANT = ("planner.prediction_max_age_s=0.5", "arm.watchdog_timeout_s=0.1")


def up_args(tmp_path: Path, clock: str, *sets: str) -> list[str]:
    """``psm up`` of the shipped stack on a free port and prefix, everything written under
    ``tmp_path``, plus ``--set`` of each of ``sets``."""
    port = free_port()
    run = tmp_path / "run"
    values = [
        f'clock="{clock}"',
        f'prefix="feed{port}"',
        f'router.listen=["tcp/127.0.0.1:{port}"]',
        f'zenoh.connect=["tcp/127.0.0.1:{port}"]',
        f'stack.run_dir="{run}"',
        f'recorder.output="{tmp_path / "run.mcap"}"',
        f'planner.summary_file="{run / "task.json"}"',
        f'planner.progress_file="{run / "progress.json"}"',
        f'arm.stats_file="{run / "arm.json"}"',
        f'planner.cache_dir="{ROOT / "out" / "models"}"',
        *sets,
    ]
    return ["up", str(STACK), "--no-live", *(a for v in values for a in ("--set", v))]


def up(tmp_path: Path, *sets: str, timeout_s: float = 240.0) -> tuple[int, str, dict[str, Any]]:
    """Run the shipped stack in lockstep to its end; returns the supervisor's exit code (-1: it
    did not end within ``timeout_s``), its log and the run's summary (``{}`` if none)."""
    run = tmp_path / "run"
    args = up_args(tmp_path, "lockstep", *sets)
    proc = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    try:
        rc = proc.wait(timeout_s)
    finally:
        proc.stop()
    log = proc.log_text()
    summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else {}
    return (-1 if rc is None else rc), log, summary


def check_task(summary: dict[str, Any], log: str) -> dict[str, Any]:
    """The summary's task succeeded with every feeding step within 1 cm; returns the task."""
    task = summary.get("task")
    assert task is not None, log
    assert task["success"], json.dumps(task, indent=1)[:3000]
    assert [s["step"] for s in task["steps"]] == STEPS
    for s in task["steps"]:
        assert s["success"] and s["position_error_m"] <= 0.01, s
    assert summary["reason"] == "planner finished", summary["reason"]
    return task


def up_port(args: list[str]) -> int:
    """The router port of ``psm up`` arguments from :func:`up_args`."""
    listen = next(a for a in args if a.startswith("router.listen="))
    return int(listen.rsplit(":", 1)[1].rstrip('"]'))


def client_session(port: int) -> Any:
    """A Zenoh client session on the router at 127.0.0.1:``port`` (multicast off), with the
    services' own settings (:func:`services.bus.runtime.zenoh_config`: it reconnects the same
    way when the router restarts)."""
    import zenoh

    from services.bus.config import ZenohConfig
    from services.bus.runtime import zenoh_config

    cfg = ZenohConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast=False)
    return zenoh.open(zenoh_config(cfg))


def started_pids(log: str) -> dict[str, int]:
    """``{process: pid}`` from the supervisor's ``started <name> (pid N)`` lines (the latest
    start of each: a restarted process has several)."""
    out: dict[str, int] = {}
    for line in log.splitlines():
        if line.startswith("started ") and "(pid " in line:
            name = line.split()[1]
            out[name] = int(line.rsplit("(pid ", 1)[1].split(")")[0])
    return out


def wait_stack_up(proc: ManagedProcess, deadline: float) -> dict[str, int]:
    """Wait until the supervisor has started its last process (the planner); returns the PIDs."""
    while time.monotonic() < deadline:
        text = proc.log_text()
        if "started planner (pid " in text:
            return started_pids(text)
        if not proc.alive():
            break
        time.sleep(0.1)
    raise AssertionError(f"the stack did not come up: {proc.log_text()[-3000:]}")


def wait_planner(port: int, deadline: float, *, min_step: int = 0, min_speed: float = 0.1) -> Any:
    """Wait until the planner reports step index ``min_step`` or later with the arm faster than
    ``min_speed`` [m/s]; returns that ``PlannerStatus`` (AssertionError at ``deadline``)."""
    from services.bus.messages import Keys, PlannerStatus

    seen: list[Any] = []
    session = client_session(port)
    try:
        sub = session.declare_subscriber(
            Keys(f"feed{port}").planner_status.key,
            lambda sample: seen.append(PlannerStatus.FromString(sample.payload.to_bytes())),
        )
        while time.monotonic() < deadline:
            if seen and seen[-1].step_index >= min_step and seen[-1].speed_mps > min_speed:
                break
            time.sleep(0.01)
        sub.undeclare()
    finally:
        session.close()
    last = seen[-1] if seen else None
    assert last is not None and last.step_index >= min_step and last.speed_mps > min_speed, last
    return last


def kill_mid_motion(
    tmp_path: Path, process: str, *sets: str, min_step: int = 0, end_timeout_s: float = 60.0
) -> tuple[int | None, str, int]:
    """``psm up`` of the shipped stack in realtime (plus ``--set`` of ``sets``); SIGKILL of
    ``process`` once the planner reports the arm moving faster than 0.1 m/s in step
    ``min_step`` or later. Waits up to ``end_timeout_s`` for the stack to end. Returns the
    supervisor's exit code (None: still running, then stopped), its log and the kill time
    (wall clock = the realtime stack's clock) [ns]."""
    args = up_args(tmp_path, "realtime", *sets)
    port = up_port(args)
    proc = ManagedProcess("up", psm_argv(args), tmp_path / "up.log", cwd=ROOT)
    try:
        deadline = time.monotonic() + 120
        pid = wait_stack_up(proc, deadline)[process]
        wait_planner(port, deadline, min_step=min_step)
        killed_ns = time.time_ns()
        os.kill(pid, signal.SIGKILL)
        rc = proc.wait(end_timeout_s)
    finally:
        proc.stop()
    return rc, proc.log_text(), killed_ns


def arm_speeds(recording: Path) -> list[tuple[int, float]]:
    """``(stamp_ns, end-effector speed [m/s])`` of every recorded arm state."""
    from services.bus.log import read_log
    from services.bus.messages import ArmState

    out = []
    for _k, msg, _t in read_log(recording):
        if isinstance(msg, ArmState):
            v = msg.ee_linear_velocity
            out.append((int(msg.stamp_ns), float(np.linalg.norm([v.x, v.y, v.z]))))
    return out


#: Where the fault tests write what they measured (``scripts/faults_table.py`` makes the table
#: of docs/faults.md from it).
FAULTS_OUT = ROOT / "out" / "faults"


def record_fault(name: str, measured: dict[str, Any]) -> Path:
    """Write one fault test's measurements to ``out/faults/<name>.json`` (with the time of the
    run); returns the path."""
    FAULTS_OUT.mkdir(parents=True, exist_ok=True)
    path = FAULTS_OUT / f"{name}.json"
    data = {"measured_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **measured}
    path.write_text(json.dumps(data, indent=1, default=float) + "\n")
    print(f"{name}: {json.dumps(measured, default=float)}")
    return path


def mount_tmpfs(path: Path, size: str) -> None:
    """Mount a tmpfs of ``size`` (e.g. ``"1m"``) on ``path``; ``pytest.skip`` if not permitted."""
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                       capture_output=True, text=True, timeout=30)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs to fill up (needs root): {r.stderr.strip()}")


def unmount(path: Path) -> None:
    """Unmount what :func:`mount_tmpfs` mounted (lazily if something still holds it)."""
    if subprocess.run(["umount", str(path)], capture_output=True, timeout=30).returncode != 0:
        subprocess.run(["umount", "-l", str(path)], capture_output=True, timeout=30)


class StackWatch:
    """A test's view of a running stack's bus: every service's latest ``ServiceStatus`` (by the
    name in its key, when the message names the same service), the planner's latest status,
    the arm's real states (its stream only: forged or fuzzed states are left out) as ``(wall
    ns, max |dq| [rad/s], EE speed [m/s])``, and the wall times of the arm commands."""

    def __init__(self, port: int, prefix: str) -> None:
        from services.bus.messages import Keys
        from services.robot.protocol import StateStream

        self.keys = Keys(prefix)
        self.session = client_session(port)
        self.status: dict[str, Any] = {}
        self.planner: Any = None
        self.states: list[tuple[int, float, float]] = []
        self.commands: list[int] = []
        self._stream = StateStream()
        self._subs = [
            self.session.declare_subscriber(self.keys.status_all.key, self._on_status),
            self.session.declare_subscriber(self.keys.arm_state.key, self._on_state),
            self.session.declare_subscriber(self.keys.planner_status.key, self._on_planner),
            self.session.declare_subscriber(self.keys.arm_command.key,
                                            lambda _s: self.commands.append(time.time_ns())),
        ]

    @staticmethod
    def _decode(sample: Any, cls: Any) -> Any:
        from services.bus.messages import decode

        try:
            return decode(sample.payload.to_bytes(), str(sample.encoding), cls)
        except ValueError:
            return None

    def _on_status(self, sample: Any) -> None:
        from services.bus.messages import ServiceStatus

        name = str(sample.key_expr).rsplit("/", 1)[1]
        msg = self._decode(sample, ServiceStatus)
        if msg is not None and msg.service == name:
            self.status[name] = msg

    def _on_planner(self, sample: Any) -> None:
        from services.bus.messages import PlannerStatus

        msg = self._decode(sample, PlannerStatus)
        if msg is not None and msg.task == "feeding" and msg.step_count == len(STEPS):
            self.planner = msg

    def _on_state(self, sample: Any) -> None:
        import math

        from services.bus.messages import ArmState

        st = self._decode(sample, ArmState)
        if st is None or not (math.isfinite(st.dt_s) and st.dt_s > 0):
            return
        if self._stream.check(int(st.tick), int(st.stamp_ns), st.dt_s)[0] not in ("", "repeat"):
            return  # not the arm's
        v = st.ee_linear_velocity
        dq = max((abs(x) for x in st.dq), default=0.0)
        self.states.append((time.time_ns(), dq, float(np.linalg.norm([v.x, v.y, v.z]))))

    def rate(self, times: list[Any], t0_ns: int, t1_ns: int) -> float:
        """Messages per second in ``times`` (wall ns, or tuples starting with it) in [t0, t1)."""
        n = sum(1 for t in times if t0_ns <= (t[0] if isinstance(t, tuple) else t) < t1_ns)
        return n / ((t1_ns - t0_ns) * 1e-9)

    def wait(self, pred: Any, timeout_s: float, what: str) -> None:
        """Poll ``pred`` until true; AssertionError naming ``what`` after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if pred():
                return
            time.sleep(0.05)
        raise AssertionError(f"{what}: {self.planner}")

    def close(self) -> None:
        """Undeclare and close the session."""
        for s in self._subs:
            s.undeclare()
        self.session.close()
