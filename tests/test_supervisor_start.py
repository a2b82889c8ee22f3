"""``psm up``'s start order: each process starts once the processes it ``needs`` are alive,
several at once where their needs allow; a process that lists no needs waits for every process
before it. The processes are stand-ins here (no process is started): each declares its
liveliness token a set number of the supervisor's start-up polls after it was spawned."""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Any

import pytest

from services.stack import load_stack
from services.supervisor import StackFailureError, Supervisor, start_after

ROOT = Path(__file__).resolve().parents[1]


class _Stub:
    """What the supervisor asks of a spawned process during start-up."""

    def __init__(self, name: str, pid: int, log_path: Path) -> None:
        self.name, self.pid, self.log_path = name, pid, log_path
        self.returncode: int | None = None

    def alive(self) -> bool:
        return self.returncode is None

    def exit(self, code: int) -> None:
        self.returncode = code

    def log_tail(self, lines: int = 12) -> str:
        return ""

    def stop(self, timeout_s: float = 10.0) -> int:
        return 0


def _start(stack_path: Path, polls_to_alive: dict[str, int], tmp_path: Path) -> list[tuple[int, str, str]]:
    """Run :meth:`Supervisor.start` on stand-ins; the events ``(poll, "spawn"|"alive", name)``."""
    stack = load_stack(stack_path, overrides={"stack.run_dir": str(tmp_path / "run")})
    sup = Supervisor(stack, out=io.StringIO(), live=False)
    events: list[tuple[int, str, str]] = []
    spawned: dict[str, tuple[int, str]] = {}  # name -> (poll of its spawn, service name)
    clock = [0]

    def spawn(spec: Any, *, append: bool = False) -> _Stub:
        spawned[spec.name] = (clock[0], spec.service_name)
        events.append((clock[0], "spawn", spec.name))
        return _Stub(spec.name, 1000 + len(spawned), tmp_path / f"{spec.name}.log")

    def poll() -> None:
        clock[0] += 1
        for name, (t0, service) in spawned.items():
            if service not in sup._alive and clock[0] - t0 >= polls_to_alive.get(name, 1):
                sup._alive.add(service)
                events.append((clock[0], "alive", name))

    sup._spawn = spawn  # type: ignore[method-assign]
    sup._poll_start = poll  # type: ignore[method-assign]
    sup._check_port_free = lambda spec: None  # type: ignore[method-assign]
    sup.start()
    assert [r.name for r in sup.rows] == [name for _, kind, name in events if kind == "spawn"]
    return events


def _when(events: list[tuple[int, str, str]], kind: str, name: str) -> int:
    return next(t for t, k, n in events if k == kind and n == name)


def test_the_feeding_stack_starts_each_process_once_its_needs_are_alive(tmp_path: Path) -> None:
    stack_path = ROOT / "configs" / "stack.toml"
    events = _start(stack_path, {"arm": 6, "camera": 4, "goal_tracker": 2}, tmp_path)
    stack = load_stack(stack_path)
    for spec in stack.processes:
        for need in spec.needs:
            assert _when(events, "spawn", spec.name) >= _when(events, "alive", need), (spec.name, need)
    # The goal tracker needs the router and the recorder, not the arm: it starts beside the arm.
    assert _when(events, "spawn", "goal_tracker") == _when(events, "spawn", "arm")
    assert _when(events, "alive", "goal_tracker") < _when(events, "alive", "arm")
    # The camera and the obstacle monitor both need the arm: they start together once it is up.
    assert _when(events, "spawn", "camera") == _when(events, "spawn", "obstacle_monitor") == _when(
        events, "alive", "arm"
    )
    # The planner needs the obstacle monitor, not the (slower) camera.
    assert _when(events, "spawn", "planner") == _when(events, "alive", "obstacle_monitor")
    assert _when(events, "spawn", "planner") < _when(events, "alive", "camera")


def test_a_process_that_lists_no_needs_starts_after_every_process_before_it(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "stack.toml").read_text()
    stack_path = tmp_path / "stack.toml"
    stack_path.write_text(re.sub(r"^needs = .*$", "", text, flags=re.MULTILINE))
    processes = load_stack(stack_path).processes
    assert all(not spec.needs for spec in processes)
    names = [spec.name for spec in processes]
    events = _start(stack_path, {"router": 3, "arm": 4, "goal_tracker": 2}, tmp_path)
    assert [(k, n) for _, k, n in events] == [(k, n) for n in names for k in ("spawn", "alive")]


def test_a_process_that_never_comes_up_fails_the_start_and_names_itself(tmp_path: Path) -> None:
    stack_path = ROOT / "configs" / "stack.toml"
    with pytest.raises(StackFailureError, match="camera did not declare its liveliness token"):
        _start_with_timeout(stack_path, tmp_path)


def _start_with_timeout(stack_path: Path, tmp_path: Path) -> None:
    stack = load_stack(
        stack_path, overrides={"stack.run_dir": str(tmp_path / "run"), "stack.startup_timeout_s": 0.3}
    )
    sup = Supervisor(stack, out=io.StringIO(), live=False)

    def spawn(spec: Any, *, append: bool = False) -> _Stub:
        if spec.name != "camera":
            sup._alive.add(spec.service_name)
        return _Stub(spec.name, 1, tmp_path / f"{spec.name}.log")

    sup._spawn = spawn  # type: ignore[method-assign]
    sup._poll_start = lambda: None  # type: ignore[method-assign]
    sup._check_port_free = lambda spec: None  # type: ignore[method-assign]
    sup.start()


def test_a_task_that_ends_while_a_process_restarts_ends_the_run_as_it_would_have(tmp_path: Path) -> None:
    """The router dies and is restarted (``restart = "always"``); while its new process is
    coming up the planner finishes its task (exit code 0, ``ends_stack``): the run stops with
    "planner finished", not as a process that "exited during start-up"."""
    stack = load_stack(ROOT / "configs" / "stack.toml", overrides={"stack.run_dir": str(tmp_path / "run")})
    sup = Supervisor(stack, out=io.StringIO(), live=False)

    def spawn(spec: Any, *, append: bool = False) -> _Stub:
        if not append:  # a first start is alive at once; the router's restart never comes up
            sup._alive.add(spec.service_name)
        return _Stub(spec.name, 1, tmp_path / f"{spec.name}.log")

    sup._spawn = spawn  # type: ignore[method-assign]
    sup._check_port_free = lambda spec: None  # type: ignore[method-assign]
    sup._router_accepts = lambda name: None  # type: ignore[method-assign]
    sup.session = object()  # the supervisor's own session: its view of the tokens is sup._alive
    sup.start()
    rows = {r.name: r for r in sup.rows}
    rows["router"].proc.exit(-9)
    rows["planner"].proc.exit(0)
    sup._check_children()
    assert sup.stop_event.is_set() and sup._stop_reason == "planner finished"
    assert rows["router"].restarts == 1


def test_start_after_names_what_each_process_waits_for() -> None:
    stack = load_stack(ROOT / "configs" / "stack.toml")
    after = {spec.name: set(names) for spec, names in start_after(stack.processes)}
    assert after["router"] == set()
    assert after["goal_tracker"] == {"router", "recorder"}
    assert after["planner"] == {"router", "recorder", "arm", "obstacle_monitor"}
