"""What the experiments share: the stack's settings for in-process runs, a lockstep run through
the stack and its recording read back, the goals a stack run's planner received as a schedule
for :func:`~services.planner.simulate.simulate_task`, and in-process runs written as MCAP.

An in-process run (:func:`run_in_process`) is the stack's control loop without the bus: the
planner's ``TaskRunner``, the arm simulation ``ArmSim`` and the obstacle monitor's logic, each
configured from ``configs/stack.toml`` as the services are (:func:`stack_settings`: the
``[arm]``, ``[planner]`` and ``[obstacle_monitor]`` tables; the robot loaded as the arm service
loads it). docs/experiments.md, "In-process harness", shows it gives the lockstep stack's
trajectory bit for bit when it is given the goals the stack's planner received
(:func:`goal_schedule`).

    settings = stack_settings()
    res = run_in_process(cfg, models, settings, obstacles=[wall])
    with TraceWriter(out / "run.mcap") as w:
        w.write_run("psm", res)
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
STACK_FILE = ROOT / "configs" / "stack.toml"
CACHE_DIR = ROOT / "out" / "models"
WALL_FILE = ROOT / "configs" / "obstacles" / "paper_wall.toml"

__all__ = [
    "STACK_FILE",
    "StackRun",
    "StackSettings",
    "TraceWriter",
    "feeding_models",
    "goal_schedule",
    "read_stack_run",
    "robot_model",
    "run_in_process",
    "run_stack",
    "stack_settings",
]


# --------------------------------------------------------------------------------------------
# The stack's settings, in process
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StackSettings:
    """The stack file's settings that shape a run: ``arm`` (``[arm]``, an
    :class:`~services.arm.config.ArmSection`), ``monitor`` (``[obstacle_monitor]`` fields other
    than the obstacles), the planner's ``prediction_max_age_s`` [s] and its
    ``joint_accel_fraction``."""

    arm: Any
    monitor: dict[str, Any]
    prediction_max_age_s: float
    joint_accel_fraction: float

    def arm_fields(self) -> dict[str, Any]:
        """The ``[arm]`` fields :func:`~services.planner.simulate.simulate_task` passes on to the
        simulator and its robot (all of them but the period and the start pose, which it takes
        itself)."""
        from services.arm.sim import ArmSimConfig
        from services.robot.description import RobotDescription

        keep = (set(ArmSimConfig.model_fields) | set(RobotDescription.model_fields)) - {"dt_s", "start_pose"}
        return {k: v for k, v in self.arm.model_dump().items() if k in keep}


def stack_settings(path: Path = STACK_FILE, overrides: Mapping[str, Any] | None = None) -> StackSettings:
    """The settings of the stack file ``path`` (environment variables ignored)."""
    from services.stack import load_stack

    st = load_stack(path, overrides=overrides, env={})
    arm = st.configs["arm"].arm  # type: ignore[attr-defined]
    mon = st.configs["obstacle_monitor"].obstacle_monitor  # type: ignore[attr-defined]
    planner = st.configs["planner"].planner  # type: ignore[attr-defined]
    skip = {"obstacles", "obstacles_file", "rt_priority"}
    monitor = {k: v for k, v in mon.model_dump().items() if k not in skip}
    return StackSettings(
        arm, monitor, float(planner.prediction_max_age_s), float(planner.joint_accel_fraction)
    )


def feeding_models(task: Any) -> Any:
    """The task's models, learned from the committed demonstrations (cached in ``out/models``,
    the cache the stack's planner uses)."""
    from services.planner.models import ModelCache, load_task_models

    return load_task_models(task, ModelCache(CACHE_DIR))


_ROBOTS: dict[str, Any] = {}


def robot_model(settings: StackSettings) -> Any:
    """The robot as the arm service loads it (one model per URDF, reused across runs)."""
    key = json.dumps([settings.arm.urdf, settings.arm.ee_frame, settings.arm.locked_joints,
                      settings.arm.accel_limits])
    if key not in _ROBOTS:
        _ROBOTS[key] = settings.arm.load_robot()
    return _ROBOTS[key]


