"""The supervisor: starts the processes of a stack, watches them, stops them (``psm up``).

:class:`ManagedProcess` is one ``psm <command...>`` child: its own process group, output to a
log file, stopped by its PID (SIGTERM, then SIGKILL of the group after a bounded wait), and
bound to the supervisor's life: the child asks the kernel for SIGTERM when its parent dies
(``PR_SET_PDEATHSIG``, set by the ``psm`` entry point when ``PSM_SUPERVISOR_PID`` is in its
environment), so no process of a stack outlives a supervisor that was killed with SIGKILL.
Tests and benchmarks start their processes with the same class.

:class:`Supervisor` runs a :class:`~services.stack.Stack`: it starts each process once those it
``needs`` have declared their liveliness tokens (several at once where the needs allow, as docker
compose does; ``startup_timeout_s`` each), shows a live status table while
they run (state, message rates, CPU %, rejected counts, last error), and on SIGINT / SIGTERM /
the end of ``duration`` stops them in reverse order and prints a summary. A process that fails
to start is reported with the tail of its log and the whole stack shuts down; one that dies
later is restarted when its ``restart`` policy says so (``on-failure``, ``always``: up to
``max_restarts`` times), left out when it is not ``required``, and otherwise stops the stack
the same way.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

from services.arm.stats import MISS_CAUSES_HEAD, miss_causes_text
from services.stack import ProcessSpec, Stack, routed_client_env

__all__ = [
    "SUPERVISOR_PID_ENV",
    "ManagedProcess",
    "StackFailureError",
    "Supervisor",
    "bind_to_supervisor",
    "cpu_seconds",
    "free_port",
    "psm_argv",
]

#: Set in every child's environment: the supervisor's PID (the child dies with it).
SUPERVISOR_PID_ENV = "PSM_SUPERVISOR_PID"
_PR_SET_PDEATHSIG = 1
_CLK_TCK = os.sysconf("SC_CLK_TCK")


def start_after(processes: Sequence[ProcessSpec]) -> list[tuple[ProcessSpec, frozenset[str]]]:
    """Each process (in the stack's order) with the names of the processes that must be alive
    before it starts: those it ``needs`` that the stack runs, or, when it lists none, every
    process before it."""
    names = {p.name for p in processes}
    out: list[tuple[ProcessSpec, frozenset[str]]] = []
    before: list[str] = []
    for p in processes:
        out.append((p, frozenset(n for n in p.needs if n in names) if p.needs else frozenset(before)))
        before.append(p.name)
    return out


def bind_to_supervisor() -> None:
    """In a child of a supervisor (``PSM_SUPERVISOR_PID`` set): ask for SIGTERM when the
    parent dies, and exit at once if it already has. A no-op elsewhere."""
    # Taken out of the environment: only the supervisor's own children bind to it, never a
    # process this one starts.
    expected = os.environ.pop(SUPERVISOR_PID_ENV, None)
    if not expected or not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if str(os.getppid()) != expected:  # the supervisor died before prctl took effect
        sys.stderr.write(f"supervisor (pid {expected}) is gone; exiting\n")
        os._exit(1)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(port: int, timeout_s: float, proc: ManagedProcess) -> None:
    """Wait until something accepts TCP connections on 127.0.0.1:``port`` (``proc`` listening),
    at most ``timeout_s``; raises RuntimeError with the tail of ``proc``'s log if it does not."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
            return
        if not proc.alive():
            break
        time.sleep(0.05)
    raise RuntimeError(f"{proc.name} does not listen on port {port}: {proc.log_tail()}")


def psm_argv(command: Sequence[str]) -> list[str]:
    """The argv that runs ``psm <command...>`` with this interpreter."""
    return [sys.executable, "-m", "services.cli", *command]


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process [s] (``None`` once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK


def set_affinity(pid: int, cpus: Sequence[int]) -> None:
    """Restrict every thread of process ``pid`` to ``cpus`` (threads it starts later inherit the
    mask of the thread that starts them). Called right after the exec, while the interpreter is
    still starting (single-threaded), so that Zenoh's and the libraries' threads inherit it.
    Raises :class:`OSError` when a CPU does not exist or is not allowed here."""
    allowed = set(cpus)
    try:
        tasks = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tasks = [pid]
    for tid in tasks:
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(tid, allowed)


class ManagedProcess:
    """One child process: own process group, output in ``log_path`` (``append``: after what
    is there), stopped by PID."""

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        log_path: Path,
        *,
        env: Mapping[str, str] | None = None,
        cwd: str | Path | None = None,
        stderr_path: Path | None = None,
        append: bool = False,
        cpu_affinity: Sequence[int] = (),
    ) -> None:
        self.name = name
        self.argv = list(argv)
        self.log_path = Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        full_env = dict(os.environ if env is None else env)
        full_env[SUPERVISOR_PID_ENV] = str(os.getpid())
        full_env.setdefault("PYTHONUNBUFFERED", "1")
        full_env.setdefault("PYTHONFAULTHANDLER", "1")  # SIGABRT dumps every thread's stack
        full_env.setdefault("RUST_LOG", "error")
        root = str(Path(__file__).resolve().parents[1])
        full_env["PYTHONPATH"] = root + os.pathsep + full_env.get("PYTHONPATH", "")
        mode = "ab" if append else "wb"  # append: a restarted process keeps its earlier output
        self._log = self.log_path.open(mode)
        self.stderr_path = stderr_path
        self._err = stderr_path.open(mode) if stderr_path is not None else None
        self.started = time.monotonic()
        self.ended: float | None = None
        self.popen = subprocess.Popen(
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=self._err if self._err is not None else subprocess.STDOUT,
            env=full_env,
            cwd=cwd or root,
            start_new_session=True,
        )
        self.pid = self.popen.pid
        if cpu_affinity:
            try:
                set_affinity(self.pid, cpu_affinity)
            except OSError:
                self.stop(1.0)
                raise

    def alive(self) -> bool:
        """True while the process runs."""
        return self.popen.poll() is None

    def poll(self) -> int | None:
        """The exit code, or ``None`` while running (as ``subprocess.Popen.poll``)."""
        rc = self.popen.poll()
        if rc is not None:
            self._mark_ended()
        return rc

    def send_signal(self, sig: int) -> None:
        """Send ``sig`` to the process (as ``subprocess.Popen.send_signal``)."""
        self.signal(sig)

    def kill(self) -> None:
        """SIGKILL the process."""
        self.signal(signal.SIGKILL)

    @property
    def returncode(self) -> int | None:
        """The exit code (``-N``: killed by signal N), ``None`` while running."""
        return self.popen.poll()

    def uptime_s(self) -> float:
        """Seconds since start (until exit once it has ended)."""
        end = self.ended if self.ended is not None else time.monotonic()
        return end - self.started

    def log_text(self) -> str:
        """The process's output so far."""
        if not self._log.closed:
            self._log.flush()
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def stderr_text(self) -> str:
        """What the process wrote to stderr (with ``stderr_path``; else its whole output)."""
        if self._err is None or self.stderr_path is None:
            return self.log_text()
        if not self._err.closed:
            self._err.flush()
        try:
            return self.stderr_path.read_text(errors="replace")
        except OSError:
            return ""

    def log_tail(self, lines: int = 12) -> str:
        """The last ``lines`` lines of the output."""
        return "\n".join(self.log_text().rstrip().splitlines()[-lines:])

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the process (by PID) if it runs."""
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def wait(self, timeout_s: float) -> int | None:
        """Wait up to ``timeout_s`` for the exit; returns the exit code or ``None``."""
        try:
            rc = self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None
        self._mark_ended()
        return rc

    def _mark_ended(self) -> None:
        if self.ended is None:
            self.ended = time.monotonic()

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait up to ``timeout_s``; a process still running then gets SIGABRT (its
        log gets the stack of every thread) and, 3 s later, SIGKILL of its process group.
        Always reaps; returns the exit code."""
        try:
            self.signal(signal.SIGTERM)
            rc = self.wait(timeout_s)
            if rc is None:
                self.signal(signal.SIGABRT)
                rc = self.wait(3.0)
            if rc is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.pid, signal.SIGKILL)
                rc = self.popen.wait(timeout=10)
            self._mark_ended()
            # Anything the child left in its group (it starts none) goes with it.
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.pid, signal.SIGKILL)
            return int(rc)
        finally:
            self._log.close()
            if self._err is not None:
                self._err.close()


