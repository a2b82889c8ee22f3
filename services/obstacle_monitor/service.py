"""The ``psm obstacles`` service: the obstacle set and a collision prediction for every arm state.

Inputs:

* ``<prefix>/arm/state`` — every :class:`ArmState` (handled on Zenoh's receive thread);
* ``<prefix>/planner/goal`` — the goal the planner's active step heads to (latched);
* ``<prefix>/obstacles/command`` — :class:`ObstacleCommand`: add, move (new pose and velocity;
  shape and size kept), remove by id, clear. A command takes effect at its ``stamp_ns`` on the
  stack's clock (0: at the latest arm state); a moving obstacle is predicted with its velocity.

Outputs:

* ``<prefix>/collision`` — :class:`CollisionPrediction` for every arm state, tagged with the
  state's tick and stamp (:class:`~services.obstacle_monitor.monitor.ObstacleMonitor`): the
  paper's segment test from the end effector to the planner's goal against the inflated
  obstacles (the first obstacle hit, where the segment enters it, the stop coordinate per axis,
  the time to collision) and the whole-arm clearance (every ``clearance_every`` ticks) with the
  closest link; a protective stop while the clearance is below ``clearance_stop_m`` plus what the
  arm can close before the next check and while braking, until it is above
  ``clearance_resume_m`` plus the same allowance;
* ``<prefix>/obstacles`` — the current :class:`ObstacleSet` (latched), and
  ``<prefix>/viz/scene`` — the obstacles and the volumes the segment test keeps the end-effector
  point out of (inflated by ``margin_m + tool_radius_m``) as a foxglove
  ``SceneUpdate`` (latched): on every change, and at ``scene_rate_hz`` while one moves.

Bad input never produces a prediction built on it: an obstacle command with NaN, a non-positive
size, an unknown shape, a non-unit quaternion, an empty id, a duplicate id on ADD or an unknown
id on MOVE / REMOVE is rejected (the service status's ``rejected`` count and ``last_error``, the
log, and per reason in the summary logged at exit) and the set is unchanged; an undecodable or
non-finite arm state, or one that does not continue the arm's stream (a tick that goes back or
jumps, a stamp that disagrees with its tick: :class:`~services.robot.protocol.StateStream`), is
rejected and not answered (the planner then has no fresh prediction and brakes); a planner goal
that is not finite, lies beyond ``MAX_EXTENT_M``, is older than the last one or stamped more
than :data:`GOAL_AHEAD_NS` ahead of the latest arm state is rejected.
Every rejection is counted by reason on the status (``rejected_by_reason``).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from psm.obstacles import MAX_EXTENT_M, Obstacle, ObstacleError
from services.bus.messages import ArmState, CollisionPrediction, Goal, ObstacleCommand, encoding_for
from services.bus.runtime import Service, ServiceApp, receive_thread_handler, run_service
from services.obstacle_monitor.config import ObstacleMonitorConfig
from services.obstacle_monitor.monitor import ObstacleMonitor, Prediction
from services.obstacle_monitor.scene import (
    obstacle_from_message,
    obstacle_set_message,
    scene_update,
    shape_enum,
)
from services.robot.protocol import StateStream
from services.threads import limit_blas_threads

SERVICE_NAME = "obstacle_monitor"

_ACTIONS = frozenset(ObstacleCommand.Action.values())

#: A planner goal is stamped with the arm state it was chosen at: one stamped further ahead of
#: the latest arm state than this [ns] is from no planner (it would hide every real update).
GOAL_AHEAD_NS = 1_000_000_000

__all__ = ["GOAL_AHEAD_NS", "SERVICE_NAME", "ObstacleMonitorService", "main", "prediction_message"]


def prediction_message(p: Prediction, seq: int, out: CollisionPrediction) -> CollisionPrediction:
    """Fill ``out`` (cleared first) with the prediction ``p``."""
    out.Clear()
    out.stamp_ns, out.seq, out.state_tick = p.stamp_ns, seq, p.tick
    out.obstacle_count = p.obstacle_count
    if p.goal is not None:
        out.goal_known = True
        out.goal.x, out.goal.y, out.goal.z = p.goal.tolist()
    out.collision, out.obstacle_id, out.inside = p.collision, p.obstacle_id, p.inside
    if p.collision:
        out.entry_point.x, out.entry_point.y, out.entry_point.z = p.entry_point.tolist()
    out.entry_distance_m = p.entry_distance_m
    out.time_to_collision_s = p.time_to_collision_s
    out.stop_position.extend(p.stop_position.tolist())
    out.min_clearance_m = p.min_clearance_m
    out.closest_link, out.clearance_obstacle_id = p.closest_link, p.clearance_obstacle_id
    out.clearance_tick = max(0, p.clearance_tick)
    out.protective_stop, out.detail = p.protective_stop, p.detail
    return out


class ObstacleMonitorService(ServiceApp):
    """The monitor process (see the module docstring)."""

    name = SERVICE_NAME
    svc: Service

    def __init__(self, config: ObstacleMonitorConfig) -> None:
        super().__init__(config)
        limit_blas_threads(1)
        self.config: ObstacleMonitorConfig = config
        sec = config.obstacle_monitor
        self.section = sec
        from services.threads import set_realtime_priority

        # Before the session opens: zenoh's threads inherit the policy.
        self._rt_problem = set_realtime_priority(sec.rt_priority, config.clock)
        robot = None
        if sec.clearance:
            from services.robot.model import RobotModel

            robot = RobotModel.load(sec.urdf or None)
        self.monitor = ObstacleMonitor(sec, robot)
        self._lock = threading.Lock()
        self._state = ArmState()
        self._state_encoding = encoding_for(ArmState)
        self._pred = CollisionPrediction()
        self._seq = 0
        self._set_seq = 0
        self._last_scene_ns = 0
        self.rejected_commands: dict[str, int] = {}  # reason -> count
        # The arm's stream (a stale, replayed or forged state gets no prediction) and the
        # latest planner goal's stamp (an older one is stale).
        self._stream = StateStream()
        self._goal_stamp = -1

    # ------------------------------------------------------------------ setup
    def setup(self, svc: Service) -> None:
        """Publishers (prediction, set, scene), the state subscriber on Zenoh's thread, the goal
        and command subscriptions."""

        self.svc = svc
        if self._rt_problem:
            svc.log.warning(self._rt_problem + "; running with normal scheduling")
        keys = svc.keys
        self._pred_pub = svc.publisher(keys.collision)
        self._set_pub = svc.publisher(keys.obstacles)
        self._scene_pub = svc.publisher(keys.scene)
        self._state_key = keys.arm_state.key
        sub = svc.session.declare_subscriber(
            self._state_key, receive_thread_handler(self._on_state)
        )
        svc.on_close(sub.undeclare)
        svc.subscribe(keys.planner_goal, self._on_goal)
        svc.subscribe(keys.obstacles_command, self._on_command)
        self._publish_set()
        svc.log.info(
            "obstacle monitor ready",
            extra={
                "obstacles": len(self.monitor),
                "margin_m": self.section.margin_m,
                "tool_radius_m": self.section.tool_radius_m,
                "clearance": self.monitor.clearance is not None,
                "clearance_every": self.section.clearance_every,
            },
        )

    # ------------------------------------------------------------------ obstacle set
    def apply_command(self, cmd: ObstacleCommand) -> str:
        """Apply one command; ``""`` if applied, else the reason it was rejected (the set is then
        unchanged). Thread-safe."""
        with self._lock:
            return self._apply(cmd)

    def _apply(self, cmd: ObstacleCommand) -> str:
        mon, stamp = self.monitor, int(cmd.stamp_ns)
        oid = cmd.obstacle.id or cmd.id
        action = cmd.action
        if action == ObstacleCommand.CLEAR:
            return mon.clear(stamp)
        if action == ObstacleCommand.REMOVE:
            return mon.remove(oid, stamp)
        if action not in (ObstacleCommand.ADD, ObstacleCommand.MOVE):
            return "action"
        msg = type(cmd.obstacle)()
        msg.CopyFrom(cmd.obstacle)
        msg.id = oid
        if action == ObstacleCommand.MOVE:
            old = mon.get(oid)
            if old is None:
                return "unknown_id"
            msg.shape = shape_enum(old.shape)  # MOVE keeps the shape and size
            msg.size.x, msg.size.y, msg.size.z = (float(c) for c in old.size)
        try:
            ob: Obstacle = obstacle_from_message(msg)
        except ObstacleError as exc:
            return exc.reason
        return mon.replace(ob, stamp) if action == ObstacleCommand.MOVE else mon.add(ob, stamp)

    def _on_command(self, cmd: ObstacleCommand, key: str) -> None:
        reason = self.apply_command(cmd)
        action = ObstacleCommand.Action.Name(cmd.action) if cmd.action in _ACTIONS else f"action {cmd.action}"
        what = f"{action} {cmd.obstacle.id or cmd.id!r}"
        if reason:
            with self._lock:
                self.rejected_commands[reason] = self.rejected_commands.get(reason, 0) + 1
            self.svc.record_rejection(key, f"obstacle command {what}: {reason}", reason)
        else:
            self.svc.log.info("obstacle set changed", extra={"command": what, "obstacles": len(self.monitor)})

    def _on_goal(self, msg: Goal, key: str) -> None:
        p = msg.position
        g = np.array([p.x, p.y, p.z])
        stamp = int(msg.stamp_ns)
        with self._lock:
            ahead = stamp - self._stream.last_stamp if self._stream.last_tick >= 0 else 0
            if stamp < self._goal_stamp:
                self.svc.record_rejection(key, "planner goal older than the last one", "stamp")
            elif ahead > GOAL_AHEAD_NS:
                self.svc.record_rejection(
                    key, f"planner goal stamped {ahead * 1e-9:.3g} s ahead of the arm's clock", "stamp")
            elif not msg.valid:
                self.monitor.set_goal(None)
                self._goal_stamp = stamp
            elif not np.isfinite(g).all():
                self.svc.record_rejection(key, "planner goal is not finite", "non_finite")
            elif float(np.abs(g).max()) > MAX_EXTENT_M:
                self.svc.record_rejection(key, f"planner goal beyond {MAX_EXTENT_M:g} m", "range")
            else:
                self.monitor.set_goal(g)
                self._goal_stamp = stamp

    def current_obstacles(self) -> list[Obstacle]:
        """The obstacles with their positions at the latest arm state."""
        with self._lock:
            return self.monitor.obstacles_at(self.monitor.now_ns)

    # ------------------------------------------------------------------ the check
    def _on_state(self, sample: Any) -> None:
        """Zenoh's receive thread: one prediction per arm state."""
        payload = sample.payload.to_bytes()
        with self._lock:
            if str(sample.encoding) != self._state_encoding:
                self.svc.record_rejection(
                    self._state_key, f"encoding {sample.encoding} is not psm.ArmState", "encoding")
                return
            st = self._state
            try:
                st.ParseFromString(payload)
            except Exception as exc:
                self.svc.record_rejection(self._state_key, f"malformed ArmState: {exc}", "malformed")
                return
            msg = self.predict(st)
            if msg is None:
                return
            out = msg.SerializeToString()
        self._pred_pub.put_bytes(out)

    def predict(self, st: ArmState) -> CollisionPrediction | None:
        """The prediction message for one arm state (under the lock), or None when the state is
        rejected."""
        p, v = st.ee_position, st.ee_linear_velocity
        x = np.array([p.x, p.y, p.z, v.x, v.y, v.z])
        dt = float(st.dt_s)
        # sum() of the joints is NaN/inf when one is: the joints are checked without an array.
        finite = math.isfinite(float(x.sum())) and math.isfinite(sum(st.q) + sum(st.dq))
        if not (finite and dt > 0.0):
            self.svc.record_rejection(
                self._state_key, f"tick {st.tick}: non-finite state or dt_s", "non_finite")
            return None
        verdict, why = self._stream.check(int(st.tick), int(st.stamp_ns), dt)
        if verdict in ("tick", "stamp"):
            self.svc.record_rejection(self._state_key, why, verdict)
            return None
        # The joints (repeated fields) become arrays only on the ticks the clearance is computed.
        pred = self.monitor.check(int(st.stamp_ns), int(st.tick), x[:3], x[3:], st.q, st.dq, dt)
        self._seq += 1
        return prediction_message(pred, self._seq, self._pred)

    # ------------------------------------------------------------------ loop
    def loop(self, svc: Service) -> None:
        """Publish the set and the scene on change, and at ``scene_rate_hz`` (stack clock) while an
        obstacle moves."""
        period_ns = int(1e9 / self.section.scene_rate_hz)
        mon = self.monitor
        while not svc.stop_event.is_set():
            svc.wait(0.02)
            with self._lock:
                due = mon.changed or (mon.moving and mon.now_ns - self._last_scene_ns >= period_ns)
            if due:
                self._publish_set()

    def _publish_set(self) -> None:
        mon = self.monitor
        with self._lock:
            now = mon.now_ns
            obs = mon.obstacles_at(now)
            removed, mon.removed = mon.removed, []
            mon.changed = False
            self._last_scene_ns = now
            self._set_seq += 1
            seq = self._set_seq
        frame = self.section.frame_id
        self._set_pub.put(obstacle_set_message(obs, now, seq, frame))
        self._scene_pub.put(scene_update(obs, mon.segment_margin_m, now, frame, removed))

    def summary(self) -> dict[str, Any]:
        """The monitor's counters."""
        with self._lock:
            return {**self.monitor.summary(), "rejected_commands": dict(self.rejected_commands)}

    def teardown(self, svc: Service) -> None:
        """Log the counters."""
        svc.log.info("obstacle monitor stopped", extra=self.summary())


def main(config: ObstacleMonitorConfig) -> int:
    """Run the monitor with a loaded config; returns the exit code."""
    return run_service(ObstacleMonitorService(config))