def run_in_process(
    cfg: Any,
    models: Any,
    settings: StackSettings,
    *,
    obstacles: Sequence[Any] = (),
    goals: Any = None,
    goal_updates: Sequence[Any] = (),
    max_s: float = 120.0,
) -> Any:
    """The task ``cfg`` (a :class:`~services.tasks.feeding.FeedingConfig`) run in process as the
    stack runs it: the planner requires the obstacle monitor's predictions, the monitor (segment
    test and whole-arm clearance) holds ``obstacles`` (:class:`psm.obstacles.Obstacle`), every
    setting from ``settings``. ``goals`` / ``goal_updates``: the live goals
    (:func:`~services.planner.simulate.simulate_task`). Returns its
    :class:`~services.planner.simulate.SimulationResult`; the monitor is ``result.monitor``."""
    from services.planner.simulate import monitor_predictor, simulate_task

    fn = monitor_predictor(list(obstacles), robot_model(settings), **settings.monitor)
    res = simulate_task(
        cfg, models, goals=goals, goal_updates=goal_updates, start_pose=settings.arm.start_pose,
        dt_s=settings.arm.dt_s, max_s=max_s, arm=settings.arm_fields(), collision=fn,
        prediction_max_age_s=settings.prediction_max_age_s,
        joint_accel_fraction=settings.joint_accel_fraction,
    )
    res.monitor = fn.monitor  # type: ignore[attr-defined]
    return res


# --------------------------------------------------------------------------------------------
# A lockstep run through the stack
# --------------------------------------------------------------------------------------------


@dataclass
class StackRun:
    """A finished ``psm up`` run: exit code (-1: did not end in time), the supervisor's log,
    ``summary.json`` (``{}`` if none), the recording and the wall time [s]."""

    rc: int
    log: str
    summary: dict[str, Any]
    recording: Path
    wall_s: float


def run_stack(workdir: Path, *sets: str, timeout_s: float = 240.0, stack_file: Path = STACK_FILE) -> StackRun:
    """``psm up <stack_file> --clock lockstep --no-live`` on a free loopback port and prefix,
    everything written under ``workdir``, plus ``--set`` of each of ``sets``."""
    from services.supervisor import ManagedProcess, free_port, psm_argv

    port = free_port()
    run = workdir / "run"
    rec = workdir / "run.mcap"
    values = [
        'clock="lockstep"',
        f'prefix="exp{port}"',
        f'router.listen=["tcp/127.0.0.1:{port}"]',
        f'zenoh.connect=["tcp/127.0.0.1:{port}"]',
        f'stack.run_dir="{run}"',
        f'recorder.output="{rec}"',
        f'planner.summary_file="{run / "task.json"}"',
        f'planner.progress_file="{run / "progress.json"}"',
        f'arm.stats_file="{run / "arm.json"}"',
        f'planner.cache_dir="{CACHE_DIR}"',
        *sets,
    ]
    args = ["up", str(stack_file), "--no-live", *(a for v in values for a in ("--set", v))]
    t0 = time.monotonic()
    proc = ManagedProcess("up", psm_argv(args), workdir / "up.log", cwd=ROOT)
    try:
        rc = proc.wait(timeout_s)
    finally:
        proc.stop()
    summary_path = run / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    return StackRun(-1 if rc is None else rc, proc.log_text(), summary, rec, time.monotonic() - t0)