class StackFailureError(RuntimeError):
    """A process of the stack failed to start or died; the message has its log's tail."""


@dataclass
class _Row:
    """What the table shows of one process."""

    name: str
    service: str
    proc: ManagedProcess
    status: Any = None  #: the latest ServiceStatus
    rate_base: tuple[float, int, int] | None = None  #: (time, received, published)
    rates: tuple[float, float] = (0.0, 0.0)  #: (received/s, published/s)
    cpu_base: tuple[float, float] | None = None  #: (wall time, cpu seconds)
    cpu_pct: float = 0.0
    ends_stack: bool = False  #: its clean exit ends the run
    spec: ProcessSpec | None = None  #: what the stack file says of it (restart policy, required)
    restarts: int = 0  #: times it was restarted in this run
    gone: bool = False  #: exited, not required and not restarted: no longer watched


@dataclass
class Summary:
    """The end of a stack run: per process, the recording, and — when the stack ran a task —
    the task's figures (the planner's last completion event) and the arm's loop statistics."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    recording: str = ""
    reason: str = ""
    ok: bool = True
    task: dict[str, Any] | None = None
    arm: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (``<run_dir>/summary.json``)."""
        return {"reason": self.reason, "ok": self.ok, "recording": self.recording,
                "processes": self.rows, "task": self.task, "arm": self.arm}


