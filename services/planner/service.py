"""The ``psm plan`` service: the task sequencer on the bus.

Every :class:`~services.bus.messages.ArmState` on ``<prefix>/arm/state`` is answered with one
Cartesian :class:`~services.bus.messages.ArmCommand` on ``<prefix>/arm/command`` echoing the
state's tick: the active step's PSM acceleration per dimension, the orientation reference that
follows the reference dimension's ``t_e`` and its angular velocity
(:class:`~services.planner.sequencer.TaskRunner`). Live goals come from ``<prefix>/goals/*``;
the first command a goal update shapes names it (``goal_updates``: name and stamp, in the order
applied), so a recording says at which tick the planner took in each update.

Published besides the commands:

* ``<prefix>/planner/status`` — :class:`PlannerStatus` at ``status_rate_hz``: state (running,
  holding and why, done, fault), the step, segment and ``t_e`` per dimension, goal in use,
  distance to it, speed, the orientation reference, state→command latency percentiles over the
  last period, counts of answered and rejected inputs;
* ``<prefix>/task/events`` — :class:`TaskEvent` for every transition (step started, segment
  changed, goal changed or lost, paused, resumed, gripper, step completed, task completed or
  aborted; the completions carry their figures as JSON);
* ``<prefix>/gripper/command`` — :class:`GripperCommand` where the task asks for one;
* ``<prefix>/planner/goal`` — :class:`Goal`: the goal the active step heads to (offset
  included), on every change, latched: the obstacle monitor tests the segment to it;
* ``<prefix>/viz/plan`` — a foxglove ``SceneUpdate`` with the status (once the first state is
  answered): the goal in use, the task's static goals, the segment from the end effector to the
  goal and the end effector's path so far (:class:`~services.planner.viz.PlanScene`, one message
  changed in place, built outside the lock).

Obstacles (``collision_check = "required"``): the monitor's :class:`CollisionPrediction` on
``<prefix>/collision`` is applied to the running step (eq. 15 stops, protective stop; see
:class:`~services.planner.sequencer.TaskRunner`); without a prediction younger than
``prediction_max_age_s`` on the stack's clock, or with the monitor's liveliness gone, every axis
brakes to rest. In lockstep a state is answered once the prediction for its tick has arrived
(the run is then as deterministic as without the monitor); a state superseded by the next one,
or held when the monitor disappears, is answered with what is known. In realtime the latest
prediction is used at once (no wait on the control path).

Live goals in lockstep (``live_goal_sync``): the goal tracker analyses the synthetic camera's
frames as fast as it can, so without a rule the tick at which a new goal is first used depends
on wall time. With the sync a state at sim time ``t`` is answered once every live goal of the
task has arrived for the camera frame due at ``t`` (frame ``k`` at ``round(k · 10⁹ / fps)``
ns on the arm's clock, :mod:`services.goal_tracker.frames`; the tracker publishes one goal per
frame, valid or not): the camera renders that frame when it sees the state, so the goals in
use at every tick, and the run, are a function of the inputs. The wait ends early once the
tracker's liveliness is gone; a wait longer than ``live_goal_wait_s`` (wall clock) answers the
state with the goals known and pauses the sync until the next live goal arrives.

Threads: the state is handled on Zenoh's receive thread (decode into a reused message, checks,
the controller step, encode into a reused command, ``put``: no queue hop, no allocation beyond
a few small arrays); goals arrive on a subscription worker; both take one lock. Events and
status are published by the service's loop thread, off the control path.

Bad input never moves the arm: an undecodable state, a state with non-finite values, a tick
that goes back or jumps ahead by more than ``max_tick_gap``, or a stamp that disagrees with
``tick × dt`` is rejected (counted, logged rate-limited) and not answered; a malformed goal, a
non-finite one, one in another frame or outside the workspace is rejected and never used. A
state that repeats the last answered one exactly (a lockstep arm re-offering it) gets the same
command again. After ``resync_after`` rejected states in a row that form a stream of their own
(:class:`~services.robot.protocol.StateStream`) the planner follows the new stream (an arm that
restarted, states back after an outage) and the active step restarts from its state; random or
stale states never form one. A prediction about a state that does not fit the arm's stream, and
a goal stamped more than ``goal_timeout_s`` ahead of the stack's clock, are rejected too.

Restarts (``progress_file``): after each step transition the loop thread writes the task's
progress (:mod:`services.planner.progress`) once the transition's events and gripper command are
published; a planner started again reads it and, when its first arm state is of the same arm
run, resumes at the step that was running, from the arm's state (the steps completed before are
not redone and stay in the summary).
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from services.bus.messages import (
    ArmCommand,
    ArmState,
    CollisionPrediction,
    Goal,
    GripperCommand,
    PlannerStatus,
    TaskEvent,
    encoding_for,
)
from services.bus.runtime import Service, ServiceApp, receive_thread_handler, run_service
from services.goal_tracker.frames import due_frame, frame_period_ns, frame_time_ns
from services.planner.config import PlannerConfig
from services.planner.feasibility import JointAccelerationScaling
from services.planner.models import DEMOS_DIR, ModelCache, load_task_models
from services.planner.progress import ProgressError, TaskProgress, read_progress, write_progress
from services.planner.sequencer import CollisionInfo, CollisionPolicy, TaskRunner
from services.planner.viz import PlanScene
from services.robot.protocol import StateStream
from services.threads import limit_blas_threads

SERVICE_NAME = "planner"

_LAT_RING = 4096  # latency samples kept between two status messages (at most ~8 s at 500 Hz)
#: Goal updates a command names at most (``ArmCommand.goal_updates``): ~34 s of a 30 Hz goal
#: without an arm state to answer; older ones are then left out of the command.
GOAL_UPDATES_MAX = 1024

_STATES = {
    "IDLE": PlannerStatus.IDLE,
    "RUNNING": PlannerStatus.RUNNING,
    "HOLDING": PlannerStatus.HOLDING,
    "DONE": PlannerStatus.DONE,
    "FAULT": PlannerStatus.FAULT,
}


class PlannerService(ServiceApp):
    """The planner process (see the module docstring). Built without the bus: the task file is
    read and every step's model learned (or read from the cache) before the process joins."""

    name = SERVICE_NAME
    svc: Service

    def __init__(self, config: PlannerConfig) -> None:
        super().__init__(config)
        from services.tasks.feeding import load_feeding
        from services.threads import set_realtime_priority

        limit_blas_threads(1)
        self.config: PlannerConfig = config
        sec = config.planner
        self.task_config = load_feeding(sec.task_path())
        cache = ModelCache(Path(sec.cache_dir)) if sec.cache_dir else None
        demos = Path(sec.demos_dir) if sec.demos_dir else DEMOS_DIR
        self.models = load_task_models(self.task_config.task, cache, demos)
        scene = self.task_config.scene
        self._check_collisions = sec.collision_check == "required"
        # The robot the arm simulates, from the [arm] table's robot fields: the commands are
        # scaled into its joint acceleration limits (services/planner/feasibility.py).
        feasibility = (
            JointAccelerationScaling(config.arm.robot_model(), sec.joint_accel_fraction)
            if sec.joint_accel_fraction > 0.0
            else None
        )
        self._n_joints = feasibility.robot.n if feasibility is not None else 0
        self._joints = (np.zeros(self._n_joints), np.zeros(self._n_joints))
        self._joint_state: ArmState | None = None  # the state being answered (its joints, when needed)
        self._joints_problem = ""
        self._joints_fn = self._read_joints if self._n_joints else None
        self.runner = TaskRunner(
            self.task_config.task,
            scene.positions(),
            self.models.models,
            self.models.profiles,
            self.models.demos,
            collision=CollisionPolicy(sec.prediction_max_age_s) if self._check_collisions else None,
            feasibility=feasibility,
        )
        # Lockstep: answer a state once the prediction for its tick is in (deterministic runs).
        self._wait_prediction = self._check_collisions and config.clock == "lockstep"
        # Lockstep with live_goal_sync: and once the live goals of every camera frame due at its
        # time are in (the goal tracker in the loop, reproducibly).
        sync = sec.live_goal_sync and config.clock == "lockstep"
        self._live_names = sorted({s.goal for s in self.task_config.task.steps if s.live}) if sync else []
        self._frame_period = frame_period_ns(config.goal_tracker.synthetic.fps) if self._live_names else None
        self._live_stamp: dict[str, int] = {}  # live goal -> stamp of the latest one received [ns]
        self._tracker_seen = False
        self._tracker_alive = False
        self._sync_paused = False  # after a wait that timed out, until the next live goal
        self.goal_wait_timeouts = 0
        #: The state waiting for its prediction or goals: (payload, receive ns, tick, sim time
        #: [ns], monotonic time it was parked [s]).
        self._parked: tuple[bytes, int, int, int, float] | None = None
        self._pred = CollisionPrediction()
        self._pred_encoding = encoding_for(CollisionPrediction)
        self._pred_tick = -1
        self.waited_states = 0
        self.rejected_predictions = 0
        self._goal_msg = Goal(frame_id=scene.frame_id)
        self._sent_goal: tuple[float, ...] | None = None  # position, velocity
        self._sent_goal_step = -1
        self.frame_id = scene.frame_id
        # After the models are learned (never fit at real-time priority) and before the bus
        # opens, so Zenoh's threads (the state is answered on one) inherit it.
        self._rt_problem = set_realtime_priority(sec.rt_priority, config.clock)
        self._lock = threading.Lock()
        self._state = ArmState()
        self._cmd = ArmCommand(
            mode=ArmCommand.CARTESIAN_ACCELERATION,
            source=sec.source,
            frame_id=scene.frame_id,
            has_angular_velocity_reference=True,
        )
        self._state_encoding = encoding_for(ArmState)
        self._last_tick = -1
        self._last_stamp = 0
        self._last_reply = b""
        #: The goal updates offered to the runner since the last command: ``(name, stamp_ns)``;
        #: with no state to answer for a long time only the latest are kept for the next command.
        self._goal_updates: deque[tuple[str, int]] = deque(maxlen=GOAL_UPDATES_MAX)
        self._stream = StateStream(
            sec.max_tick_gap, round(sec.stamp_tolerance_s * 1e9), sec.resync_after
        )
        self._dt_s = 0.0  # the period of the last state answered [s]
        self._seq = 0
        self.answered = 0
        self.rejected_states = 0
        self.duplicate_states = 0
        self._lat = np.zeros(_LAT_RING, dtype=np.int64)
        self._n_lat = 0
        self._lat_all: list[float] = []  # every latency, µs, for the summary percentiles
        self._events: deque[Any] = deque()
        self._ended_at: float | None = None
        self._x = np.zeros(3)
        self._v = np.zeros(3)
        self._a = np.zeros(3)
        self._q = np.zeros(4)
        # Restarts: the progress an earlier planner left (decided on the first state), why it
        # cannot be used, and the arm's period of the states answered [ns].
        self._progress: TaskProgress | None = None
        self._progress_problem = ""
        if sec.progress_file:
            try:
                self._progress = read_progress(sec.progress_file, self.task_config.task)
            except ProgressError as exc:
                self._progress_problem = str(exc)
        self._dt_ns = 0
        self._wake = threading.Event()  # a transition to publish (and to write to the progress file)
        self.plan_scene = PlanScene(
            scene.frame_id, self.runner.goals.static, sec.viz_path_points, sec.viz_path_step_m
        )

    # ------------------------------------------------------------------ setup
    def setup(self, svc: Service) -> None:
        """Declare the command, status, event and gripper publishers, the state subscriber (on
        Zenoh's thread) and the goal subscription."""

        self.svc = svc
        keys = svc.keys
        if self._rt_problem:
            svc.log.warning(self._rt_problem + "; running with normal scheduling")
        self._cmd_pub = svc.publisher(keys.arm_command)
        self._status_pub = svc.publisher(keys.planner_status)
        self._event_pub = svc.publisher(keys.task_events)
        self._gripper_pub = svc.publisher(keys.gripper_command)
        # Before the state subscriber: the first answer may publish the goal at once.
        self._goal_pub = svc.publisher(keys.planner_goal)
        self._viz_pub = svc.publisher(keys.viz_plan)
        self._state_key = keys.arm_state.key
        sub = svc.session.declare_subscriber(
            self._state_key, receive_thread_handler(self._on_state)
        )
        svc.on_close(sub.undeclare)
        self._goals_prefix = keys.goals_all.key[:-1]
        svc.subscribe(keys.goals_all, self._on_goal)
        if self._check_collisions:
            self._pred_key = keys.collision.key
            pred_sub = svc.session.declare_subscriber(
                self._pred_key, receive_thread_handler(self._on_prediction)
            )
            svc.on_close(pred_sub.undeclare)
            # Not alive until its token is seen (no prediction yet means blocked either way).
            self.runner.set_monitor_alive(False)
            svc.watch_liveliness([self.config.planner.monitor_service], self._on_monitor)
        if self._frame_period is not None:
            svc.watch_liveliness([self.config.planner.tracker_service], self._on_tracker)
        task = self.task_config.task
        if self._progress_problem:
            svc.log.warning("progress file not used: the task starts from its first step",
                            extra={"reason": self._progress_problem})
        svc.log.info(
            "planner ready",
            extra={"task": task.name, "steps": ",".join(task.sequence), "models": len(self.models.models)},
        )

    # ------------------------------------------------------------------ inputs
    def _reject_state(self, reason: str, kind: str) -> None:
        self.rejected_states += 1
        self.svc.record_rejection(self._state_key, reason, kind)

    def _on_state(self, sample: Any) -> None:
        """Zenoh's receive thread: answer the state (see the module docstring)."""
        t_recv = time.perf_counter_ns()
        payload = sample.payload.to_bytes()
        if str(sample.encoding) != self._state_encoding:
            with self._lock:
                self._reject_state(f"encoding {sample.encoding} is not psm.ArmState", "encoding")
            return
        with self._lock:
            if not self._parse_state(payload):
                return
            if self._wait_prediction or self._frame_period is not None:
                st = self._state
                tick = int(st.tick)
                # A later state supersedes a parked one (the arm stepped without an answer): it
                # is answered with what is known. The same state offered again (before the first
                # answer the arm repeats state 0) waits on.
                prev, self._parked = self._parked, None
                superseded = prev is not None and tick > prev[2]
                parked_at = prev[4] if prev is not None and not superseded else time.monotonic()
                now_ns = int(st.sim_time_ns or st.stamp_ns)
                if (
                    not superseded
                    and tick != self._last_tick
                    and (self._prediction_pending(tick) or self._goals_pending(now_ns))
                ):
                    # answered by _on_prediction / _on_goal / the loop's wait bound
                    self._parked = (payload, t_recv, tick, now_ns, parked_at)
                    return
            self._handle_state(t_recv)

    def _prediction_pending(self, tick: int) -> bool:
        """Lockstep: the prediction for ``tick`` is still to come (under the lock)."""
        return self._wait_prediction and self.runner.monitor_alive and tick > self._pred_tick

    def _goals_pending(self, now_ns: int) -> bool:
        """Lockstep with ``live_goal_sync``: a live goal of a camera frame due at the sim time
        ``now_ns`` is still to come (under the lock). Never once the tracker is gone, nor while
        the sync is paused after a wait ran out."""
        period = self._frame_period
        if period is None or self._sync_paused or (self._tracker_seen and not self._tracker_alive):
            return False
        due = frame_time_ns(due_frame(now_ns, period), period)
        return any(self._live_stamp.get(name, -1) < due for name in self._live_names)

    def _answer_if_ready(self) -> None:
        """Answer the parked state once nothing it waits for is pending (under the lock)."""
        parked = self._parked
        if parked is None or self._prediction_pending(parked[2]) or self._goals_pending(parked[3]):
            return
        self.waited_states += 1
        self._answer_parked()

    def _parse_state(self, payload: bytes) -> bool:
        """Parse ``payload`` into the reused state message; False (rejected) if it does not parse."""
        try:
            self._state.ParseFromString(payload)
        except Exception as exc:
            self._reject_state(f"malformed ArmState ({len(payload)} bytes): {exc}", "malformed")
            return False
        return True

    def _answer_parked(self) -> None:
        """Answer the state waiting for its prediction, if any (under the lock)."""
        parked, self._parked = self._parked, None
        if parked is not None and self._parse_state(parked[0]):
            self._handle_state(parked[1])

    def _handle_state(self, t_recv: int) -> None:
        """Check and answer the parsed state (under the lock)."""
        st = self._state
        self.svc.counters.add("received")
        reply = self._answer(st)
        if reply is None:
            return
        # A changed goal goes out before the command: the monitor then has it before the arm
        # state that the command leads to (same session and router, so the order holds).
        self._publish_goal()
        self._cmd_pub.put_bytes(reply)
        lat = time.perf_counter_ns() - t_recv
        self._lat[self._n_lat % _LAT_RING] = lat
        self._n_lat += 1
        if len(self._lat_all) < 2_000_000:
            self._lat_all.append(lat * 1e-3)

    def _publish_goal(self) -> None:
        """Publish the goal in use when it changed (the monitor's segment end)."""
        g = self.runner.goal
        if g is None:
            return
        gv = self.runner.goal_velocity
        key = (float(g[0]), float(g[1]), float(g[2]), float(gv[0]), float(gv[1]), float(gv[2]))
        if key == self._sent_goal and self._sent_goal_step == self.runner.index:
            return
        self._sent_goal, self._sent_goal_step = key, self.runner.index
        spec = self.runner.step_spec
        m = self._goal_msg
        m.stamp_ns = self._last_stamp
        m.seq += 1
        m.name = spec.goal if spec else ""
        m.position.x, m.position.y, m.position.z = key[:3]
        m.velocity.x, m.velocity.y, m.velocity.z = key[3:]
        m.valid = True
        self._goal_pub.put(m)

    def _on_prediction(self, sample: Any) -> None:
        """Zenoh's receive thread: the monitor's prediction; answers a state waiting for it."""
        payload = sample.payload.to_bytes()
        with self._lock:
            if str(sample.encoding) != self._pred_encoding:
                self._reject_prediction(f"encoding {sample.encoding}", "encoding")
                return
            pr = self._pred
            try:
                pr.ParseFromString(payload)
            except Exception as exc:
                self._reject_prediction(f"malformed CollisionPrediction: {exc}", "malformed")
                return
            stop = np.array(pr.stop_position, dtype=float) if pr.stop_position else np.full(3, np.nan)
            if stop.shape != (3,) or np.isinf(stop).any():
                self._reject_prediction("stop_position is not 3 numbers (NaN = none)", "stop_position")
                return
            if math.isnan(pr.min_clearance_m):
                self._reject_prediction("min_clearance_m is NaN", "non_finite")
                return
            tick = int(pr.state_tick)
            if not self._stream.follows(tick, int(pr.stamp_ns), self._dt_s):
                # A prediction about a state the arm did not publish (far from its last tick, or
                # a stamp that disagrees with it): never used, and never lets a forged tick hide
                # the real predictions behind it.
                self._reject_prediction(
                    f"prediction for tick {tick} (stamp {int(pr.stamp_ns)}) does not fit the arm's "
                    f"stream at tick {self._stream.last_tick}", "tick")
                return
            if tick < self._pred_tick:
                return  # an older prediction arriving late
            self._pred_tick = tick
            self.runner.set_collision(
                CollisionInfo(
                    stamp_ns=int(pr.stamp_ns),
                    tick=tick,
                    collision=bool(pr.collision),
                    obstacle_id=pr.obstacle_id,
                    stop_position=stop,
                    protective_stop=bool(pr.protective_stop),
                    min_clearance_m=float(pr.min_clearance_m),
                    closest_link=pr.closest_link,
                    detail=pr.detail,
                    inside=bool(pr.inside),
                )
            )
            self._answer_if_ready()

    def _reject_prediction(self, reason: str, kind: str) -> None:
        self.rejected_predictions += 1
        self.svc.record_rejection(self._pred_key, reason, kind)

    def _on_monitor(self, name: str, alive: bool) -> None:
        with self._lock:
            self.runner.set_monitor_alive(alive)
            if not alive:
                self.svc.log.warning("obstacle monitor gone: braking every axis", extra={"service": name})
                self._answer_parked()

    def _on_tracker(self, name: str, alive: bool) -> None:
        """The goal tracker's liveliness (``live_goal_sync``): once it is gone, no state waits for
        its goals."""
        with self._lock:
            self._tracker_alive = alive
            if alive:
                self._tracker_seen = True
                return
            self.svc.log.warning("goal tracker gone: states no longer wait for its goals",
                                 extra={"service": name})
            self._answer_if_ready()

    def _check_goal_wait(self) -> None:
        """The loop's bound on a wait for goals (``live_goal_wait_s``, wall clock): past it the
        parked state is answered with the goals known and the sync pauses until the next live
        goal arrives."""
        with self._lock:
            parked = self._parked
            if parked is None or not self._goals_pending(parked[3]):
                return
            waited = time.monotonic() - parked[4]
            if waited < self.config.planner.live_goal_wait_s:
                return
            self._sync_paused = True
            self.goal_wait_timeouts += 1
            self.svc.log.warning(
                "no live goal for a due camera frame: answering without it, the sync pauses until the "
                "next goal", extra={"tick": parked[2], "waited_s": round(waited, 3)})
            self._answer_if_ready()

    def _read_joints(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The joints ``(q, dq)`` of the state being answered, for the joint acceleration scaling
        (None, with one warning, when the arm's joints are not the planner's robot's)."""
        st = self._joint_state
        if st is None:
            return None
        n = self._n_joints
        if len(st.q) != n or len(st.dq) != n:
            if not self._joints_problem:
                self._joints_problem = (
                    f"the arm has {len(st.q)} joints, the planner's robot {n}: commands are not scaled "
                    "into the joint limits (check the [arm] table's robot)"
                )
                self.svc.log.warning(self._joints_problem)
            return None
        q, dq = self._joints
        q[:] = st.q
        dq[:] = st.dq
        return q, dq

    def _answer(self, st: ArmState) -> bytes | None:
        """The command bytes answering ``st``, or None when it is rejected (under the lock)."""
        tick, stamp = int(st.tick), int(st.stamp_ns)
        if tick == self._last_tick and stamp == self._last_stamp and self._last_reply:
            self.duplicate_states += 1
            return self._last_reply
        p, v, o, a = st.ee_position, st.ee_linear_velocity, st.ee_orientation, st.ee_linear_acceleration
        # The checks on plain floats (numpy calls cost ~1 µs each on 3-vectors), then the
        # values into the reused arrays the runner reads.
        px, py, pz, vx, vy, vz = p.x, p.y, p.z, v.x, v.y, v.z
        qx, qy, qz, qw = o.x, o.y, o.z, o.w
        dt = float(st.dt_s)
        if not (math.isfinite(dt) and dt > 0.0):
            self._reject_state(f"tick {tick}: dt_s {dt} is not a positive number", "dt")
            return None
        isfinite = math.isfinite
        if not (
            isfinite(px) and isfinite(py) and isfinite(pz) and isfinite(vx) and isfinite(vy)
            and isfinite(vz) and isfinite(qx) and isfinite(qy) and isfinite(qz) and isfinite(qw)
        ):
            self._reject_state(f"tick {tick}: non-finite end-effector state", "non_finite")
            return None
        x = self._x
        x[0], x[1], x[2] = px, py, pz
        vv = self._v
        vv[0], vv[1], vv[2] = vx, vy, vz
        q = self._q
        q[0], q[1], q[2], q[3] = qx, qy, qz, qw
        acc = self._a
        acc[0], acc[1], acc[2] = a.x, a.y, a.z
        nq = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if abs(nq - 1.0) > 0.01:
            self._reject_state(f"tick {tick}: orientation quaternion norm {nq:.3g}", "quaternion")
            return None
        verdict, why = self._stream.check(tick, stamp, dt)
        if verdict in ("tick", "stamp"):
            self._reject_state(why, verdict)
            return None
        if verdict == "resync":
            self.svc.log.warning("following a new arm state stream", extra={"reason": why})
            self.runner.restart_step()
        self._dt_s = dt
        if self._dt_ns == 0:
            self._first_state(tick, stamp, dt)
        self._joint_state = st
        out = self.runner.step(stamp, x, vv, q, dt, tick=tick, measured_accel=acc, joints=self._joints_fn)
        events = self.runner.drain_events()
        if events:
            self._events.extend(events)
            self._wake.set()
        cmd = self._cmd
        self._seq += 1
        cmd.stamp_ns, cmd.tick, cmd.seq = stamp, tick, self._seq
        c = cmd.linear_acceleration
        c.x, c.y, c.z = out.acceleration.tolist()
        r = cmd.orientation_reference
        r.x, r.y, r.z, r.w = out.orientation.tolist()
        w = cmd.angular_velocity_reference
        w.x, w.y, w.z = out.angular_velocity.tolist()
        if self._goal_updates:
            refs = cmd.goal_updates
            for name, goal_stamp in self._goal_updates:
                ref = refs.add()
                ref.name, ref.stamp_ns = name, goal_stamp
            self._goal_updates.clear()
            reply = cmd.SerializeToString()
            del refs[:]
        else:
            reply = cmd.SerializeToString()
        self._last_tick, self._last_stamp, self._last_reply = tick, stamp, reply
        self.answered += 1
        return reply

    def _first_state(self, tick: int, stamp: int, dt: float) -> None:
        """The first state answered (under the lock): resume the task from the progress file if
        the file is of this run of the arm (:meth:`TaskProgress.same_arm_run`)."""
        self._dt_ns = round(dt * 1e9)
        p, self._progress = self._progress, None
        if p is None:
            return
        tolerance = round(self.config.planner.stamp_tolerance_s * 1e9)
        if not p.same_arm_run(stamp, tick, self._dt_ns, tolerance):
            self.svc.log.info(
                "progress file of another arm run: the task starts from its first step",
                extra={"file": self.config.planner.progress_file, "tick": tick, "file_tick": p.tick},
            )
            return
        self.runner.resume(p.next_index, p.completed, p.resumes)
        self.svc.log.warning(
            "resuming the task",
            extra={"next_step": p.next_index, "completed": p.next_index, "tick": tick,
                   "resumes": len(p.resumes) + 1},
        )

    def _write_progress(self, ev: Any) -> None:
        """After a transition's events are published (loop thread): the task's progress up to
        the step ``ev`` completed (``STEP_COMPLETED``, ``COMPLETED``)."""
        path = self.config.planner.progress_file
        if not path or self._dt_ns == 0:
            return
        n = len(self.task_config.task.steps)
        upto = n if ev.kind == "COMPLETED" else ev.step_index + 1
        with self._lock:
            progress = TaskProgress(
                task=self.task_config.task.name,
                steps=list(self.task_config.task.sequence),
                next_index=upto,
                arm_origin_ns=int(ev.stamp_ns) - int(ev.tick) * self._dt_ns,
                dt_ns=self._dt_ns,
                tick=int(ev.tick),
                completed=self.runner.completed_steps(upto),
                resumes=list(self.runner.resumes),
            )
        try:
            write_progress(path, progress)
        except OSError as exc:
            self.svc.record_error(f"cannot write the progress file {path}: {exc.strerror}")

    def _on_goal(self, msg: Goal, key: str) -> None:
        name = msg.name or key[len(self._goals_prefix) :]
        p = msg.position
        with self._lock:
            if msg.frame_id and msg.frame_id != self.frame_id:
                self.runner.goals.rejected += 1
                self.svc.record_rejection(
                    key, f"goal {name} in frame {msg.frame_id!r}, expected {self.frame_id!r}", "frame"
                )
                return
            now = self._last_stamp if self._last_tick >= 0 else None
            problem = self.runner.update_goal(
                name, (p.x, p.y, p.z), int(msg.stamp_ns), bool(msg.valid), msg.invalid_reason, now_ns=now
            )
            self._goal_updates.append((name, int(msg.stamp_ns)))
            kind = self.runner.goals.last_rejection_kind
            sync = self._frame_period is not None and name in self._live_names
            if sync and (not problem or kind != "stamp"):
                # The goal of its frame is in, valid or not, used or rejected (a goal whose stamp
                # was refused is not).
                self._live_stamp[name] = max(self._live_stamp.get(name, -1), int(msg.stamp_ns))
                self._sync_paused = False
                self._answer_if_ready()
        if problem:
            self.svc.record_rejection(key, f"goal {name}: {problem}", kind)

    # ------------------------------------------------------------------ loop
    def loop(self, svc: Service) -> None:
        """Publish the status at ``status_rate_hz`` and the events as they come; stop after the
        task ends when ``exit_when_done``."""
        sec = self.config.planner
        period = 1.0 / sec.status_rate_hz
        next_t = time.monotonic() + period
        while not svc.stop_event.is_set():
            # Woken by a transition: its events (and the progress file) go out at once.
            self._wake.wait(max(0.0, next_t - time.monotonic()))
            self._wake.clear()
            if self._frame_period is not None:
                self._check_goal_wait()
            self._publish_events()
            if time.monotonic() < next_t:
                continue
            next_t += period
            self._publish_status()
            if self.runner.state in ("DONE", "FAULT") and sec.exit_when_done:
                if self._ended_at is None:
                    self._ended_at = time.monotonic()
                    svc.log.info(
                        "task ended", extra={"state": self.runner.state, "detail": self.runner.detail}
                    )
                elif time.monotonic() - self._ended_at >= sec.linger_s:
                    # A task that failed is a failed process (docker: restart on-failure).
                    self.exit_code = 0 if self.runner.state == "DONE" else 1
                    break
        self._publish_events()
        self._publish_status()

    def _publish_events(self) -> None:
        task = self.task_config.task.name
        while self._events:
            ev = self._events.popleft()
            msg = TaskEvent(
                stamp_ns=ev.stamp_ns,
                task=task,
                kind=getattr(TaskEvent, ev.kind),
                detail=ev.detail,
                step=ev.step,
                step_index=ev.step_index,
                state_tick=max(0, ev.tick),
                summary_json=json.dumps(ev.summary, default=float) if ev.summary else "",
            )
            self._event_pub.put(msg)
            if ev.kind == "GRIPPER":
                action = GripperCommand.CLOSE if ev.detail == "close" else GripperCommand.OPEN
                self._gripper_pub.put(
                    GripperCommand(
                        stamp_ns=ev.stamp_ns, action=action, step=ev.step, source=self.config.planner.source
                    )
                )
            if ev.kind in ("STEP_COMPLETED", "COMPLETED"):
                self._write_progress(ev)
            if ev.kind in (
                "STARTED",
                "STEP_COMPLETED",
                "COMPLETED",
                "ABORTED",
                "GOAL_LOST",
                "RESUMED",
                "GRIPPER",
            ):
                self.svc.log.info(f"{ev.kind.lower()}: {ev.detail}", extra={"tick": ev.tick})

    def _publish_status(self) -> None:
        with self._lock:
            r = self.runner
            ctrl = r.controller
            n = min(self._n_lat, _LAT_RING)
            lat = np.sort(self._lat[:n]) * 1e-3 if n else None
            self._n_lat = 0
            spec = r.step_spec
            msg = PlannerStatus(
                stamp_ns=self._last_stamp,
                state=_STATES[r.state],
                task=r.task.name,
                state_tick=max(0, self._last_tick),
                detail=r.detail,
                step=spec.name if spec else "",
                step_index=max(0, r.index),
                step_count=len(r.task.steps),
                distance_to_goal_m=r.distance if math.isfinite(r.distance) else 0.0,
                speed_mps=r.speed,
                answered=self.answered,
                rejected_states=self.rejected_states,
                rejected_goals=r.goals.rejected,
                goal_name=spec.goal if spec else "",
                step_elapsed_s=(self._last_stamp - r.reports[-1].start_ns) * 1e-9 if r.reports else 0.0,
                goal_speed_mps=float(np.linalg.norm(r.goal_velocity)),
            )
            if self._check_collisions:
                info = r.collision
                msg.collision_check = True
                msg.monitor_alive = r.monitor_alive
                msg.collision_stops = r.collision_stops
                msg.waited_states = self.waited_states
                if info is not None:
                    msg.collision = info.collision
                    msg.obstacle_id = info.obstacle_id
                    msg.stop_position.extend(float(c) for c in info.stop_position)
                    msg.min_clearance_m = info.min_clearance_m
                    msg.prediction_age_s = (self._last_stamp - info.stamp_ns) * 1e-9
            if ctrl is not None:
                msg.segment_index.extend(int(s) for s in ctrl.segment)
                msg.time_to_go_s.extend(float(t) for t in ctrl.time_to_go)
                msg.mode.extend(ctrl.modes)
            if r.goal is not None:
                g = r.goal
                msg.goal.x, msg.goal.y, msg.goal.z = float(g[0]), float(g[1]), float(g[2])
            q = r.orientation_reference
            o = msg.orientation_reference
            o.x, o.y, o.z, o.w = (float(c) for c in q)
            if lat is not None:
                msg.latency_p50_us = float(lat[n // 2])
                msg.latency_p99_us = float(lat[min(n - 1, int(0.99 * n))])
                msg.latency_max_us = float(lat[-1])
            # The scene's inputs (copied: the control path reuses these arrays).
            answered = self._last_tick >= 0
            ee = (float(self._x[0]), float(self._x[1]), float(self._x[2]))
            goal = None if r.goal is None else (float(r.goal[0]), float(r.goal[1]), float(r.goal[2]))
            goal_name = msg.goal_name
        self._status_pub.put(msg)
        if answered:
            self._viz_pub.put(self.plan_scene.update(msg.stamp_ns, ee, goal, goal_name))

    # ------------------------------------------------------------------ end
    def summary(self) -> dict[str, Any]:
        """The task summary plus the planner's own counters and latency percentiles [µs]."""
        with self._lock:
            out = self.runner.summary()
            lat = np.asarray(self._lat_all) if self._lat_all else None
            out["planner"] = {
                "answered": self.answered,
                "rejected_states": self.rejected_states,
                "duplicate_states": self.duplicate_states,
                "rejected_goals": self.runner.goals.rejected,
            }
            if self._check_collisions:
                out["planner"].update(
                    collision_stops=self.runner.collision_stops,
                    rejected_predictions=self.rejected_predictions,
                )
            if self._check_collisions or self._frame_period is not None:
                out["planner"]["waited_states"] = self.waited_states
            if self._frame_period is not None:
                out["planner"]["live_goal_sync"] = {
                    "goals": sorted(self._live_names),
                    "frame_period_ns": float(self._frame_period),
                    "wait_timeouts": self.goal_wait_timeouts,
                }
        if lat is not None:
            p50, p99, p999 = np.percentile(lat, [50, 99, 99.9])
            out["planner"]["latency_us"] = {
                "p50": float(p50),
                "p99": float(p99),
                "p99.9": float(p999),
                "max": float(lat.max()),
                "n": int(lat.size),
            }
        return out

    def teardown(self, svc: Service) -> None:
        """Log the outcome and write the summary file."""
        s = self.summary()
        svc.log.info(
            "planner stopped",
            extra={
                "state": s["state"],
                "steps_succeeded": s["steps_succeeded"],
                "answered": self.answered,
                "rejected_states": self.rejected_states,
            },
        )
        path = self.config.planner.summary_file
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(path).with_suffix(".tmp")
            tmp.write_text(json.dumps(s, indent=2, default=float))
            with contextlib.suppress(OSError):
                tmp.replace(path)


def main(config: PlannerConfig) -> int:
    """Run the planner with a loaded config; returns the exit code."""
    return run_service(PlannerService(config))
