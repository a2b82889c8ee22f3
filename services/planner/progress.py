"""The planner's task progress on disk: what a restarted planner resumes from (bus-free).

A planner that is killed and started again (``psm up``'s ``restart = "on-failure"``, docker's
restart policy) must neither redo the steps it completed — a second grasp of a spoon already
in the gripper — nor jump: it resumes at the step that was running, started afresh from the
arm's measured state (the arm has braked to rest meanwhile), like any step start.

The planner writes :class:`TaskProgress` to ``[planner] progress_file`` after each step
transition (a step completed, the task completed), *after* the transition's events and
gripper command are on the bus, atomically (a temporary file in the same directory, fsync,
rename): a reader sees the previous record or the new one, never a part. At start it reads the
file back, and on the first arm state it resumes only if the record belongs to the same run of
the arm: the arm's clock origin ``stamp_ns - tick * dt`` (the UNIX time of tick 0 for a realtime
arm) is the record's, and the tick is past the record's. A record of another run — an arm that
was restarted, a lockstep stack started again (origin 0, tick 0) — is ignored and the task
starts from its first step.

Example::

    progress = read_progress(path, task)          # None when absent or of another task
    if progress is not None and progress.same_arm_run(stamp_ns, tick, dt_ns, tolerance_ns):
        runner.resume(progress.next_index, progress.completed, progress.resumes)
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.planner.task import TaskSpec

__all__ = ["PROGRESS_FORMAT", "ProgressError", "TaskProgress", "read_progress", "write_progress"]

#: Version of the record's layout: a record of another version is ignored.
PROGRESS_FORMAT = 1


class ProgressError(ValueError):
    """A progress file that cannot be used (unreadable, malformed, another task)."""


@dataclass
class TaskProgress:
    """How far a task got: ``next_index`` is the step to run next (``len(steps)``: the task is
    done); ``completed`` one record per completed step (``start_ns``, ``end_ns`` [ns, stack
    clock] and its ``summary``, :meth:`StepReport.summary`); ``resumes`` the earlier resumes
    (``at_step``, ``tick``). ``arm_origin_ns`` [ns] is the arm's clock origin (``stamp_ns - tick
    * dt_ns`` of its states), ``tick`` the arm tick of the transition, ``dt_ns`` the arm's
    period [ns]."""

    task: str
    steps: list[str]
    next_index: int
    arm_origin_ns: int
    dt_ns: int
    tick: int
    completed: list[dict[str, Any]] = field(default_factory=list)
    resumes: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """The JSON record (with the format version and the time it was written)."""
        return {
            "format": PROGRESS_FORMAT,
            "task": self.task,
            "steps": list(self.steps),
            "next_index": self.next_index,
            "arm_origin_ns": self.arm_origin_ns,
            "dt_ns": self.dt_ns,
            "tick": self.tick,
            "completed": self.completed,
            "resumes": self.resumes,
            "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }

    @classmethod
    def from_json(cls, data: Any, task: TaskSpec) -> TaskProgress:
        """Parse a record for ``task``; :class:`ProgressError` if it is not one."""
        if not isinstance(data, dict) or data.get("format") != PROGRESS_FORMAT:
            raise ProgressError(f"not a progress record of format {PROGRESS_FORMAT}")
        steps = list(task.sequence)
        if data.get("task") != task.name or data.get("steps") != steps:
            raise ProgressError(
                f"a record of task {data.get('task')!r} with steps {data.get('steps')}, "
                f"not of {task.name!r} with {steps}"
            )
        try:
            progress = cls(
                task=task.name,
                steps=steps,
                next_index=int(data["next_index"]),
                arm_origin_ns=int(data["arm_origin_ns"]),
                dt_ns=int(data["dt_ns"]),
                tick=int(data["tick"]),
                completed=list(data.get("completed", [])),
                resumes=list(data.get("resumes", [])),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ProgressError(f"malformed progress record: {exc!r}") from None
        if not 0 <= progress.next_index <= len(steps) or len(progress.completed) != progress.next_index:
            raise ProgressError(
                f"next step {progress.next_index} with {len(progress.completed)} completed of {len(steps)}"
            )
        if progress.dt_ns <= 0:
            raise ProgressError(f"arm period {progress.dt_ns} ns")
        return progress

    def same_arm_run(self, stamp_ns: int, tick: int, dt_ns: int, tolerance_ns: int) -> bool:
        """True if the arm state ``(stamp_ns, tick)`` with period ``dt_ns`` [ns] comes from the
        arm run this record was written in: same period, clock origin within ``tolerance_ns``,
        and a tick after the record's."""
        origin = stamp_ns - tick * dt_ns
        return (
            dt_ns == self.dt_ns
            and abs(origin - self.arm_origin_ns) <= tolerance_ns
            and tick > self.tick
        )


def read_progress(path: str | Path, task: TaskSpec) -> TaskProgress | None:
    """The record in ``path`` for ``task``; ``None`` if there is no file. Raises
    :class:`ProgressError` (one line) for a file that cannot be used."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise ProgressError(f"{p}: {exc.strerror}") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ProgressError(f"{p}: not JSON ({exc})") from None
    try:
        return TaskProgress.from_json(data, task)
    except ProgressError as exc:
        raise ProgressError(f"{p}: {exc}") from None


def write_progress(path: str | Path, progress: TaskProgress) -> None:
    """Write ``progress`` to ``path`` atomically: a temporary file next to it, flushed to the
    disk, then renamed over it (a crash leaves the old record or the new one)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    data = json.dumps(progress.to_json(), indent=1, default=float).encode()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, p)