class Supervisor:
    """Runs a :class:`~services.stack.Stack` (see the module docstring)."""

    def __init__(
        self,
        stack: Stack,
        *,
        env_overrides: Mapping[str, str] | None = None,
        out: TextIO | None = None,
        live: bool | None = None,
    ) -> None:
        self.stack = stack
        self.cfg = stack.config
        self.run_dir = Path(self.cfg.stack.run_dir)
        self.env = {**os.environ, **(env_overrides or {})}
        self.out = out or sys.stdout
        self.live = self.out.isatty() if live is None else live
        self.rows: list[_Row] = []
        self.session: Any = None
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self.stop_event = threading.Event()
        self._stop_reason = ""
        self.planner_status: Any = None  #: the latest PlannerStatus, if a planner runs
        self.task_summary: dict[str, Any] | None = None  #: from the task's completion event
        #: With ``[stack] access_control``: the credentials' directory (``<run_dir>/secrets``).
        self.secrets_dir: Path | None = None

    # ------------------------------------------------------------------ start
    def _say(self, text: str) -> None:
        print(text, file=self.out, flush=True)

    def _open_session(self) -> None:
        from services.bus.messages import Keys, PlannerStatus, ServiceStatus, TaskEvent, decode
        from services.bus.runtime import open_session

        self.session = open_session(self._session_zenoh())
        keys = Keys(self.cfg.prefix)
        base = keys.liveliness_all.key[:-1]

        def on_token(sample: Any) -> None:
            import zenoh

            name = str(sample.key_expr)[len(base):]
            with self._lock:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._alive.add(name)
                else:
                    self._alive.discard(name)

        def on_status(sample: Any) -> None:
            try:
                msg = decode(sample.payload.to_bytes(), str(sample.encoding), ServiceStatus)
            except ValueError:
                return
            now = time.monotonic()
            with self._lock:
                for row in self.rows:
                    if row.service == msg.service:
                        row.status = msg
                        counts = (now, int(msg.received), int(msg.published))
                        if row.rate_base is not None and now - row.rate_base[0] >= 0.5:
                            dt = now - row.rate_base[0]
                            row.rates = ((counts[1] - row.rate_base[1]) / dt,
                                         (counts[2] - row.rate_base[2]) / dt)
                            row.rate_base = counts
                        elif row.rate_base is None:
                            row.rate_base = counts

        def on_planner(sample: Any) -> None:
            with contextlib.suppress(ValueError):
                msg = decode(sample.payload.to_bytes(), str(sample.encoding), PlannerStatus)
                with self._lock:
                    self.planner_status = msg

        def on_event(sample: Any) -> None:
            with contextlib.suppress(ValueError):
                msg = decode(sample.payload.to_bytes(), str(sample.encoding), TaskEvent)
                if msg.kind in (TaskEvent.COMPLETED, TaskEvent.ABORTED) and msg.summary_json:
                    summary = json.loads(msg.summary_json)
                    if isinstance(summary, dict):  # anything else is not a task's summary
                        with self._lock:
                            self.task_summary = summary

        self._token_sub = self.session.liveliness().declare_subscriber(
            keys.liveliness_all.key, on_token, history=True
        )
        self._status_sub = self.session.declare_subscriber(keys.status_all.key, on_status)
        self._planner_sub = self.session.declare_subscriber(keys.planner_status.key, on_planner)
        self._event_sub = self.session.declare_subscriber(keys.task_events.key, on_event)

    def _router_endpoint(self, name: str) -> tuple[str, int] | None:
        cfg = self.stack.configs[name]
        router = getattr(cfg, "router", None)
        if router is None:
            return None
        proto, _, rest = router.listen[0].partition("/")
        host, _, port = rest.rpartition(":")
        if proto != "tcp" or not port.isdigit():
            return None
        host = "127.0.0.1" if host in ("0.0.0.0", "[::]", "") else host.strip("[]")
        return host, int(port)

    def _until_alive(self, service: str, poll: Callable[[], bool]) -> Literal["alive", "ended", "timeout"]:
        """Wait for ``service``'s liveliness token, at most the stack's ``startup_timeout_s``.
        ``poll`` runs every 20 ms while it has not come: it raises :class:`StackFailureError` to
        give up (a process that died, a stop) and returns True when the wait is moot (the stack
        has ended)."""
        deadline = time.monotonic() + self.cfg.stack.startup_timeout_s
        while time.monotonic() < deadline:
            if poll():
                return "ended"
            if self.session is not None:
                with self._lock:
                    if service in self._alive:
                        return "alive"
            time.sleep(0.02)
        return "timeout"

    def _wait_ready(self, row: _Row) -> bool:
        """Wait until ``row``'s process (a restarted one) is alive, watching the others; False
        when the stack ended meanwhile (:meth:`_poll_start`)."""
        outcome = self._until_alive(row.service, self._poll_start)
        if outcome == "timeout":
            raise StackFailureError(self._never_alive(row))
        return outcome == "alive"

    def _never_alive(self, row: _Row) -> str:
        timeout = self.cfg.stack.startup_timeout_s
        return self._died(row, f"did not declare its liveliness token '{row.service}' within {timeout:g} s")

    def wait_alive(self, service: str, proc: ManagedProcess) -> None:
        """Wait until ``service`` has declared its liveliness token on the stack's prefix, for a
        process started outside the stack file (a benchmark's own); the stack's
        ``startup_timeout_s`` bounds the wait. Raises :class:`StackFailureError` with the tail of
        ``proc``'s log if it exits first or the time runs out."""

        def poll() -> bool:
            if not proc.alive():
                raise StackFailureError(f"{proc.name} exited during start-up; last lines of "
                                        f"{proc.log_path}:\n{proc.log_tail()}")
            return False

        if self._until_alive(service, poll) != "alive":
            timeout = self.cfg.stack.startup_timeout_s
            raise StackFailureError(f"{proc.name} did not declare its liveliness token '{service}' "
                                    f"within {timeout:g} s; last lines of {proc.log_path}:\n"
                                    f"{proc.log_tail()}")

    def _died(self, row: _Row, what: str) -> str:
        rc = row.proc.returncode
        code = "" if rc is None else f" (exit code {rc})"
        tail = row.proc.log_tail()
        return f"{row.name} {what}{code}; last lines of {row.proc.log_path}:\n{tail}"

    def _session_zenoh(self) -> Any:
        """The zenoh settings of the supervisor's own session: the stack's, as the
        ``operator`` role under access control."""
        zenoh = self.cfg.zenoh
        if self.secrets_dir is None:
            return zenoh
        from services.bus.credentials import password_file

        return zenoh.model_copy(update={
            "user": "operator", "password_file": str(password_file(self.secrets_dir, "operator")),
        })

    def _env_of(self, spec: ProcessSpec) -> dict[str, str]:
        """The environment of a process: the stack's, plus under access control the router's
        users file and access control, or the process's role credentials (its name) and the
        client settings every message through the router needs (:data:`services.stack.ROUTED_CLIENT`)."""
        env = dict(self.env)
        if self.secrets_dir is None:
            return env
        from services.bus.config import env_var_name
        from services.bus.credentials import USERS_FILE, password_file

        if spec.is_router:
            env[env_var_name("router.access_control")] = "true"
            env[env_var_name("router.users_file")] = str(self.secrets_dir / USERS_FILE)
        else:
            env.update(routed_client_env())
            env[env_var_name("zenoh.user")] = spec.name
            env[env_var_name("zenoh.password_file")] = str(password_file(self.secrets_dir, spec.name))
        return env

    def start(self) -> None:
        """Start the processes, each once the processes it ``needs`` are alive (one that lists
        none: once every process before it is), several at once where their needs allow, as
        docker compose starts them; fails with the first one that dies or does not declare its
        liveliness token within ``startup_timeout_s`` of its start. Returns early, the stack
        stopping, when a process that ends the stack has already finished cleanly."""
        here = os.sched_getaffinity(0)  # the CPUs a process's cpu_affinity may name
        for i, spec in enumerate(self.cfg.stack.processes):
            missing = sorted(set(spec.cpu_affinity) - here) if spec.enabled else []
            if missing:
                raise StackFailureError(
                    f"stack.processes[{i}].cpu_affinity: CPU {', '.join(map(str, missing))} is not "
                    f"available here (this process may use {', '.join(map(str, sorted(here)))})"
                )
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if self.cfg.stack.access_control:
            from services.bus.credentials import write_secrets

            self.secrets_dir = write_secrets(self.run_dir / "secrets").out_dir.resolve()
            self._say(f"access control on: the processes' credentials are in {self.secrets_dir}")
        if not any(self._router_endpoint(p.name) for p in self.stack.processes):
            self._open_session()
        waiting = start_after(self.stack.processes)
        starting: dict[str, tuple[_Row, float]] = {}  # by name: spawned, not alive yet
        ready: set[str] = set()
        while waiting or starting:
            due = [spec for spec, after in waiting if after <= ready]
            waiting = [(spec, after) for spec, after in waiting if not after <= ready]
            if not due and not starting:  # (the stack's check() rules this out: needs come first)
                raise StackFailureError(f"{waiting[0][0].name} needs a process that cannot start")
            for spec in due:
                self._check_port_free(spec)
                proc = self._spawn(spec)
                row = _Row(spec.name, spec.service_name, proc, ends_stack=spec.ends_stack, spec=spec)
                with self._lock:
                    self.rows.append(row)
                starting[spec.name] = (row, time.monotonic())
            if self._poll_start():
                return  # the stack has ended (run() sees the stop)
            with self._lock:
                alive = [name for name, (row, _) in starting.items() if row.service in self._alive]
            for name in alive:
                row = starting.pop(name)[0]
                ready.add(name)
                if not self.live:
                    self._say(f"started {row.name} (pid {row.proc.pid})")
            timeout = self.cfg.stack.startup_timeout_s
            for row, t0 in starting.values():
                if time.monotonic() - t0 > timeout:
                    raise StackFailureError(self._never_alive(row))
            if starting and not alive:
                time.sleep(0.02)

    def _router_accepts(self, name: str) -> tuple[str, int] | None:
        """The endpoint of the router process ``name`` if something accepts connections on it."""
        endpoint = self._router_endpoint(name)
        if endpoint is None:
            return None
        with socket.socket() as s:
            s.settimeout(0.2)
            return endpoint if s.connect_ex(endpoint) == 0 else None

    def _check_port_free(self, spec: ProcessSpec) -> None:
        """A router's listening port must be free before it starts (another router running?)."""
        endpoint = self._router_accepts(spec.name)
        if endpoint is not None:
            raise StackFailureError(
                f"{spec.name}: tcp/{endpoint[0]}:{endpoint[1]} is already in use (another router running?)"
            )

    def _poll_start(self) -> bool:
        """One look while processes start (or one restarts): a process that exited, a stop, and
        (until it is open) the supervisor's own session once a router of the stack accepts
        connections. True when a process that ends the stack has exited with code 0: the run's
        normal end (the stack is told to stop); any other exit is a failure."""
        for other in self.rows:
            if not other.gone and not other.proc.alive():
                if self._finished(other):
                    return True
                raise StackFailureError(self._died(other, "exited during start-up"))
        if self.stop_event.is_set():
            raise StackFailureError(self._stop_reason or "stopped during start-up")
        if self.session is None and any(self._router_accepts(row.name) for row in self.rows):
            self._open_session()
        return False

    def _spawn(self, spec: ProcessSpec, *, append: bool = False) -> ManagedProcess:
        """Start ``psm <command> --config <stack file>`` of ``spec`` (its log in the run dir)."""
        argv = psm_argv([*spec.command, "--config", str(self.stack.path.resolve())])
        return ManagedProcess(spec.name, argv, self.run_dir / f"{spec.name}.log",
                              env=self._env_of(spec), append=append, cpu_affinity=spec.cpu_affinity)

    def _restart(self, row: _Row) -> None:
        """Start ``row``'s process again (its log goes on in the same file) and wait until it is
        alive, as at start-up."""
        assert row.spec is not None
        row.restarts += 1
        self._say(f"{row.name} exited with code {row.proc.returncode}; restarting it "
                  f"({row.restarts}/{row.spec.max_restarts})")
        row.proc.stop(1.0)  # reaps it and closes its log
        with self._lock:
            # The old token's loss may not have reached this session yet: the new process's
            # token is the one to wait for.
            self._alive.discard(row.service)
            row.proc = self._spawn(row.spec, append=True)
            row.status, row.rate_base, row.cpu_base = None, None, None
        if self._wait_ready(row):
            self._say(f"started {row.name} (pid {row.proc.pid})")
        # else the task ended while it restarted: the run stops as it would have

    # ------------------------------------------------------------------ run
    def _finished(self, row: _Row) -> bool:
        """Whether ``row``'s exited process ended the run normally: an ``ends_stack`` process
        that exited with code 0 (the task is done). Then the stack is told to stop."""
        if row.ends_stack and row.proc.returncode == 0:
            self.stop(f"{row.name} finished")
            return True
        return False

    def _check_children(self) -> None:
        """Act on the processes that exited: the clean end of an ``ends_stack`` process stops the
        run; one whose restart policy applies is restarted (``max_restarts`` times); one that is
        not required is left out; any other exit stops the stack (StackFailureError)."""
        for row in self.rows:
            if row.gone or row.proc.alive():
                continue
            if self._finished(row):
                return
            rc = row.proc.returncode
            policy = row.spec.restart if row.spec is not None else "no"
            if policy == "always" or (policy == "on-failure" and rc != 0):
                assert row.spec is not None
                if row.restarts >= row.spec.max_restarts:
                    raise StackFailureError(
                        self._died(row, f"died again after {row.restarts} restarts (max_restarts)"))
                self._restart(row)
                if self.stop_event.is_set():
                    return  # the stack ended while it restarted (or a stop came): nothing more to act on
                continue
            if row.spec is not None and not row.spec.required:
                row.gone = True
                self._say(f"{row.name} exited with code {rc}; it is not required, the stack goes on "
                          f"(log: {row.proc.log_path})")
                continue
            raise StackFailureError(self._died(row, "died"))

    def _update_cpu(self) -> None:
        now = time.monotonic()
        for row in self.rows:
            cpu = cpu_seconds(row.proc.pid)
            if cpu is None:
                continue
            if row.cpu_base is not None and now - row.cpu_base[0] > 0.2:
                row.cpu_pct = 100.0 * (cpu - row.cpu_base[1]) / (now - row.cpu_base[0])
            row.cpu_base = (now, cpu)

    def table(self) -> Any:
        """The live status table (a ``rich`` Table)."""
        from rich.table import Table

        from services.bus.introspect import rejected_cell
        from services.bus.messages import ServiceStatus

        c = self.cfg
        t = Table(title=f"stack {c.stack.name} · prefix {c.prefix} · clock {c.clock}",
                  caption=self.task_line())
        numeric = ("pid", "in/s", "out/s", "CPU %", "rejected", "errors")
        for col in ("service", "pid", *numeric[1:], "state", "last error"):
            t.add_column(col, justify="right" if col in numeric else "left")
        with self._lock:
            for row in self.rows:
                st = row.status
                state = ServiceStatus.State.Name(st.state) if st is not None else "STARTING"
                if not row.proc.alive():
                    state = f"EXITED {row.proc.returncode}"
                t.add_row(
                    row.name, str(row.proc.pid),
                    f"{row.rates[0]:.0f}", f"{row.rates[1]:.0f}", f"{row.cpu_pct:.0f}",
                    rejected_cell(st) if st else "-", str(st.errors) if st else "-",
                    state, (st.last_error[:60] if st else ""),
                )
        return t

    def task_line(self) -> str:
        """One line on the task's progress (from the planner's status), ``""`` without one."""
        from services.bus.messages import PlannerStatus

        with self._lock:
            ps = self.planner_status
        if ps is None:
            return ""
        state = PlannerStatus.State.Name(ps.state)
        line = (f"task {ps.task} · step {ps.step_index + 1}/{ps.step_count} {ps.step} · {state}"
                f" · {ps.distance_to_goal_m:.3f} m to {ps.goal_name or 'goal'} · {ps.speed_mps:.2f} m/s")
        if ps.detail:
            line += f" · {ps.detail}"
        return line

    def run(self, duration_s: float | None = None) -> None:
        """Watch the stack until ``duration_s`` (``None``: until a signal or :meth:`stop`)."""
        deadline = None if duration_s is None else time.monotonic() + duration_s

        def remaining() -> float:
            return 0.5 if deadline is None else max(0.0, min(0.5, deadline - time.monotonic()))

        if self.live:
            from rich.console import Console
            from rich.live import Live

            with Live(self.table(), console=Console(file=self.out), refresh_per_second=2) as live:
                while not self.stop_event.wait(remaining()):
                    self._update_cpu()
                    self._check_children()
                    live.update(self.table())
                    if deadline is not None and time.monotonic() >= deadline:
                        break
        else:
            while not self.stop_event.wait(remaining()):
                self._update_cpu()
                self._check_children()
                if deadline is not None and time.monotonic() >= deadline:
                    break

    def stop(self, reason: str = "") -> None:
        """Ask :meth:`run` to return (thread- and signal-safe)."""
        self._stop_reason = self._stop_reason or reason
        self.stop_event.set()

    # ------------------------------------------------------------------ stop
    def shutdown(self) -> Summary:
        """Stop the processes in reverse order; returns the summary."""
        summary = Summary()
        timeout = self.cfg.stack.stop_timeout_s
        codes: dict[str, int] = {}
        for row in reversed(self.rows):
            codes[row.name] = row.proc.stop(timeout)
        for row in self.rows:
            st = row.status
            summary.rows.append({
                "service": row.name,
                "pid": row.proc.pid,
                "uptime_s": round(row.proc.uptime_s(), 2),
                "received": int(st.received) if st else None,
                "published": int(st.published) if st else None,
                "rejected": int(st.rejected) if st else None,
                "rejected_by_reason": dict(st.rejected_by_reason) if st else {},
                "errors": int(st.errors) if st else None,
                "exit_code": codes[row.name],
                "restarts": row.restarts,
                "log": str(row.proc.log_path),
            })
        for spec in self.stack.processes:
            rec = getattr(self.stack.configs[spec.name], "recorder", None)
            if tuple(spec.command[:1]) == ("record",) and rec is not None and spec.name in codes:
                summary.recording = rec.output
        for name, cfg in self.stack.configs.items():
            planner = getattr(cfg, "planner", None)
            arm = getattr(cfg, "arm", None)
            if planner is not None and planner.summary_file and name in codes:
                summary.task = _read_json(planner.summary_file) or summary.task
            if arm is not None and getattr(arm, "stats_file", "") and name in codes:
                summary.arm = _read_json(arm.stats_file)
        if summary.task is None:
            with self._lock:
                summary.task = self.task_summary
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        return summary

    def print_summary(self, summary: Summary) -> None:
        """Print the per-process summary (and where the recording is)."""
        from rich.table import Table

        t = Table(title=f"stack {self.cfg.stack.name}: {summary.reason or 'stopped'}")
        for col in ("service", "uptime s", "received", "published", "rejected", "errors", "exit code"):
            t.add_column(col, justify="left" if col == "service" else "right")
        for r in summary.rows:
            counts = ("-" if r[k] is None else str(r[k])
                      for k in ("received", "published", "rejected", "errors"))
            t.add_row(r["service"], f"{r['uptime_s']:.1f}", *counts, str(r["exit_code"]))
        tables = [t] + ([task_table(summary.task)] if summary.task is not None else [])
        console = summary_console(self.out, tables)
        for tb in tables:
            console.print(tb)
        if summary.arm is not None:
            console.print(arm_line(summary.arm))
        path = self.run_dir / "summary.json"
        with contextlib.suppress(OSError):
            path.write_text(json.dumps(summary.to_dict(), indent=2, default=str))
            console.print(f"summary: {path}")
        if summary.recording:
            console.print(f"recording: {summary.recording}")
        console.print(f"logs: {self.run_dir}/")


