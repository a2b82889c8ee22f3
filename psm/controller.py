"""The online PSM controller: phase-space state in, Cartesian (or any-space) acceleration out.

Per dimension it runs the chain of PSTFs learned by :class:`psm.PhaseSpaceModel`, re-solving the
current segment from the measured state at every tick, which is what makes the model robust to
pushes, moved starts and moving goals (paper §III-C..F; corrected equations in ``docs/psm.md``):

* **segment law** (eq. 7 with the corrected eq. 5): towards the next via-point ``(x_n, v_n)`` the
  acceleration is ``c₀ − k Δ/2`` with ``Δ = x_n − x``, ``c₀ = (v_n² − v²)/(2Δ)``; the learned ``k`` is
  clamped to ``ρ k_max(v, v_n, Δ) − κ`` so a perturbed state never makes the segment unstable;
* **wrong direction** (eq. 10): a velocity pointing away from ``x_n`` gets a constant acceleration
  ``m`` towards it until it is zero;
* **synchronisation**: a dimension whose time to completion ``t_e`` is below the largest one
  ``t_E`` is slowed. ``sync_mode="brake"`` is the paper's eq. 14, ``−T v (t_E − t_e)`` with ``t_e``
  from the nominal segment durations (eq. 13); ``"scale"`` compares the dimensions on the
  demonstration's own clock (``t_e`` = time to the next via-point + the demonstration time after
  it) and time-scales a dimension that is ahead by the lead ``L``: its law runs at the rate
  ``s = 1 − L/τ`` and ``−(1−s) v/τ`` brakes it, so at ``L ≥ τ`` it holds still (a dwell of one
  dimension while another moves is kept). The part of a lead that a goal change opens is excused
  (shrinking with the slowest ``t_E``), so a suddenly-ahead dimension slows over the rest of the
  motion instead of stopping at once; ``sync_gain = 0`` switches either off;
* **start shift** (option ``start_shift``): from a start other than the demonstrated one, the
  via-points are displaced by the start's offset, fading linearly to nothing at the goal over the
  nominal duration (see :meth:`PSMController._shift_start`);
* **start retiming** (option ``start_retime``): at the first step the slope of the segment the
  motion starts in is re-solved so that the segment keeps its nominal duration from the actual
  start (as a DMP keeps its execution time);
* **rest retiming** (option ``rest_retime``, on by default): a dimension that comes to rest
  inside a segment (held still, stopped by a push) re-solves that segment's slope so that it
  takes the nominal time left from there (the segment's nominal duration times the fraction of
  its length still ahead). Without it a dimension at rest short of a via-point at rest crawls
  on the stability margin κ alone, and the synchronisation holds the others back for it;
* **segment retiming** (option ``segment_retime``, on by default): a segment whose learned slope
  lies close to the stability bound has a duration that is sensitive to the state it is entered
  in (a tick short of its via-point, a fraction of a percent slow: several percent longer). When
  a dimension enters a segment on the demonstrated state but the learned slope would take more
  than two ticks and 2 % longer or shorter than the nominal time, the slope is re-solved for the
  nominal time (see :meth:`PSMController._retime_entry`). Without it such a dimension falls
  behind at the via-point, the synchronisation slows the others, and they in turn miss their
  next via-points' speeds;
* **collision stop** (eq. 15): a per-dimension request "stop at x_ob" decelerates with
  ``−v²/(2(x_ob − x))`` while the obstacle lies between the state and the via-point (at most the
  deceleration that ends the tick on the stop); given the obstacle's side of the stop, a
  dimension found past it is brought back to it by the holding spring;
* **saturation**: the segment law (with the synchronisation term) is limited to
  ``max_acceleration`` per dimension; a state that cannot match a via-point's velocity in time
  passes it (a non-reversal via-point is skipped when that would take more than ``2 m``);
* **terminal capture**: within one tick of the goal a critically damped spring holds the goal.

Via-points are stored relative to the goal, so :meth:`PSMController.set_goal` moves all of them at
once; the current segment index only moves forward (progress), skipping via-points the state has
already passed. The hot path is plain ``math`` on floats: one ``step`` costs a few microseconds
per dimension.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from psm.errors import ParameterError, ShapeError
from psm.pstf import K_MAX_FRACTION, K_ZERO_TOL, k_for_duration, k_limit, time_to_reach

_INF = math.inf
_TWO_PI = 2.0 * math.pi
_THREE_HALVES_PI = 1.5 * math.pi
_sqrt, _log, _atan2 = math.sqrt, math.log, math.atan2
_cosh, _sinh, _cos, _sin = math.cosh, math.sinh, math.cos, math.sin

#: Segment retiming (option ``segment_retime``) acts on a segment entered with a velocity within
#: this fraction of the segment's speed scale ``max(|v_j|, |v_n|)`` of its via-point's ...
SEGMENT_RETIME_SPEED_FRACTION = 0.1
#: ... when the learned slope would take longer or shorter than the nominal time by more than
#: this many control ticks and this fraction of the segment's nominal duration.
SEGMENT_RETIME_TICKS = 2.0
SEGMENT_RETIME_DURATION_FRACTION = 0.02
#: Defaults of the controller options ``rest_retime`` and ``segment_retime`` (also those of
#: :meth:`psm.PhaseSpaceModel.controller` and :meth:`~psm.PhaseSpaceModel.rollout`).
REST_RETIME_DEFAULT = True
SEGMENT_RETIME_DEFAULT = True

#: Controller modes of one dimension (reported by :attr:`PSMController.modes`).
MODE_SEGMENT = "segment"
MODE_WRONG_WAY = "wrong_way"
MODE_STOP = "collision_stop"
MODE_TERMINAL = "terminal"

#: Synchronisation modes: the paper's eq. 14 braking, or time-scaling on a shared progress.
SYNC_BRAKE = "brake"
SYNC_SCALE = "scale"
SYNC_MODES = (SYNC_BRAKE, SYNC_SCALE)


def validate_sync(sync_mode: str, sync_time: float) -> None:
    """Raise :class:`ParameterError` unless ``sync_mode`` is one of :data:`SYNC_MODES` and
    ``sync_time`` [s] is finite and > 0."""
    if sync_mode not in SYNC_MODES:
        raise ParameterError(f"sync_mode must be one of {SYNC_MODES}, got {sync_mode!r}")
    if not (math.isfinite(sync_time) and sync_time > 0.0):
        raise ParameterError(f"sync_time must be a finite number > 0, got {sync_time}")


@dataclass(frozen=True)
class DimensionChain:
    """One dimension's PSTF chain in goal-relative coordinates (what the controller runs).

    ``offsets (N+1,)`` via-point positions minus the goal [unit] (last is 0), ``velocities (N+1,)``
    [unit/s] (last is 0), ``k (N,)`` [1/s²], ``kappa (N,)`` [1/s²], ``durations (N,)`` [s].
    ``demo_tails (N,)`` [s], optional: the demonstration time left after each segment's end
    via-point (used by the ``"scale"`` synchronisation; default: the nominal durations' sums).
    """

    offsets: tuple[float, ...]
    velocities: tuple[float, ...]
    k: tuple[float, ...]
    kappa: tuple[float, ...]
    durations: tuple[float, ...]
    hold: bool
    demo_tails: tuple[float, ...] | None = None


class PSMController:
    """Stateful online controller for one motion; create it with ``model.controller(goal)``.

    ``a = ctrl.step(x, v, dt)`` takes the measured position ``x (D,)`` [unit] and velocity
    ``v (D,)`` [unit/s] and returns the commanded acceleration ``(D,)`` [unit/s²] for the next ``dt``
    [s]; for a moving goal, ``ctrl.step(x, v, dt, goal_velocity)`` runs the phase-space law on the
    velocity relative to the goal's (the via-points move with it) and the collision stops, fixed in
    the world, on the measured velocity. ``ctrl.set_goal(g)`` moves the goal at any time (velocity
    stays continuous);
    ``ctrl.time_to_go`` is each dimension's ``t_e`` [s]; ``ctrl.done`` is true once every dimension
    holds the goal within the model's tolerances.
    """

    def __init__(
        self,
        chains: list[DimensionChain],
        goal: ArrayLike,
        wrong_way_accel: NDArray[np.float64],
        sync_gain: float,
        position_tolerance: float,
        velocity_tolerance: float,
        terminal_omega: float | None = None,
        max_acceleration: NDArray[np.float64] | None = None,
        sync_mode: str = SYNC_BRAKE,
        sync_time: float = 0.1,
        start_retime: bool = False,
        start_shift: bool = False,
        rest_retime: bool = REST_RETIME_DEFAULT,
        segment_retime: bool = SEGMENT_RETIME_DEFAULT,
    ) -> None:
        validate_sync(sync_mode, sync_time)
        self._D = len(chains)
        self._chains = chains
        self._holds = [c.hold for c in chains]  # read every step (hot path)
        self._n = [len(c.k) for c in chains]
        self._sync_mode = sync_mode
        self._sync_time = float(sync_time)
        self._start_retime = bool(start_retime)
        self._start_shift = bool(start_shift)
        self._rest_retime = bool(rest_retime)
        self._segment_retime = bool(segment_retime)
        # weight of a start displacement at each via-point: the nominal time left there / total
        self._shift_weight = [
            [float(sum(c.durations[j:])) / max(float(sum(c.durations)), 1e-300) for j in range(len(c.k) + 1)]
            for c in chains
        ]
        # tail[d][j]: time after segment j's end via-point. Eq. 14 ("brake") uses the nominal
        # durations of the later segments (eq. 13); "scale" uses the demonstration's own schedule
        # (the same clock for every dimension) when the chain carries it.
        self._tail = [
            list(c.demo_tails)
            if sync_mode == SYNC_SCALE and c.demo_tails is not None
            else [float(sum(c.durations[j + 1 :])) for j in range(len(c.k))]
            for c in chains
        ]
        self._dir = [
            [math.copysign(1.0, c.offsets[j + 1] - c.offsets[j]) for j in range(len(c.k))] for c in chains
        ]
        self._m = [float(m) for m in wrong_way_accel]
        self._a_max = (
            [math.inf] * len(chains) if max_acceleration is None else [float(a) for a in max_acceleration]
        )
        self._sync_gain = float(sync_gain)
        self._pos_tol = float(position_tolerance)
        self._vel_tol = float(velocity_tolerance)
        self._terminal_omega = terminal_omega
        self._goal: list[float] = []
        self._stops: list[float | None] = [None] * self._D
        self._stop_sides: list[float | None] = [None] * self._D  # the obstacle's side of each stop
        self._t_e = [float(sum(c.durations)) for c in chains]
        self._modes = [MODE_SEGMENT] * self._D
        self.reset()
        self.set_goal(goal)

    # ------------------------------------------------------------------ public state
    @property
    def dim(self) -> int:
        """Number of dimensions D."""
        return self._D

    @property
    def goal(self) -> NDArray[np.float64]:
        """Current goal ``(D,)`` [unit]."""
        return np.array(self._goal)

    @property
    def segment(self) -> NDArray[np.int64]:
        """Index of the segment each dimension is in ``(D,)``."""
        return np.array(self._segment, dtype=np.int64)

    @property
    def time_to_go(self) -> NDArray[np.float64]:
        """Each dimension's time to completion ``t_e`` (eq. 13) ``(D,)`` [s], as of the last step."""
        return np.array(self._t_e)

    @property
    def segment_tuple(self) -> tuple[int, ...]:
        """:attr:`segment` as a tuple of ints (for a control loop that reads it every tick)."""
        return tuple(self._segment)

    @property
    def time_to_go_tuple(self) -> tuple[float, ...]:
        """:attr:`time_to_go` as a tuple of floats [s] (for a control loop that reads it every
        tick)."""
        return tuple(self._t_e)

    @property
    def modes(self) -> list[str]:
        """Each dimension's mode in the last step (segment, wrong_way, collision_stop, terminal)."""
        return list(self._modes)

    @property
    def done(self) -> bool:
        """True once every dimension holds the goal (within position/velocity tolerance)."""
        return self._done

    # ------------------------------------------------------------------ commands
    def set_goal(self, goal: ArrayLike) -> None:
        """Move the goal ``(D,)`` [unit]; via-points move with it. Takes effect at the next step."""
        g = np.asarray(goal, dtype=float).ravel()
        if g.shape != (self._D,):
            raise ShapeError(f"goal must have shape ({self._D},), got {np.shape(goal)}")
        if not np.all(np.isfinite(g)):
            raise ShapeError("goal must be finite")
        goal = [float(e) for e in g]
        if self._goal and goal != self._goal:
            self._goal_moved = True
        self._goal = goal
        self._terminal = [False] * self._D
        self._k_cap = [math.inf] * self._D
        self._done = False

    def request_stop(self, dim: int, position: float, side: float | None = None) -> None:
        """Collision braking (eq. 15): dimension ``dim`` stops at ``position`` [unit] while the stop
        lies between the state and the via-point it is heading to. Replaces an earlier request.

        ``side`` (+1 or −1, optional): the obstacle lies on that side of ``position``. With it the
        stop is also a barrier: an axis found past it on that side (pushed, drifted, or stopped
        where it already was) is brought back to it by the holding spring instead of going on
        with its segment; without it a stop only brakes an axis approaching it."""
        if not 0 <= dim < self._D:
            raise ShapeError(f"dimension index {dim} out of range 0..{self._D - 1}")
        if not math.isfinite(position):
            raise ParameterError("stop position must be finite")
        if side is not None and side not in (1.0, -1.0):
            raise ParameterError(f"stop side must be +1 or -1, got {side}")
        self._stops[dim] = float(position)
        self._stop_sides[dim] = None if side is None else float(side)

    def set_stops(self, positions: ArrayLike, sides: ArrayLike | None = None) -> None:
        """Set every dimension's stop at once: ``positions (D,)`` [unit], NaN meaning no stop;
        ``sides (D,)`` (optional): the side of each stop the obstacle lies on, +1 or −1 (0 or
        NaN: not known), see :meth:`request_stop`."""
        p = np.asarray(positions, dtype=float).ravel()
        if p.shape != (self._D,):
            raise ShapeError(f"stops must have shape ({self._D},), got {np.shape(positions)}")
        if sides is None:
            q = [None] * self._D
        else:
            sd = np.asarray(sides, dtype=float).ravel()
            if sd.shape != (self._D,):
                raise ShapeError(f"stop sides must have shape ({self._D},), got {np.shape(sides)}")
            q = [float(e) if e in (1.0, -1.0) else None for e in sd.tolist()]
        self._stops = [None if math.isnan(e) else float(e) for e in p]
        self._stop_sides = [sd_ if st is not None else None for st, sd_ in zip(self._stops, q, strict=True)]

    def clear_stops(self) -> None:
        """Remove every collision stop; the motion resumes from wherever it is."""
        self._stops = [None] * self._D
        self._stop_sides = [None] * self._D

    def reset(self) -> None:
        """Start the motion over (first segment) with the current goal (also the initial state)."""
        D = self._D
        self._segment = [0] * D
        self._terminal = [False] * D
        self._k_cap = [math.inf] * D
        self._returning = [False] * D
        self._done = False
        # Start retiming and start shift act once, at the first step of a motion: the re-solved
        # slope of the segment the motion starts in (segment, k), the shifted via-points.
        self._retime_pending = [True] * D
        self._shift_pending = [True] * D
        self._k_start: list[tuple[int, float] | None] = [None] * D
        self._at_rest = [True] * D  # rest retiming acts when a dimension comes to rest
        self._offsets = [list(c.offsets) for c in self._chains]
        self._vels = [list(c.velocities) for c in self._chains]
        self._axes = [self._axis(d) for d in range(D)]
        # "scale" synchronisation: leads of the last step and the part of each lead a goal change
        # opened (excused, shrinking with the slowest time to completion) [s]
        self._goal_moved = False
        self._lead = [0.0] * D
        self._excused = [0.0] * D
        self._t_big_prev = 0.0

    # ------------------------------------------------------------------ the control law
    def step(
        self, x: ArrayLike, v: ArrayLike, dt: float, goal_velocity: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """Acceleration command ``(D,)`` [unit/s²] for the measured state ``x, v (D,)`` over ``dt`` [s].

        ``goal_velocity (D,)`` [unit/s] (None: a static goal): the velocity of a moving goal. The
        via-points are relative to the goal, so the law runs on ``v − goal_velocity``; a collision
        stop is a position in the world and brakes ``v`` itself to rest there."""
        D = self._D
        xs = x.tolist() if isinstance(x, np.ndarray) else list(x)
        v_world = v.tolist() if isinstance(v, np.ndarray) else list(v)
        if goal_velocity is None:
            vs = v_world
        else:
            gv = goal_velocity.tolist() if isinstance(goal_velocity, np.ndarray) else list(goal_velocity)
            if len(gv) != D:
                raise ShapeError(f"goal_velocity must have shape ({D},), got {len(gv)}")
            vs = [v_world[d] - gv[d] for d in range(len(v_world))]
        if len(xs) != D or len(vs) != D:
            raise ShapeError(f"state must have shape ({D},), got x {len(xs)}, v {len(vs)}")
        if not dt > 0.0:
            raise ParameterError(f"dt must be > 0, got {dt}")
        acc = [0.0] * D
        t_e, modes, returning, holds = self._t_e, self._modes, self._returning, self._holds
        goal, pos_tol, vel_tol = self._goal, self._pos_tol, self._vel_tol
        braking = [False] * D
        all_done = True
        t_big = 0.0  # the largest finite t_e of the dimensions that take part in the synchronisation
        dimension = self._dimension
        for d in range(D):
            x_d, v_d = xs[d], vs[d]
            a, te, mode = dimension(d, x_d, v_d, v_world[d], dt)
            acc[d] = a
            t_e[d] = te
            modes[d] = mode
            if mode == MODE_SEGMENT:
                all_done = False
                # Hold dimensions, stopped ones and one returning from an overshoot of its goal (a
                # correction, not demonstrated progress) take no part in the synchronisation.
                if not holds[d] and not returning[d]:
                    braking[d] = True
                    if t_big < te < _INF:
                        t_big = te
            elif not (mode == MODE_TERMINAL and abs(x_d - goal[d]) <= pos_tol and abs(v_d) <= vel_tol):
                all_done = False
        self._done = all_done
        gain = self._sync_gain
        a_max = self._a_max
        if gain > 0.0 and D > 1:
            if self._sync_mode == SYNC_BRAKE:
                # Eq. 14: slow the dimensions ahead of the slowest one.
                for d in range(D):
                    if braking[d] and t_e[d] < t_big:
                        acc[d] -= gain * vs[d] * (t_big - t_e[d])
            else:
                # Time scaling on a shared progress: a dimension whose time to completion is
                # shorter than the slowest one's by the lead L runs at the rate s = 1 − L/τ
                # (τ = sync_time, s ≥ 0): a law that speeds it up (or starts it from rest) is
                # scaled by s, and −(1−s) v/τ brakes it towards rest. At L ≥ τ it holds still: a
                # dwell is kept while the others catch up. A slowed dimension's own t_e grows, so
                # the lead closes from both sides; the reference (the slowest) always runs its
                # own law, so nothing can wait for ever.
                tau = self._sync_time
                # A lead that a goal change opens is not a demonstrated dwell: it is excused and
                # the excuse shrinks with the slowest dimension's time to completion, so the
                # dimension catches up by slowing over the rest of the motion instead of holding
                # still at once (the dimensions still arrive together).
                lead_prev, excused = self._lead, self._excused
                goal_moved = self._goal_moved
                t_big_prev = self._t_big_prev
                shrink = t_big / t_big_prev if not goal_moved and 0.0 < t_big < t_big_prev else 0.0
                leads = [0.0] * D
                self._goal_moved = False
                self._t_big_prev = t_big
                self._lead = leads
                for d in range(D):
                    te_d = t_e[d]
                    lead_d = t_big - te_d if braking[d] and te_d < t_big else 0.0
                    leads[d] = lead_d
                    if goal_moved:
                        opened = lead_d - lead_prev[d]
                        excused[d] += opened if opened > 0.0 else 0.0
                    elif shrink:
                        excused[d] *= shrink
                    if modes[d] is not MODE_SEGMENT:
                        continue
                    a_d = acc[d]
                    if lead_d > 0.0:
                        lead = lead_d - excused[d]
                        s = 1.0 - (lead if lead > 0.0 else 0.0) / tau  # 1 − max(0, lead)/τ
                        if s < 0.0:
                            s = 0.0
                        v_d = vs[d]
                        if a_d * v_d > 0.0 or v_d == 0.0:
                            a_d *= s  # speeding up: slowed time scales the push
                        # (a deceleration is never weakened: that would overshoot the via-point)
                        a_d = a_d - (1.0 - s) * v_d / tau
                    # saturation, as below (in this loop: one pass over the dimensions)
                    limit = a_max[d]
                    acc[d] = limit if a_d > limit else (-limit if a_d < -limit else a_d)
                return np.array(acc)
        # The segment law is exact but not gentle: a state pushed right in front of a reversal would
        # have to stop within millimetres. Saturate it; the state then overshoots the via-point and
        # the next segment (or eq. 10) brings it back. Collision stops are never saturated.
        for d in range(D):
            if modes[d] is MODE_SEGMENT:
                limit = a_max[d]
                a_d = acc[d]
                acc[d] = limit if a_d > limit else (-limit if a_d < -limit else a_d)
        return np.array(acc)

    def _dimension(self, d: int, x: float, v: float, v_world: float, dt: float) -> tuple[float, float, str]:
        """Acceleration, time to completion and mode of dimension ``d`` in the state ``x`` [unit],
        ``v`` relative to the goal and ``v_world`` measured [unit/s]."""
        k_seg, kappas, durations, hold, n, offsets, vels, dirs, m, a_max, tail = self._axes[d]
        g = self._goal[d]
        if self._terminal[d]:
            if 2.0 * abs(v) <= a_max * dt * 5.0 and abs(x - g) <= 100.0 * self._pos_tol:
                return self._terminal_law(x - g, v, dt, a_max), 0.0, MODE_TERMINAL
            self._terminal[d] = False  # knocked off the goal: the last segment's law takes over
        if self._shift_pending[d]:
            self._shift_pending[d] = False
            if self._start_shift and not hold:
                self._shift_start(d, x - g)
                offsets, vels = self._offsets[d], self._vels[d]
        pos_tol = self._pos_tol
        vel_tol = self._vel_tol
        j = j_prev = self._segment[d]
        while True:
            x_n = g + offsets[j + 1]
            v_n = vels[j + 1]
            delta = x_n - x
            last = j == n - 1
            if not last and delta * dirs[j] <= 0.0:
                j += 1  # progress: this via-point is already behind the state
                continue
            if -pos_tol <= delta <= pos_tol and -vel_tol <= v <= vel_tol:
                if last:
                    break
                # At rest on a via-point: it is reached. (A state still moving within pos_tol of
                # a via-point keeps following the segment law until it arrives, below: skipping
                # ahead there would cut a slow approach short and run ahead of the demonstration.)
                j += 1
                continue
            if delta == 0.0:
                # Exactly on the goal and still moving (only the last via-point gets here: an
                # earlier one at the state is behind it): no segment law is defined for Δ = 0.
                # Brake to rest as eq. 10 does; the last segment's law returns any overshoot.
                self._segment[d] = j
                self._returning[d] = True
                return -math.copysign(min(m, abs(v) / dt), v), abs(v) / m, MODE_WRONG_WAY
            direction = 1.0 if delta > 0.0 else -1.0
            v_along = v * direction
            dist = delta * direction  # |Δ| (Δ ≠ 0 here)
            if not last and v_n != 0.0 and v_along >= 0.0 and abs(v_n * v_n - v * v) > 4.0 * m * dist:
                # Matching this via-point's velocity would take more than 2 m (a push along the
                # motion right before it, say): pass it and aim at the next one instead.
                j += 1
                continue
            wrong_way = v_along < 0.0 and -v_along > m * dt
            v_eff = v if v_along >= 0.0 else 0.0  # a wrong-way speed below one tick of m is rest
            k_learned = k_seg[j]
            if j != j_prev:
                self._k_cap[d] = math.inf
                if self._segment_retime and not hold and not wrong_way:
                    self._retime_entry(d, j, x, v, v_eff, x_n, v_n, delta, dt)
            if self._retime_pending[d]:
                # First step of the motion: the start may lie anywhere (another start point than
                # the demonstration's). Re-solve this segment's k once so that it takes its
                # nominal duration from here, as the demonstration's did from its via-point.
                self._retime_pending[d] = False
                if self._start_retime and not hold and not wrong_way:
                    k_hi = k_limit(v_eff, v_n, delta, kappas[j])
                    if k_hi > -math.inf and durations[j] > 0.0:
                        k_new = k_for_duration(x, v_eff, x_n, v_n, durations[j], k_hi)
                        if math.isfinite(k_new):
                            self._k_start[d] = (j, k_new)
            elif self._rest_retime:
                at_rest = -vel_tol <= v <= vel_tol
                if at_rest and not self._at_rest[d] and not hold and durations[j] > 0.0:
                    # Brought to rest inside a segment (held, or pushed to a stop): from rest a
                    # segment towards a via-point at rest would crawl on the margin κ alone.
                    # Re-solve its slope so that it takes the nominal time left from here: the
                    # segment's nominal duration times the fraction of its length still ahead.
                    span = abs(offsets[j + 1] - offsets[j])
                    left = min(1.0, abs(delta) / span) if span > 0.0 else 1.0
                    k_hi = k_limit(0.0, v_n, delta, kappas[j])
                    if k_hi > -math.inf:
                        t_left = max(left * durations[j], 2.0 * dt)
                        k_new = k_for_duration(x, 0.0, x_n, v_n, t_left, k_hi)
                        if math.isfinite(k_new):
                            self._k_start[d] = (j, k_new)
                            self._k_cap[d] = math.inf
                if at_rest is not self._at_rest[d]:
                    self._at_rest[d] = at_rest
            ks = self._k_start[d]
            if ks is not None:
                if ks[0] == j:
                    k_learned = ks[1]
                else:
                    self._k_start[d] = None
            # Clamp k below the stability bound of the measured state. The clamp only tightens
            # within a segment: re-solving from each new state would otherwise ride the bound
            # and creep (the bound rises as the segment progresses).
            # (This is the hot path: k_limit and the min/max are written out with the same
            # operations in the same order, so the results are the same; Δ ≠ 0, v_eff = v when
            # it points along Δ, else 0.)
            speed_sum = (v_along if v_along >= 0.0 else 0.0) + (v_n if v_n >= 0.0 else -v_n)  # |v_eff|+|v_n|
            speed_ratio = speed_sum / delta
            k_max = speed_ratio * speed_ratio
            k_bound = K_MAX_FRACTION * k_max  # ρ k_max: the bound without the speed margin κ
            k_stable = k_bound - kappas[j]
            k_cap = self._k_cap[d]
            k_eff = k_learned  # min(k_learned, k_stable, k_cap)
            if k_stable < k_eff:
                k_eff = k_stable
            if k_cap < k_eff:
                k_eff = k_cap
            if k_eff < k_learned:
                self._k_cap[d] = k_eff
            # Keep the law within the acceleration limit where the via-point allows it: the line
            # c₀ + k (x − m) peaks at an end, so |k Δ/2| <= a_max − |c₀| bounds it on the segment.
            # (A steep learned k would otherwise saturate, miss the via-point and, at the goal,
            # cycle around it.)
            # The limit outranks the stability margin κ (a speed floor scaled to the demonstrated
            # segment: far from it, e.g. after a large goal jump, it would demand a stiff spring
            # whose law saturates and overshoots), never the bound ρ k_max itself. A state that
            # cannot reach the via-point within the limit at all (|c₀| ≥ a_max) gets k = 0: the
            # constant c₀, i.e. braking as hard as allowed, instead of a law that accelerates
            # now and would need more than the limit to stop later.
            c0 = (v_n * v_n - v_eff * v_eff) / (2.0 * delta)  # the law's mid-point acceleration
            k_room = 2.0 * (a_max - (c0 if c0 >= 0.0 else -c0)) / dist
            if k_room > 0.0:  # min(max(k_eff, −k_room), k_room, k_bound)
                if -k_room > k_eff:
                    k_eff = -k_room
                if k_room < k_eff:
                    k_eff = k_room
                if k_bound < k_eff:
                    k_eff = k_bound
            else:  # min(0, k_bound)
                k_eff = k_bound if k_bound < 0.0 else 0.0
            a_c = c0 - 0.5 * k_eff * delta  # the law's acceleration at the state
            if wrong_way:
                t_stop = -v_along / m
                x_stop = x + 0.5 * v * t_stop
                t_seg = t_stop + time_to_reach(x_stop, 0.0, x_n, v_n, k_eff)
            elif k_eff < k_max and v_n * delta >= 0.0:
                # Stable by construction (v_eff along Δ, k_eff ≤ ρ k_max) unless k_max = 0 (rest
                # to rest: k_eff may sit on the bound) or v_n points against Δ (the checked
                # closed form below decides those: it returns inf for an unstable segment).
                # psm.pstf.stable_segment_time written out, the same operations in the same
                # order (so the same t_seg, bit for bit: tests/core/test_model.py checks it),
                # reusing |Δ|, |v_eff| + |v_n| and a_c from above: ~5 % of a step at D = 7.
                t0 = 2.0 * dist / speed_sum if speed_sum > 0.0 else _INF
                k_abs = k_eff if k_eff >= 0.0 else -k_eff
                if k_eff == 0.0 or (t0 != _INF and k_abs * t0 * t0 < K_ZERO_TOL):
                    t_seg = t0  # k ≈ 0: t = 2Δ/(v_c + v_n)
                else:
                    a_n = c0 + 0.5 * k_eff * delta
                    if k_eff > 0.0:
                        w = _sqrt(k_eff)
                        p_c, q_c = a_c / w + v_eff, a_c / w - v_eff
                        ratio = (a_n / w + v_n) / p_c if abs(p_c) >= abs(q_c) else q_c / (a_n / w - v_n)
                        if not ratio > 0.0:
                            t_seg = _INF
                        else:
                            t_seg = _log(ratio) / w
                            if 0.0 > t_seg:
                                t_seg = 0.0
                    else:
                        w = _sqrt(-k_eff)
                        dtheta = (_atan2(-v_n * w, -a_n) - _atan2(-v_eff * w, -a_c)) % _TWO_PI
                        t_seg = 0.0 if dtheta > _THREE_HALVES_PI else dtheta / w
            else:
                t_seg = time_to_reach(x, v_eff, x_n, v_n, k_eff)
            if t_seg <= dt and not wrong_way:
                if last:
                    break  # terminal capture (or overshoot), decided below
                j += 1  # the via-point is reached within this tick
                continue
            break
        if j != j_prev:
            self._segment[d] = j
        self._returning[d] = last and delta * dirs[j] < 0.0
        # Capture only a state the holding spring can absorb within the acceleration limit (one
        # that arrives too fast overshoots, and the last segment's law brings it back).
        if last and (
            (-pos_tol <= delta <= pos_tol and -vel_tol <= v <= vel_tol)
            or (t_seg <= dt and 2.0 * abs(v) <= a_max * dt * 5.0)
        ):
            self._terminal[d] = True
            return self._terminal_law(x - g, v, dt, a_max), 0.0, MODE_TERMINAL
        te = t_seg + tail[j]
        stop = self._stops[d]
        if stop is not None:
            gap = stop - x
            # The stop is fixed in the world: it brakes the measured velocity (that relative to a
            # moving goal would let the axis drift through the stop at the goal's speed).
            vw = v_world
            side = self._stop_sides[d]
            on_line = gap * vw <= 0.0 and abs(gap) <= abs(vw) * dt
            if side is not None and gap * side < 0.0 and not on_line:
                # Past the stop on the obstacle's side by more than a tick of travel (pushed or
                # drifted through it, or stopped where it already was): the holding spring brings
                # the axis back to it instead of the segment's law carrying it on.
                return self._terminal_law(-gap, vw, dt, a_max), math.inf, MODE_STOP
            if 0.0 < gap * direction <= abs(delta):
                # Eq. 15: the obstacle stop lies ahead of the state, before the via-point.
                if vw * gap > 0.0:
                    a_stop = vw * vw / (2.0 * gap)
                    travel = abs(vw) * dt
                    if travel > 2.0 * abs(gap):
                        # The stop is nearer than half a tick of travel: vw² / 2 gap would turn
                        # the velocity round within the tick and grows without bound as the gap
                        # closes (a push at the stop would ask for thousands of m/s²). The
                        # smaller constant deceleration that ends the tick on the stop instead.
                        a_stop = 2.0 * (travel - abs(gap)) / (dt * dt)
                    return -math.copysign(a_stop, vw), math.inf, MODE_STOP
                # At rest, or moving back from the stop (the last braking tick's rounding, a
                # push): brought to rest, not left drifting at that velocity.
                if vw == 0.0:
                    return 0.0, math.inf, MODE_STOP
                return -math.copysign(min(m, abs(vw) / dt), vw), math.inf, MODE_STOP
            if on_line:
                # On (or a tick past) the stop line and still moving: brake to rest.
                return -math.copysign(min(m, abs(vw) / dt), vw), math.inf, MODE_STOP
        if wrong_way:
            # Eq. 10: moving away from x_n; brake at constant m until the velocity is zero.
            return m * direction, te, MODE_WRONG_WAY
        # Eq. 7 with the corrected eq. 5, solved from the measured state. The command is the
        # constant acceleration that gives the PSTF's exact velocity one tick later:
        # v(dt) = v C + a_c dt S with z = k dt² (see psm.pstf.propagate).
        z = k_eff * dt * dt
        if -1e-5 < z < 1e-5:
            c_m1 = z * (0.5 + z / 24.0)
            s_ = 1.0 + z / 6.0
        elif z > 0.0:
            r = _sqrt(z)
            c_m1 = _cosh(r) - 1.0
            s_ = _sinh(r) / r
        else:
            r = _sqrt(-z)
            c_m1 = _cos(r) - 1.0
            s_ = _sin(r) / r
        a = (v_eff * c_m1 + a_c * dt * s_) / dt + (v_eff - v) / dt
        return a, te, MODE_SEGMENT

    def _axis(self, d: int) -> tuple:
        """What :meth:`_dimension` reads of dimension ``d`` at every step, in one tuple (one
        unpacking instead of a dozen attribute and index look-ups on the hot path): the chain's
        ``k``, ``κ``, durations, hold flag and segment count, the via-point offsets and velocities
        in use, the segments' directions, the wrong-way acceleration ``m``, the acceleration limit
        and the time after each segment."""
        c = self._chains[d]
        return (c.k, c.kappa, c.durations, c.hold, self._n[d], self._offsets[d], self._vels[d],
                self._dir[d], self._m[d], self._a_max[d], self._tail[d])

    def _retime_entry(
        self, d: int, j: int, x: float, v: float, v_eff: float, x_n: float, v_n: float, delta: float,
        dt: float,
    ) -> None:
        """Segment retiming: dimension ``d`` has just entered segment ``j`` in the state ``(x, v)``.

        A slope ``k`` close to the stability bound makes a segment's duration sensitive to its
        entry state: entering a tick short of the via-point, a fraction of a percent slow, can
        stretch it by several percent. Where the entry is on the demonstrated state (the velocity
        within :data:`SEGMENT_RETIME_SPEED_FRACTION` of the segment's speed scale) but the learned
        slope would take longer or shorter than the nominal time left by more than
        :data:`SEGMENT_RETIME_TICKS` ticks and :data:`SEGMENT_RETIME_DURATION_FRACTION` of the
        duration, the slope is re-solved for that time (the nominal duration less the time since
        the via-point, at most one tick). An entry away from the via-point's state (farther from
        its position than one tick of travel plus the position tolerance: a start inside the
        chain, a skipped via-point; or at another velocity: a push) keeps the learned slope."""
        chain = self._chains[d]
        duration = chain.durations[j]
        v_j = self._vels[d][j]
        if duration <= 0.0 or abs(v - v_j) > SEGMENT_RETIME_SPEED_FRACTION * max(abs(v_j), abs(v_n)):
            return
        k_hi = k_limit(v_eff, v_n, delta, chain.kappa[j])
        if k_hi == -math.inf:
            return
        past = (x - self._goal[d] - self._offsets[d][j]) * self._dir[d][j]
        if abs(past) > max(abs(v), abs(v_j)) * dt + self._pos_tol:
            return  # not entered at its via-point (a start inside the chain, a skipped via-point)
        elapsed = min(dt, past / abs(v)) if past > 0.0 and v != 0.0 else 0.0
        t_left = max(duration - elapsed, 2.0 * dt)
        k_try = min(chain.k[j], k_hi)
        t_learned = time_to_reach(x, v_eff, x_n, v_n, k_try)
        slack = max(SEGMENT_RETIME_TICKS * dt, SEGMENT_RETIME_DURATION_FRACTION * duration)
        if abs(t_learned - t_left) <= slack:
            return
        k_new = k_for_duration(x, v_eff, x_n, v_n, t_left, k_hi, k_guess=k_try)
        if math.isfinite(k_new):
            self._k_start[d] = (j, k_new)

    def _shift_start(self, d: int, x_rel: float) -> None:
        """Start shift of dimension ``d`` started at ``x_rel`` (relative to the goal).

        The demonstration plus a displacement ``δ (1 − τ/T)`` that fades linearly over the nominal
        time ``τ`` from the demonstrated start (``δ`` = start − demonstrated start, ``T`` = nominal
        duration): via-point ``j`` moves by ``δ w_j`` (``w_j`` = nominal time left there / ``T``: 1
        at the first, 0 at the goal) and its velocity by that displacement's velocity ``−δ/T``. A
        segment the shift would reverse is collapsed to zero length (the progress rule then skips
        it); a via-point velocity that would point against one of its segments becomes 0 (as at a
        reversal), so every segment stays monotone and the PSTF's stability bound holds."""
        chain = self._chains[d]
        base = chain.offsets
        w = self._shift_weight[d]
        delta0 = x_rel - base[0]
        out = [base[i] + delta0 * w[i] for i in range(len(base))]
        out[-1] = base[-1]
        dirs = self._dir[d]
        for j in range(len(base) - 2):
            if (out[j + 1] - out[j]) * dirs[j] < 0.0:
                out[j + 1] = out[j]
        self._offsets[d] = out
        total = float(sum(chain.durations))
        dv = -delta0 / total if total > 0.0 else 0.0
        vel = list(chain.velocities)
        for i in range(1, len(vel) - 1):
            if vel[i] != 0.0:
                shifted = vel[i] + dv
                vel[i] = shifted if shifted * dirs[i - 1] > 0.0 and shifted * dirs[i] > 0.0 else 0.0
        self._vels[d] = vel
        self._axes[d] = self._axis(d)

    def _terminal_law(self, error: float, v: float, dt: float, a_max: float) -> float:
        """Critically damped hold of the goal, ``−ω² e − 2ω v`` (``ω`` = terminal_omega or
        ``0.2/dt``), limited to ``±a_max``."""
        w = self._terminal_omega if self._terminal_omega is not None else 0.2 / dt
        return max(-a_max, min(a_max, -w * w * error - 2.0 * w * v))