@dataclass
class RecordedRun:
    """A stack recording's control loop, per arm tick: ``tick (N,)``, ``t (N,)`` [s], ``x, v, a
    (N, 3)`` end effector [m, m/s, m/s²], ``quat (N, 4)``, ``q, dq (N, n)``; per answered tick
    ``cmd_tick (M,)``, ``a_cmd (M, 3)`` [m/s²], ``quat_ref (M, 4)``, ``omega_cmd (M, 3)`` [rad/s];
    the predictions ``pred_tick (P,)``, ``collision (P,)``, ``protective_stop (P,)``,
    ``min_clearance (P,)`` [m]; ``goals``: every ``goals/*`` message as ``(name, position,
    stamp_ns, valid)``; ``goal_updates``: the goal updates the planner's commands name
    (``ArmCommand.goal_updates``) as ``(tick, name, stamp_ns)``, in order; ``events``: the task
    events as ``(kind, step, state_tick)``."""

    arrays: dict[str, NDArray[Any]]
    goals: list[tuple[str, tuple[float, float, float], int, bool]] = field(default_factory=list)
    goal_updates: list[tuple[int, str, int]] = field(default_factory=list)
    events: list[tuple[str, str, int]] = field(default_factory=list)


def read_stack_run(path: Path) -> RecordedRun:
    """Read a stack recording (:func:`services.bus.log.read_log`) into a :class:`RecordedRun`.
    Arm states are the ``arm/state`` stream's, one per tick (a re-offered state once)."""
    from services.bus.log import read_log
    from services.bus.messages import ArmCommand, ArmState, CollisionPrediction, Goal, TaskEvent

    states: dict[int, Any] = {}
    cmds: dict[int, Any] = {}
    preds: dict[int, Any] = {}
    out = RecordedRun({})
    topics = [f"*/{t}" for t in ("arm/state", "arm/command", "collision", "goals/*", "task/events")]
    for key, msg, _t in read_log(path, topics):
        topic = key.split("/", 1)[1]
        if isinstance(msg, ArmState) and topic == "arm/state":
            states.setdefault(int(msg.tick), msg)
        elif isinstance(msg, ArmCommand) and topic == "arm/command":
            cmds.setdefault(int(msg.tick), msg)
        elif isinstance(msg, CollisionPrediction):
            preds.setdefault(int(msg.state_tick), msg)
        elif isinstance(msg, Goal) and topic.startswith("goals/"):
            p = msg.position
            out.goals.append((msg.name or topic.split("/", 1)[1], (p.x, p.y, p.z), int(msg.stamp_ns),
                              bool(msg.valid)))
        elif isinstance(msg, TaskEvent):
            out.events.append((TaskEvent.Kind.Name(msg.kind), msg.step, int(msg.state_tick)))

    def v3(m: Any) -> tuple[float, float, float]:
        return (m.x, m.y, m.z)

    ticks = sorted(states)
    st = [states[k] for k in ticks]
    ct = sorted(cmds)
    cm = [cmds[k] for k in ct]
    out.goal_updates = [(k, u.name, int(u.stamp_ns)) for k, m in zip(ct, cm, strict=True)
                        for u in m.goal_updates]
    pt = sorted(preds)
    pr = [preds[k] for k in pt]
    out.arrays = {
        "tick": np.array(ticks, dtype=np.int64),
        "t": np.array([m.stamp_ns for m in st], dtype=np.int64) * 1e-9,
        "x": np.array([v3(m.ee_position) for m in st]),
        "v": np.array([v3(m.ee_linear_velocity) for m in st]),
        "a": np.array([v3(m.ee_linear_acceleration) for m in st]),
        "quat": np.array([(m.ee_orientation.x, m.ee_orientation.y, m.ee_orientation.z, m.ee_orientation.w)
                          for m in st]),
        "q": np.array([list(m.q) for m in st]),
        "dq": np.array([list(m.dq) for m in st]),
        "cmd_tick": np.array(ct, dtype=np.int64),
        "a_cmd": np.array([v3(m.linear_acceleration) for m in cm]),
        "quat_ref": np.array([(m.orientation_reference.x, m.orientation_reference.y,
                               m.orientation_reference.z, m.orientation_reference.w) for m in cm]),
        "omega_cmd": np.array([v3(m.angular_velocity_reference) for m in cm]),
        "pred_tick": np.array(pt, dtype=np.int64),
        "collision": np.array([bool(m.collision) for m in pr]),
        "protective_stop": np.array([bool(m.protective_stop) for m in pr]),
        "min_clearance": np.array([float(m.min_clearance_m) for m in pr]),
    }
    return out