def summary_console(out: TextIO | None, tables: Sequence[Any]) -> Any:
    """A ``rich`` Console on ``out`` as wide as ``tables`` need unwrapped (a narrower one would
    cut step names and figures short), at least 100 columns and at least the terminal's width."""
    from rich.console import Console

    probe = Console(file=out)
    wide = probe.options.update_width(1000)
    width = max(100, probe.width, *(probe.measure(tb, options=wide).maximum for tb in tables))
    return Console(file=out, width=width)


def _read_json(path: str) -> dict[str, Any] | None:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _num(value: Any, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def _small(value: Any) -> str:
    """A figure that is usually far below 1 (an orientation error in degrees): two significant
    digits below 10 (0.0044, not 0.00), one decimal above."""
    if value is None:
        return "-"
    return format(value, ".1f") if abs(value) >= 10.0 else format(value, ".2g")


def task_table(task: dict[str, Any]) -> Any:
    """The per-step table of a task summary (``TaskRunner.summary``) as a ``rich`` Table."""
    from rich.table import Table

    why = f"{task.get('state')}: {task.get('detail')}"
    ok = "succeeded" if task.get("success") else f"did not succeed ({why})"
    done = f"{task.get('steps_succeeded')}/{task.get('steps_total')} steps"
    t = Table(title=f"task {task.get('task')}: {done}, {ok}, {_num(task.get('duration_s'), '.2f')} s")
    cols = ("step", "outcome", "duration s", "pos err mm", "vel err mm/s", "peak m/s", "× demo", "peak m/s²",
            "orient err °")
    for col in cols:
        t.add_column(col, justify="left" if col in ("step", "outcome") else "right")
    for s in task.get("steps", []):
        pe, ve = s.get("position_error_m"), s.get("velocity_error_mps")
        t.add_row(
            s.get("step", ""), s.get("outcome", ""), _num(s.get("duration_s"), ".2f"),
            _num(None if pe is None else 1e3 * pe, ".1f"), _num(None if ve is None else 1e3 * ve, ".1f"),
            _num(s.get("peak_speed_mps"), ".3f"), _num(s.get("peak_speed_ratio"), ".2f"),
            _num(s.get("peak_accel_mps2"), ".2f"), _small(s.get("max_orientation_error_deg")),
        )
    lat = (task.get("planner") or {}).get("latency_us")
    if lat:
        t.caption = (f"planner state→command latency p50 {lat['p50']:.0f} µs, p99 {lat['p99']:.0f} µs, "
                     f"max {lat['max']:.0f} µs over {lat['n']} states")
    return t


def arm_line(arm: dict[str, Any]) -> str:
    """One line of the arm's loop statistics (its ``stats_file``)."""
    lat = arm.get("state_to_command_latency") or {}
    jit = arm.get("jitter") or {}
    parts = [f"arm ({arm.get('clock')}): {arm.get('ticks')} ticks, {arm.get('ticks_per_s', 0):.0f}/s"]
    if arm.get("clock") == "realtime":
        missed = f"missed {arm.get('missed_ticks')}"
        by = arm.get("missed_by")
        if arm.get("missed_ticks") and by:
            missed += f" ({MISS_CAUSES_HEAD}: {miss_causes_text(by)}; {by.get('skipped', 0)} skipped)"
        parts.append(f"{missed}, late commands {arm.get('late_commands')}, "
                     f"publication jitter p99 {jit.get('p99_us', 0):.0f} µs")
    else:
        parts.append(f"lockstep timeouts {arm.get('lockstep_timeouts')}")
    if lat:
        parts.append(f"state→command at the arm p50 {lat.get('p50_us', 0):.0f} µs, "
                     f"p99 {lat.get('p99_us', 0):.0f} µs")
    return " · ".join(parts)


def run_stack(
    stack: Stack,
    *,
    duration_s: float | None = None,
    env_overrides: Mapping[str, str] | None = None,
    out: TextIO | None = None,
    live: bool | None = None,
    on_started: Callable[[Supervisor], None] | None = None,
) -> int:
    """``psm up``: start, watch, stop, summarise; returns the exit code (0 clean, 1 when a
    process failed; SIGINT/SIGTERM end the run cleanly)."""
    sup = Supervisor(stack, env_overrides=env_overrides, out=out, live=live)

    def on_signal(signum: int, _frame: Any) -> None:
        sup.stop(f"signal {signal.Signals(signum).name}")

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    failure = ""
    try:
        try:
            sup.start()
            if on_started is not None:
                on_started(sup)
            if not sup.stop_event.is_set():
                sup.run(duration_s)
        except StackFailureError as exc:
            failure = str(exc)
        finally:
            summary = sup.shutdown()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if failure:
        summary.ok = False
        summary.reason = "failed"
        print(f"psm up: error: {failure}", file=sys.stderr, flush=True)
    else:
        summary.reason = sup._stop_reason or (f"ran {duration_s:g} s" if duration_s else "stopped")
    bad = [r for r in summary.rows if r["exit_code"] not in (0, -signal.SIGTERM)]
    sup.print_summary(summary)
    if bad and not failure:
        summary.ok = False
        print("psm up: error: " + ", ".join(f"{r['service']} exited with {r['exit_code']}" for r in bad),
              file=sys.stderr)
    return 0 if summary.ok else 1

