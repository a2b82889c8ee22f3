"""The obstacle monitor's logic, free of the bus: the obstacle set over the stack's clock and
the prediction for one arm state.

:class:`ObstacleMonitor` is used unchanged by the ``psm obstacles`` service (on every
``ArmState``) and by the in-process runs (:func:`services.planner.simulate.monitor_predictor`)::

    mon = ObstacleMonitor(section, robot)          # section: ObstacleMonitorSection
    mon.set_goal(goal)                             # the planner's goal in use (None: unknown)
    mon.add(obstacle, stamp_ns)                    # "" or the reason it was rejected
    pred = mon.check(stamp_ns, tick, x, v, q, dq, dt)

Time: every obstacle has a position at the *epoch* (the stack time of the last change to the set)
and moves with its velocity from there; a change first moves every obstacle to the change's time,
so the set always describes one instant. Units: m, m/s, s (ns for stamps), rad.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from psm.obstacles import Obstacle, SegmentHit, compile_obstacles, segment_check, stopping_check
from services.obstacle_monitor.config import ObstacleMonitorSection

__all__ = ["ObstacleMonitor", "Prediction"]

#: Reasons a change to the set is rejected (besides :data:`psm.obstacles.REASONS`).
REASON_DUPLICATE = "duplicate_id"
REASON_UNKNOWN = "unknown_id"


#: The default of the vector fields of :class:`Prediction` (read-only: shared by every instance).
_NAN3 = np.full(3, np.nan)
_NAN3.setflags(write=False)


@dataclass
class Prediction:
    """The monitor's answer to one arm state (the fields of ``CollisionPrediction``).

    ``stop_position (3,)`` [m] NaN where the axis goes on; ``min_clearance_m`` [m] +inf without
    obstacles within the cutoff; ``clearance_tick`` the tick the clearance was computed at."""

    stamp_ns: int
    tick: int
    obstacle_count: int
    goal: NDArray[np.float64] | None = None
    collision: bool = False
    obstacle_id: str = ""
    inside: bool = False
    entry_point: NDArray[np.float64] = field(default_factory=lambda: _NAN3)
    entry_distance_m: float = math.inf
    time_to_collision_s: float = math.inf
    stop_position: NDArray[np.float64] = field(default_factory=lambda: _NAN3)
    min_clearance_m: float = math.inf
    closest_link: str = ""
    clearance_obstacle_id: str = ""
    clearance_tick: int = 0
    protective_stop: bool = False
    detail: str = ""


class ObstacleMonitor:
    """Obstacle set + segment test + whole-arm clearance (see the module docstring).

    Args:
        section: the ``[obstacle_monitor]`` settings (its start obstacles are loaded).
        robot: the arm's :class:`~services.robot.model.RobotModel` for the whole-arm clearance
            (None: no clearance, whatever ``section.clearance`` says).
    """

    def __init__(self, section: ObstacleMonitorSection, robot: Any | None = None) -> None:
        self.section = section
        self._obstacles: dict[str, Obstacle] = {o.id: o for o in section.start_obstacles()}
        self._epoch_ns: int | None = None  # start obstacles begin to move at the first state
        self.now_ns = 0
        self._moving = False
        self.removed: list[str] = []  # ids removed since the caller last emptied this list
        self.changed = True  # the set changed since the caller last cleared this flag
        self.clearance: Any = None
        if section.clearance and robot is not None:
            from services.robot.clearance import ArmClearance

            self.clearance = ArmClearance(
                robot, margin_m=section.margin_m, cutoff_m=section.clearance_cutoff_m
            )
        self._clearance_dirty = True
        self._goal: NDArray[np.float64] | None = None
        self._last_clear_tick = -(10**12)
        self._clear: Any = None
        self._stopped = False
        self._held: SegmentHit | None = None  # the stopping check's hit, held until released
        self.predictions = 0
        self.collisions = 0
        self.protective_stops = 0
        self.clearance_checks = 0
        self.clearance_us: list[float] = []
        self._recompile()

    # ------------------------------------------------------------------ the set
    @property
    def segment_margin_m(self) -> float:
        """How much the segment test inflates every obstacle [m]: the safety margin plus the
        tool's reach around the end-effector point (the whole-arm clearance uses the margin
        alone, on the arm's real geometry)."""
        return self.section.margin_m + self.section.tool_radius_m

    @property
    def moving(self) -> bool:
        """Some obstacle has a non-zero velocity."""
        return self._moving

    def __len__(self) -> int:
        return len(self._obstacles)

    def obstacles_at(self, stamp_ns: int) -> list[Obstacle]:
        """The obstacles with their positions at ``stamp_ns`` (the stack's clock)."""
        dt = 0.0 if self._epoch_ns is None else (stamp_ns - self._epoch_ns) * 1e-9
        if dt == 0.0 or not self._moving:
            return list(self._obstacles.values())
        return [
            Obstacle(o.id, o.shape, o.position + o.velocity * dt, o.orientation, o.size, o.velocity)
            for o in self._obstacles.values()
        ]

    def get(self, oid: str) -> Obstacle | None:
        """The obstacle ``oid`` (position at the epoch), or None."""
        return self._obstacles.get(oid)

    def _rebase(self, now_ns: int) -> None:
        """Move every obstacle to ``now_ns``; the epoch becomes ``now_ns``."""
        self._obstacles = {o.id: o for o in self.obstacles_at(now_ns)}
        self._epoch_ns = now_ns

    def _recompile(self) -> None:
        obs = list(self._obstacles.values())
        self._compiled = compile_obstacles(obs, self.segment_margin_m)
        self._moving = any(bool(np.any(o.velocity != 0.0)) for o in obs)
        self._clearance_dirty = True
        self.changed = True

    def _stamp(self, stamp_ns: int) -> int:
        return stamp_ns if stamp_ns > 0 else self.now_ns

    def add(self, ob: Obstacle, stamp_ns: int = 0) -> str:
        """Add ``ob`` (valid already) at ``stamp_ns`` (0: now); ``""`` or the rejection reason."""
        if ob.id in self._obstacles:
            return REASON_DUPLICATE
        self._rebase(self._stamp(stamp_ns))
        self._obstacles[ob.id] = ob
        self._recompile()
        return ""

    def replace(self, ob: Obstacle, stamp_ns: int = 0) -> str:
        """Move the existing obstacle ``ob.id`` to ``ob`` (its new pose and velocity)."""
        if ob.id not in self._obstacles:
            return REASON_UNKNOWN
        self._rebase(self._stamp(stamp_ns))
        self._obstacles[ob.id] = ob
        self._recompile()
        return ""

    def remove(self, oid: str, stamp_ns: int = 0) -> str:
        """Remove obstacle ``oid``."""
        if oid not in self._obstacles:
            return REASON_UNKNOWN
        self._rebase(self._stamp(stamp_ns))
        del self._obstacles[oid]
        self.removed.append(oid)
        self._recompile()
        return ""

    def clear(self, stamp_ns: int = 0) -> str:
        """Remove every obstacle."""
        self._rebase(self._stamp(stamp_ns))
        self.removed.extend(self._obstacles)
        self._obstacles.clear()
        self._recompile()
        return ""

    def set_goal(self, goal: Any | None) -> None:
        """The planner's goal in use ``(3,)`` [m] (the segment's end), or None (unknown)."""
        self._goal = None if goal is None else np.asarray(goal, dtype=float).copy()

    # ------------------------------------------------------------------ the check
    def stop_threshold(self, speed_bound_mps: float, dt_s: float) -> float:
        """Clearance [m] below which a protective stop is asked for, for an arm whose fastest
        point moves at most ``speed_bound_mps``: ``clearance_stop_m`` + what it can close before
        the next check (``speed · clearance_every · dt``) + its stopping distance at the
        planner's deceleration (``speed² / (2 brake_decel_mps2)``)."""
        sec = self.section
        return (
            sec.clearance_stop_m
            + speed_bound_mps * sec.clearance_every * dt_s
            + speed_bound_mps * speed_bound_mps / (2.0 * sec.brake_decel_mps2)
        )

    def check(
        self,
        stamp_ns: int,
        tick: int,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
        q: Any,
        dq: Any,
        dt_s: float,
    ) -> Prediction:
        """The prediction for the arm state at ``stamp_ns`` (tick ``tick``): end effector ``x, v
        (3,)`` [m, m/s], joints ``q, dq (n,)`` [rad, rad/s] (any sequence: converted only when the
        clearance is computed), control period ``dt_s`` [s]."""
        if self._epoch_ns is None:
            self._epoch_ns = stamp_ns
        self.now_ns = stamp_ns
        sec = self.section
        out = Prediction(stamp_ns, tick, len(self._obstacles), self._goal)
        compiled = self._compiled
        if self._moving:
            compiled = compiled.at((stamp_ns - self._epoch_ns) * 1e-9)
        if len(compiled):
            horizon = sec.horizon_s if self._moving else 0.0
            hit: SegmentHit | None = None
            if self._goal is not None:
                hit = segment_check(x, self._goal, compiled, horizon_s=horizon, velocity=v)
            if hit is not None and hit.collision:
                self._held = None
                if hit.inside:
                    out.detail = f"end effector inside the safety volume of {hit.obstacle_id}"
                    if sec.stopping_check and not np.isfinite(hit.stop_position).any():
                        # No axis goes deeper towards the goal, but the end effector's own path
                        # may (its segment bends, the goal moved): an axis whose velocity goes
                        # deeper is held where it is, as the stopping check holds it outside.
                        deeper = stopping_check(x, v, compiled, sec.brake_decel_mps2, dt_s, horizon_s=horizon)
                        if deeper.inside and np.isfinite(deeper.stop_position).any():
                            hit = deeper
            elif sec.stopping_check:
                hit = self._stopping(x, v, compiled, horizon, dt_s)
                if hit is not None:
                    out.detail = f"stopping path enters the safety volume of {hit.obstacle_id}"
            if hit is not None and hit.collision:
                self.collisions += 1
                out.collision, out.obstacle_id, out.inside = True, hit.obstacle_id, bool(hit.inside)
                out.entry_point = np.asarray(hit.entry_point, dtype=float)
                out.entry_distance_m = float(hit.distance_m)
                out.time_to_collision_s = float(hit.time_to_collision_s)
                out.stop_position = np.asarray(hit.stop_position, dtype=float)
        else:
            self._held = None
        clr = self.clearance
        if clr is not None and self._obstacles:
            if self._clearance_dirty or tick - self._last_clear_tick >= sec.clearance_every:
                if self._clearance_dirty or self._moving:
                    clr.set_obstacles(self.obstacles_at(stamp_ns))
                    self._clearance_dirty = False
                t0 = time.perf_counter_ns()
                q_arr, dq_arr = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
                res = clr.check(q_arr, per_link=False)  # the prediction carries the closest link only
                bound = clr.speed_bound(q_arr, dq_arr)
                self.clearance_us.append((time.perf_counter_ns() - t0) * 1e-3)
                if len(self.clearance_us) > 100_000:
                    del self.clearance_us[:50_000]
                self._clear, self._last_clear_tick = res, tick
                self.clearance_checks += 1
                limit = self.stop_threshold(bound, dt_s)
                if self._stopped:
                    if res.min_distance_m > limit - sec.clearance_stop_m + sec.clearance_resume_m:
                        self._stopped = False
                elif res.min_distance_m < limit:
                    self._stopped = True
                    self.protective_stops += 1
            res = self._clear
            out.min_clearance_m = float(res.min_distance_m)
            out.closest_link, out.clearance_obstacle_id = res.link, res.obstacle_id
            out.clearance_tick = self._last_clear_tick
        else:
            self._stopped = False
        if self._stopped:
            out.protective_stop = True
            out.detail = (
                f"clearance {out.min_clearance_m:.3f} m between {out.closest_link} "
                f"and {out.clearance_obstacle_id}"
            )
        self.predictions += 1
        return out

    def _stopping(
        self, x: NDArray[np.float64], v: NDArray[np.float64], compiled: Any, horizon: float, dt_s: float
    ) -> SegmentHit | None:
        """The stopping check (:func:`psm.obstacles.stopping_check`) while the segment to the goal
        is clear: the end effector's path bends away from that segment (a re-targeted goal, the
        demonstration's shape) and may cut an obstacle's edge the segment clears. A hit is held
        while the end effector stays within ``stopping_release_m`` of the surface it headed into
        (a probe that far along the surface's inward normal still enters the same obstacle), so
        an axis held at a face is not released and caught again at every tick. With moving
        obstacles nothing is held: the stop is computed afresh at every tick."""
        sec = self.section
        held = self._held
        if held is not None:
            probe = segment_check(x, x - held.normal * sec.stopping_release_m, compiled, horizon_s=horizon)
            if probe.collision and probe.obstacle_id == held.obstacle_id:
                return held
            self._held = None
        hit = stopping_check(x, v, compiled, sec.brake_decel_mps2, dt_s, horizon_s=horizon)
        if not hit.collision:
            return None
        if not hit.inside and not self._moving:
            self._held = hit
        return hit

    def summary(self) -> dict[str, Any]:
        """Counters and the clearance check's cost percentiles [µs]."""
        out: dict[str, Any] = {
            "predictions": self.predictions,
            "collisions": self.collisions,
            "protective_stops": self.protective_stops,
            "clearance_checks": self.clearance_checks,
            "obstacles": len(self._obstacles),
        }
        if self.clearance_us:
            a = np.asarray(self.clearance_us)
            out["clearance_us"] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}
        return out