def goal_schedule(run: RecordedRun) -> list[Any]:
    """The live goals of a stack run as its planner took them in, for
    :func:`~services.planner.simulate.simulate_task` (``goal_updates``).

    The planner's first command after it applied a goal update names it
    (``ArmCommand.goal_updates``: name and stamp, in the order applied), so each update is offered
    before the tick of that command, with the position and validity of the recorded
    ``goals/<name>`` message of that name and stamp. An update no command names (after the last
    command, or never applied) is not offered."""
    from services.planner.simulate import GoalUpdate

    recorded: dict[tuple[str, int], list[tuple[tuple[float, float, float], bool]]] = {}
    for name, pos, stamp, valid in run.goals:
        recorded.setdefault((name, stamp), []).append((pos, valid))
    out = []
    for tick, name, stamp in run.goal_updates:
        same = recorded.get((name, stamp))
        if not same:
            raise ValueError(f"the command of tick {tick} names goal update {name} @ {stamp} ns, "
                             "which is not in the recording")
        pos, valid = same.pop(0)
        out.append(GoalUpdate(tick, name, pos, stamp, valid))
    return out


# --------------------------------------------------------------------------------------------
# In-process runs as MCAP
# --------------------------------------------------------------------------------------------


class TraceWriter:
    """In-process runs written as the stack's recorder writes a run (the project's MCAP writer,
    the bus's message types, schemas and encodings), so the recording readers, ``psm report`` and
    Foxglove open them. :meth:`write_run` writes one run under a key prefix: per tick an
    ``<prefix>/arm/state`` (``ArmState``) and the ``<prefix>/arm/command`` (``ArmCommand``) that
    answered it, ``<prefix>/planner/goal`` (``Goal``) on every change and ``<prefix>/task/events``
    (``TaskEvent``). Log and publish times are the run's sim time."""

    def __init__(self, path: Path, library: str = "psm-dataflow experiments") -> None:
        from services.bus.mcap_writer import FastMcapWriter

        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = path.open("wb")
        self._w = FastMcapWriter(self._fh)
        self._w.start(profile="", library=library)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def metadata(self, name: str, data: Mapping[str, str]) -> None:
        """An MCAP metadata record (e.g. the trial's parameters)."""
        self._w.add_metadata(name, dict(data))

    def write(self, key: str, msg: Any, stamp_ns: int) -> None:
        """One message on ``key`` at ``stamp_ns`` [ns]."""
        from services.bus.messages import encoding_for, file_descriptor_set, schema_name_of

        ch = self._channels.get(key)
        if ch is None:
            name = schema_name_of(msg)
            sid = self._schemas.get(name)
            if sid is None:
                sid = self._w.register_schema(name=name, encoding="protobuf", data=file_descriptor_set(name))
                self._schemas[name] = sid
            ch = self._w.register_channel(
                topic=key, message_encoding="protobuf", schema_id=sid,
                metadata={"zenoh_encoding": encoding_for(type(msg))},
            )
            self._channels[key] = ch
            self._seq[ch] = 0
        self._seq[ch] += 1
        self._w.add_message(ch, stamp_ns, msg.SerializeToString(), stamp_ns, self._seq[ch])

    def write_run(self, prefix: str, res: Any, joint_names: Sequence[str] = (), frame_id: str = "base",
                  task: str = "feeding") -> int:
        """Write an in-process run (:class:`~services.planner.simulate.SimulationResult`) under
        ``prefix``; returns the number of messages written."""
        from services.bus.messages import ArmCommand, ArmState, Goal, TaskEvent

        tr = res.trace
        n0 = self._w.message_count
        dt = float(tr["t"][1] - tr["t"][0]) if len(tr["t"]) > 1 else 0.0
        st = ArmState(joint_names=list(joint_names), frame_id=frame_id, dt_s=dt)
        cmd = ArmCommand(mode=ArmCommand.CARTESIAN_ACCELERATION, source="planner", frame_id=frame_id,
                         has_angular_velocity_reference=True)
        goal = Goal(frame_id=frame_id, valid=True)
        last_goal: tuple[float, ...] | None = None
        steps = [s.name for s in res.runner.task.steps]
        for i in range(len(tr["t"])):
            stamp = round(float(tr["t"][i]) * 1e9)
            tick = int(tr["tick"][i])
            st.stamp_ns = st.sim_time_ns = stamp
            st.tick = tick
            st.q[:] = tr["q"][i].tolist()
            st.dq[:] = tr["dq"][i].tolist()
            for vec, arr in ((st.ee_position, tr["x"][i]), (st.ee_linear_velocity, tr["v"][i]),
                             (st.ee_linear_acceleration, tr["a"][i])):
                vec.x, vec.y, vec.z = (float(c) for c in arr)
            o = st.ee_orientation
            o.x, o.y, o.z, o.w = (float(c) for c in tr["quat"][i])
            self.write(f"{prefix}/arm/state", st, stamp)
            g = tr["goal"][i]
            if np.isfinite(g).all() and tuple(g) != last_goal:
                last_goal = tuple(float(c) for c in g)
                goal.stamp_ns, goal.seq = stamp, goal.seq + 1
                k = int(tr["step"][i])
                goal.name = res.runner.task.steps[k].goal if 0 <= k < len(steps) else ""
                goal.position.x, goal.position.y, goal.position.z = last_goal
                self.write(f"{prefix}/planner/goal", goal, stamp)
            cmd.stamp_ns, cmd.tick, cmd.seq = stamp, tick, i + 1
            c = cmd.linear_acceleration
            c.x, c.y, c.z = (float(v) for v in tr["a_cmd"][i])
            r = cmd.orientation_reference
            r.x, r.y, r.z, r.w = (float(v) for v in tr["quat_ref"][i])
            w = cmd.angular_velocity_reference
            w.x, w.y, w.z = (float(v) for v in tr["omega_cmd"][i])
            self.write(f"{prefix}/arm/command", cmd, stamp)
        for ev in res.events:
            msg = TaskEvent(
                stamp_ns=ev.stamp_ns, task=task, kind=getattr(TaskEvent, ev.kind), detail=ev.detail,
                step=ev.step, step_index=ev.step_index, state_tick=max(0, ev.tick),
                summary_json=json.dumps(ev.summary, default=float) if ev.summary else "",
            )
            self.write(f"{prefix}/task/events", msg, ev.stamp_ns)
        return self._w.message_count - n0

    def write_obstacles(self, prefix: str, obstacles: Sequence[Any], margin_m: float, stamp_ns: int = 0,
                        frame_id: str = "base") -> None:
        """The obstacle set as the monitor publishes it: ``<prefix>/obstacles`` (``ObstacleSet``)
        and ``<prefix>/viz/scene`` (Foxglove ``SceneUpdate`` with the volumes inflated by
        ``margin_m`` [m])."""
        from services.obstacle_monitor.scene import obstacle_set_message, scene_update

        self.write(f"{prefix}/obstacles", obstacle_set_message(obstacles, stamp_ns, 1, frame_id), stamp_ns)
        scene = scene_update(list(obstacles), margin_m, stamp_ns, frame_id)
        self.write(f"{prefix}/viz/scene", scene, stamp_ns)

    def close(self) -> None:
        """End the file."""
        if self._fh.closed:
            return
        self._w.finish()
        self._fh.close()
