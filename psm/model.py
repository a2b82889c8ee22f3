"""The Phase Space Model: learn from one demonstration, generate motion towards any goal.

>>> import numpy as np
>>> from psm import PhaseSpaceModel
>>> t = np.linspace(0.0, 2.0, 1001)                        # (T,) [s]
>>> s = 10 * (t / 2) ** 3 - 15 * (t / 2) ** 4 + 6 * (t / 2) ** 5
>>> X = np.stack([0.4 * s, 0.2 * np.sin(np.pi * s)], axis=1)  # (T, 2) [m]
>>> model = PhaseSpaceModel.fit(t, X, segments="auto", smoothing=0.02)
>>> r = model.rollout(X[0], goal=[0.5, 0.1], dt=0.002)
>>> bool(np.allclose(r.x[-1], [0.5, 0.1], atol=1e-3))
True
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from psm.controller import (
    REST_RETIME_DEFAULT,
    SEGMENT_RETIME_DEFAULT,
    DimensionChain,
    PSMController,
    validate_sync,
)
from psm.errors import ModelFileError, ParameterError, ShapeError
from psm.fitting import (
    K_FIT_MODES,
    VELOCITY_EXTREMUM_PROMINENCE,
    DimensionFit,
    RawDemo,
    check_via_point_times,
    fit_dimensions,
    fit_grid,
    smooth,
    validate_demonstration,
)

#: Identifies a saved model file; bump :data:`FORMAT_VERSION` on any incompatible change.
FORMAT_NAME = "psm-model"
#: Version 2 added the parameters ``velocity_extrema`` and ``via_point_times`` (the fit keeps
#: demonstrated states as via-points); version 1 files load as fitted without them.
FORMAT_VERSION = 2
#: The versions :meth:`PhaseSpaceModel.from_dict` reads.
READABLE_VERSIONS = (1, 2)
#: Revision of what :meth:`PhaseSpaceModel.fit` learns from given samples and options; bump it
#: with any change of the fit's result (a cache of learned models keyed on the samples and the
#: options must include it). 2: the velocity extrema join the automatic segmentation, on by
#: default.
FIT_REVISION = 2

GoalFn = Callable[[float], ArrayLike]
Disturbance = Callable[[float, NDArray[np.float64], NDArray[np.float64]], tuple[ArrayLike, ArrayLike]]


class ViaPoints(NamedTuple):
    """One dimension's via-points relative to the goal: ``position (N+1,)`` [unit] (last 0) and
    ``velocity (N+1,)`` [unit/s] (last 0)."""

    position: NDArray[np.float64]
    velocity: NDArray[np.float64]


@dataclass(frozen=True)
class ModelParameters:
    """Everything that shaped a fit and the controller's defaults (saved with the model).

    * ``smoothing``: Gaussian sigma [s]; ``segments``: as given to :meth:`PhaseSpaceModel.fit`;
    * ``auto_tolerance``: position error budget per segment in auto mode and ``hold_tolerance``:
      motion below which a dimension is a hold and a reversal is noise (so is one below 8× the
      noise the smoothing left, :func:`psm.fitting.noise_level`), both relative to the
      demonstration's largest range (:func:`psm.fitting.fit_dimensions`);
    * ``max_segments``: per dimension in auto mode; ``min_speed_ratio``: μ of the stability
      margin (:func:`psm.pstf.k_limit`);
    * ``wrong_way_accel (D,)``: ``m`` of eq. 10 [unit/s²]; ``sync_gain``: ``T`` of eq. 14 [1/s²];
    * ``position_tolerance`` [unit] and ``velocity_tolerance`` [unit/s] (absolute) for ``done``;
    * ``max_acceleration (D,)`` [unit/s²]: saturation of the segment law (default 3 ``m``);
    * ``k_fit``: how each segment's ``k`` was chosen: ``"least_squares"`` in the
      position–acceleration plane as in the paper, or ``"duration"``: the ``k`` whose closed-form
      segment time equals the demonstrated one;
    * ``sync_mode``: ``"brake"`` (the paper's eq. 14, ``−T v (t_E − t_e)``) or ``"scale"`` (time
      scaling on the demonstration's schedule, see :class:`psm.controller.PSMController`) and
      ``sync_time`` [s]: the lead at which ``"scale"`` holds a dimension still;
    * ``start_retime``: the segment the motion starts in keeps its nominal duration from any
      start; ``start_shift``: via-points are displaced by the start's offset from the demonstrated
      start, fading to nothing at the goal (see docs/psm.md, "Running");
    * ``velocity_extrema``: the significant velocity extrema of every dimension were kept as
      via-points with the unsmoothed demonstration's velocity, and ``via_point_times`` [s] the
      demonstration times of the user's via-points (see docs/psm.md, "Via-points").
    Files written before the ``sync_mode`` … ``start_shift`` parameters existed load as
    ``"brake"``, 0.1 s, off, off: they run as they did; version 1 files, before the last two, as
    fitted without velocity extrema and user via-points (as they were).
    """

    smoothing: float
    segments: str | int | list[float]
    auto_tolerance: float
    hold_tolerance: float
    max_segments: int
    min_speed_ratio: float
    wrong_way_accel: list[float]
    sync_gain: float
    position_tolerance: float
    velocity_tolerance: float
    k_fit: str = "duration"
    max_acceleration: list[float] | None = None
    sync_mode: str = "brake"
    sync_time: float = 0.1
    start_retime: bool = False
    start_shift: bool = False
    velocity_extrema: bool = False
    via_point_times: list[float] = field(default_factory=list)


@dataclass
class Rollout:
    """A generated motion: ``t (N,)`` [s], ``x, v, a (N, D)`` position, velocity and the commanded
    acceleration applied over each step (the last row repeats the previous command), ``goal (N, D)``
    the goal in force, ``done`` whether the goal was reached before ``max_duration``."""

    t: NDArray[np.float64]
    x: NDArray[np.float64]
    v: NDArray[np.float64]
    a: NDArray[np.float64]
    goal: NDArray[np.float64]
    done: bool
    segment: NDArray[np.int64] = field(repr=False, default_factory=lambda: np.zeros((0, 0), int))


class PhaseSpaceModel:
    """A learned PSM: per dimension a chain of PSTFs through via-points stored relative to the goal.

    Create with :meth:`fit` (or :meth:`load`); generate motion with :meth:`rollout` (offline) or
    :meth:`controller` (online, one acceleration per control tick).
    """

    def __init__(
        self,
        fits: Sequence[DimensionFit],
        goal: ArrayLike,
        start: ArrayLike,
        demo_duration: float,
        demo_dt: float,
        parameters: ModelParameters,
        cut_times: Sequence[Sequence[float]] | None = None,
    ) -> None:
        self._goal = np.asarray(goal, dtype=float).copy()
        self._start = np.asarray(start, dtype=float).copy()
        self._chains = [
            DimensionChain(
                offsets=tuple(float(p) for p in f.knots - f.knots[-1]),
                velocities=tuple(float(v) for v in f.velocities),
                k=tuple(float(k) for k in f.k),
                kappa=tuple(float(k) for k in f.kappa),
                durations=tuple(float(d) for d in f.durations),
                hold=bool(f.hold),
            )
            for f in fits
        ]
        self._demo_duration = float(demo_duration)
        self._demo_dt = float(demo_dt)
        self.parameters = parameters
        self._cut_times = (
            [list(map(float, c)) for c in cut_times]
            if cut_times is not None
            else [list(map(float, f.cut_indices * demo_dt)) for f in fits]
        )
        # The demonstration time left after each segment's end via-point: one clock for every
        # dimension (the "scale" synchronisation compares dimensions on it).
        self._chains = [
            replace(c, demo_tails=tuple(max(0.0, self._demo_duration - tc) for tc in ct[1:]))
            if len(ct) == len(c.k) + 1
            else c
            for c, ct in zip(self._chains, self._cut_times, strict=True)
        ]

    # ------------------------------------------------------------------ learning
    @classmethod
    def fit(
        cls,
        t: ArrayLike,
        X: ArrayLike,
        segments: str | int | Sequence[float] = "auto",
        smoothing: float = 0.02,
        *,
        auto_tolerance: float = 5e-3,
        hold_tolerance: float = 1e-3,
        max_segments: int = 24,
        min_speed_ratio: float = 0.5,
        wrong_way_accel: float | ArrayLike | None = None,
        sync_gain: float = 4.0,
        sync_mode: str = "scale",
        sync_time: float = 0.1,
        start_retime: bool = False,
        start_shift: bool = False,
        position_tolerance: float = 1e-4,
        velocity_tolerance: float = 1e-3,
        k_fit: str = "duration",
        max_acceleration: float | ArrayLike | None = None,
        velocity_extrema: bool = True,
        via_point_times: Sequence[float] | None = None,
    ) -> PhaseSpaceModel:
        """Learn a model from ONE demonstration.

        ``t (T,)`` [s] strictly increasing; ``X (T, D)`` positions [unit] (``(T,)`` for D = 1).
        ``segments``: ``"auto"`` (cut points and their number chosen to keep the position–acceleration
        fit under ``auto_tolerance``), an int N (the paper's N cuts uniform in time) or cut times [s];
        direction reversals are always cuts. ``smoothing``: Gaussian sigma [s].
        ``hold_tolerance``, ``position_tolerance`` and ``velocity_tolerance`` are relative to the
        demonstration's largest range (``position_tolerance=1e-4`` of a 0.5 m reach is 50 µm).
        ``wrong_way_accel`` (``m`` of eq. 10, per dimension) defaults to the largest |acceleration|
        demonstrated in any dimension; ``max_acceleration`` (saturation of the segment law, per
        dimension) to 3 ``m``.
        ``k_fit``: ``"duration"`` (default) gives each segment the ``k`` whose
        closed-form duration equals the demonstrated one; ``"least_squares"`` is the paper's
        least squares in the position–acceleration plane (see docs/psm.md for the comparison).
        ``sync_gain``, ``sync_mode``, ``sync_time``, ``start_retime`` and ``start_shift`` are the
        controller's defaults, stored with the model (see :class:`ModelParameters`; ``sync_mode``
        ``"brake"`` is the paper's eq. 14).
        ``velocity_extrema`` (default on): keep each dimension's significant velocity extrema
        (speed peaks and dips from which the velocity swings back by 20 % of the
        demonstration's top speed, :func:`psm.fitting.velocity_extremum_points`) as via-points;
        in ``"auto"`` mode they join the segmentation found without them (its cuts are kept,
        ``max_segments`` caps that segmentation and the task via-points come in addition);
        ``via_point_times``: demonstration times [s] from its first sample, strictly inside the
        demonstration, of via-points every moving dimension must keep (task points: where a
        tool must touch, strike or release). A user's via-point and a fast extremum (at least
        :data:`psm.fitting.RAW_VELOCITY_MIN_SPEED` of the top speed) keep the velocity of the
        unsmoothed demonstration there (:meth:`psm.fitting.RawDemo.velocity`), so that the
        motion passes those positions at the demonstrated velocities; a slower extremum keeps
        the smoothed one (docs/psm.md, "Via-points").
        Raises :class:`psm.PSMError` subclasses on invalid input.
        """
        t_arr, X_arr = validate_demonstration(t, X)
        for name, value in (
            ("auto_tolerance", auto_tolerance),
            ("hold_tolerance", hold_tolerance),
            ("min_speed_ratio", min_speed_ratio),
            ("position_tolerance", position_tolerance),
            ("velocity_tolerance", velocity_tolerance),
        ):
            if not (math.isfinite(value) and value > 0.0):
                raise ParameterError(f"{name} must be a finite number > 0, got {value}")
        if not (math.isfinite(sync_gain) and sync_gain >= 0.0):
            raise ParameterError(f"sync_gain must be a finite number >= 0, got {sync_gain}")
        validate_sync(sync_mode, sync_time)
        if k_fit not in K_FIT_MODES:
            raise ParameterError(f"k_fit must be one of {K_FIT_MODES}, got {k_fit!r}")
        if int(max_segments) < 1:
            raise ParameterError(f"max_segments must be >= 1, got {max_segments}")
        task_times = check_via_point_times(via_point_times, float(t_arr[-1]))
        demo = smooth(t_arr, X_arr, float(smoothing))
        D = X_arr.shape[1]
        scale = float(np.max(np.ptp(demo.x, axis=0)))
        if scale <= 1e-12 * float(np.max(np.abs(demo.x))):
            # Nothing moves (the smoothing's rounding is not a motion): every dimension is a hold
            # and the tolerances are taken in the demonstration's units.
            scale = 1.0
        grid = fit_grid(demo, float(smoothing))
        min_samples = max(3, round(float(smoothing) / grid.dt))
        top_speed = float(np.max(np.abs(grid.v)))  # [unit/s], over every dimension
        fits = fit_dimensions(
            grid.t, grid.x, grid.v, grid.a, grid.dt, segments,
            hold_tolerance=hold_tolerance * scale,
            auto_tolerance=auto_tolerance * scale,
            max_segments=int(max_segments),
            min_speed_ratio=float(min_speed_ratio),
            min_segment_samples=min_samples,
            k_fit=k_fit,
            raw=RawDemo(t_arr, X_arr, speed_scale=top_speed, max_window=float(smoothing)),
            extremum_tolerance=VELOCITY_EXTREMUM_PROMINENCE * top_speed if velocity_extrema else None,
            via_point_times=task_times,
        )
        if wrong_way_accel is None:
            # Isotropic: the largest |acceleration| demonstrated in any dimension. A per-dimension
            # value would make a dimension that barely moves in the demonstration (a constant
            # height, say) brake at almost nothing when pushed: it would drift for minutes.
            # Floor: 4 range / T², the least peak acceleration that covers the range in the
            # demonstrated time (never binding for a real motion; it gives a demonstration that
            # does not move at all a braking acceleration other than the smoothing's rounding).
            floor = 4.0 * scale / max(float(demo.t[-1]), demo.dt) ** 2
            m = np.full(D, max(float(np.max(np.abs(demo.a))), floor))
        else:
            m = np.broadcast_to(np.asarray(wrong_way_accel, dtype=float), (D,)).copy()
            if not np.all(np.isfinite(m) & (m > 0)):
                raise ParameterError("wrong_way_accel must be finite and > 0")
        if max_acceleration is None:
            a_max = 3.0 * m
        else:
            a_max = np.broadcast_to(np.asarray(max_acceleration, dtype=float), (D,)).copy()
            if not np.all(a_max > 0):
                raise ParameterError("max_acceleration must be > 0 (inf disables the saturation)")
        params = ModelParameters(
            smoothing=float(smoothing),
            segments=segments if isinstance(segments, str | int) else [float(s) for s in segments],
            auto_tolerance=float(auto_tolerance),
            hold_tolerance=float(hold_tolerance),
            max_segments=int(max_segments),
            min_speed_ratio=float(min_speed_ratio),
            wrong_way_accel=[float(e) for e in m],
            sync_gain=float(sync_gain),
            position_tolerance=float(position_tolerance) * scale,
            velocity_tolerance=float(velocity_tolerance) * scale,
            k_fit=k_fit,
            max_acceleration=[float(e) for e in a_max],
            sync_mode=sync_mode,
            sync_time=float(sync_time),
            start_retime=bool(start_retime),
            start_shift=bool(start_shift),
            velocity_extrema=bool(velocity_extrema),
            via_point_times=task_times,
        )
        # Goal and start are the demonstrated end points themselves (smoothing biases the ends
        # of a motion that is still settling); via-points are relative to the goal.
        return cls(
            fits,
            goal=X_arr[-1],
            start=X_arr[0],
            demo_duration=float(demo.t[-1]),
            demo_dt=demo.dt,
            parameters=params,
            cut_times=[f.cut_indices * grid.dt for f in fits],
        )

    # ------------------------------------------------------------------ properties
    @property
    def dim(self) -> int:
        """Number of dimensions D."""
        return len(self._chains)

    @property
    def goal(self) -> NDArray[np.float64]:
        """The demonstration's goal (its last position) ``(D,)`` [unit]."""
        return self._goal.copy()

    @property
    def start(self) -> NDArray[np.float64]:
        """The demonstration's start (its first position) ``(D,)`` [unit]."""
        return self._start.copy()

    @property
    def via_points(self) -> list[ViaPoints]:
        """Per dimension, the via-points relative to the goal (positions and velocities)."""
        return [ViaPoints(np.array(c.offsets), np.array(c.velocities)) for c in self._chains]

    @property
    def k(self) -> list[NDArray[np.float64]]:
        """Per dimension, the slope ``k`` of every segment ``(N_d,)`` [1/s²]."""
        return [np.array(c.k) for c in self._chains]

    @property
    def segment_durations(self) -> list[NDArray[np.float64]]:
        """Per dimension, each segment's nominal duration ``(N_d,)`` [s] (closed form, eq. 12)."""
        return [np.array(c.durations) for c in self._chains]

    @property
    def cut_times(self) -> list[list[float]]:
        """Per dimension, the demonstration times [s] of the via-points (first 0, last the end)."""
        return [list(c) for c in self._cut_times]

    @property
    def duration(self) -> float:
        """Nominal duration of the whole motion [s]: the largest per-dimension sum (eq. 13)."""
        return max(float(sum(c.durations)) for c in self._chains)

    @property
    def demo_duration(self) -> float:
        """Duration of the demonstration [s]."""
        return self._demo_duration

    @property
    def hold_dimensions(self) -> list[int]:
        """Indices of dimensions that barely move in the demonstration (rest-to-rest holds)."""
        return [d for d, c in enumerate(self._chains) if c.hold]

    def __repr__(self) -> str:
        n = [len(c.k) for c in self._chains]
        return f"PhaseSpaceModel(dim={self.dim}, segments={n}, duration={self.duration:.3f}s)"

    # ------------------------------------------------------------------ generation
    def _check_vector(self, name: str, value: ArrayLike | None, default: NDArray) -> NDArray:
        if value is None:
            return default.copy()
        arr = np.asarray(value, dtype=float).ravel()
        if arr.shape != (self.dim,):
            raise ShapeError(f"{name} must have shape ({self.dim},), got {np.shape(value)}")
        if not np.all(np.isfinite(arr)):
            raise ShapeError(f"{name} must be finite")
        return arr

    def controller(
        self,
        goal: ArrayLike | None = None,
        *,
        sync_gain: float | None = None,
        wrong_way_accel: float | ArrayLike | None = None,
        terminal_omega: float | None = None,
        sync_mode: str | None = None,
        sync_time: float | None = None,
        start_retime: bool | None = None,
        start_shift: bool | None = None,
        rest_retime: bool = REST_RETIME_DEFAULT,
        segment_retime: bool = SEGMENT_RETIME_DEFAULT,
    ) -> PSMController:
        """An online controller towards ``goal (D,)`` [unit] (default: the demonstration's goal).

        ``sync_gain``, ``sync_mode``, ``sync_time``, ``start_retime``, ``start_shift`` and
        ``wrong_way_accel`` override the model's defaults; ``terminal_omega`` [rad/s] is the
        goal-holding spring's natural frequency (default ``0.2/dt``). ``rest_retime`` (on by
        default, not a model parameter): a dimension brought to rest inside a segment (held,
        stopped by a push) re-solves that segment's slope for the nominal time left;
        ``segment_retime`` (on by default, not a model parameter): a segment entered on its
        demonstrated state but whose learned slope would run off its nominal duration re-solves
        the slope for it. See :class:`~psm.controller.PSMController`."""
        g = self._check_vector("goal", goal, self._goal)
        m = (
            np.asarray(self.parameters.wrong_way_accel)
            if wrong_way_accel is None
            else np.broadcast_to(np.asarray(wrong_way_accel, dtype=float), (self.dim,))
        )
        if not np.all(np.isfinite(m) & (m > 0)):
            raise ParameterError("wrong_way_accel must be finite and > 0")
        gain = self.parameters.sync_gain if sync_gain is None else float(sync_gain)
        if not (math.isfinite(gain) and gain >= 0.0):
            raise ParameterError(f"sync_gain must be a finite number >= 0, got {gain}")
        a_max = self.parameters.max_acceleration
        return PSMController(
            self._chains,
            g,
            m,
            gain,
            self.parameters.position_tolerance,
            self.parameters.velocity_tolerance,
            terminal_omega,
            None if a_max is None else np.asarray(a_max, dtype=float),
            sync_mode=self.parameters.sync_mode if sync_mode is None else sync_mode,
            sync_time=self.parameters.sync_time if sync_time is None else float(sync_time),
            start_retime=self.parameters.start_retime if start_retime is None else bool(start_retime),
            start_shift=self.parameters.start_shift if start_shift is None else bool(start_shift),
            rest_retime=bool(rest_retime),
            segment_retime=bool(segment_retime),
        )

    def rollout(
        self,
        x0: ArrayLike | None = None,
        v0: ArrayLike | None = None,
        goal: ArrayLike | None = None,
        dt: float = 0.002,
        max_duration: float | None = None,
        goal_fn: GoalFn | None = None,
        disturbance: Disturbance | None = None,
        *,
        sync_gain: float | None = None,
        sync_mode: str | None = None,
        sync_time: float | None = None,
        start_retime: bool | None = None,
        start_shift: bool | None = None,
        rest_retime: bool = REST_RETIME_DEFAULT,
        segment_retime: bool = SEGMENT_RETIME_DEFAULT,
    ) -> Rollout:
        """Generate a motion from ``x0 (D,)`` [unit] (default: the demonstration's start) with initial
        velocity ``v0 (D,)`` [unit/s] (default 0) towards ``goal (D,)`` (default: the demonstration's).

        Each step applies the controller's acceleration for ``dt`` [s] exactly (constant acceleration
        over the step). ``goal_fn(t) -> (D,)`` replaces the goal over time; ``disturbance(t, x, v) ->
        (x, v)`` lets a caller push the state before each control step. Stops once the goal is held
        or after ``max_duration`` [s] (default: three times the nominal duration plus one second).
        ``sync_gain``, ``sync_mode``, ``sync_time``, ``start_retime`` and ``start_shift`` override
        the model's defaults for this rollout; ``rest_retime`` and ``segment_retime`` as in
        :meth:`controller`.
        """
        x = self._check_vector("x0", x0, self._start)
        v = self._check_vector("v0", v0, np.zeros(self.dim))
        g = self._check_vector("goal", goal, self._goal)
        if not (math.isfinite(dt) and dt > 0.0):
            raise ParameterError(f"dt must be a finite number > 0, got {dt}")
        if max_duration is None:
            max_duration = 3.0 * self.duration + 1.0
        if not (math.isfinite(max_duration) and max_duration > 0.0):
            raise ParameterError(f"max_duration must be a finite number > 0, got {max_duration}")
        ctrl = self.controller(
            g,
            sync_gain=sync_gain,
            sync_mode=sync_mode,
            sync_time=sync_time,
            start_retime=start_retime,
            start_shift=start_shift,
            rest_retime=rest_retime,
            segment_retime=segment_retime,
        )
        n_max = math.ceil(max_duration / dt) + 1
        D = self.dim
        ts = np.empty(n_max)
        xs = np.empty((n_max, D))
        vs = np.empty((n_max, D))
        acc = np.zeros((n_max, D))
        goals = np.empty((n_max, D))
        segs = np.empty((n_max, D), dtype=np.int64)
        last_goal = g
        n = 0
        for i in range(n_max):
            t = i * dt
            if disturbance is not None:
                xd, vd = disturbance(t, x.copy(), v.copy())
                x = self._check_vector("disturbed x", xd, x)
                v = self._check_vector("disturbed v", vd, v)
            if goal_fn is not None:
                gi = self._check_vector("goal_fn(t)", goal_fn(t), last_goal)
                if not np.array_equal(gi, last_goal):
                    ctrl.set_goal(gi)
                    last_goal = gi
            a = ctrl.step(x, v, dt)
            ts[i], xs[i], vs[i], acc[i], goals[i] = t, x, v, a, last_goal
            segs[i] = ctrl.segment
            n = i + 1
            if ctrl.done:
                break
            x = x + v * dt + 0.5 * a * dt * dt
            v = v + a * dt
        return Rollout(
            t=ts[:n],
            x=xs[:n],
            v=vs[:n],
            a=acc[:n],
            goal=goals[:n],
            done=ctrl.done,
            segment=segs[:n],
        )

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """The model as a JSON-ready dict (format :data:`FORMAT_NAME`, version :data:`FORMAT_VERSION`)."""
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "dim": self.dim,
            "goal": self._goal.tolist(),
            "start": self._start.tolist(),
            "demo_duration": self._demo_duration,
            "demo_dt": self._demo_dt,
            "parameters": asdict(self.parameters),
            "dimensions": [
                {
                    "offsets": list(c.offsets),
                    "velocities": list(c.velocities),
                    "k": list(c.k),
                    "kappa": list(c.kappa),
                    "durations": list(c.durations),
                    "hold": c.hold,
                    "cut_times": self._cut_times[d],
                }
                for d, c in enumerate(self._chains)
            ],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PhaseSpaceModel:
        """Rebuild a model from :meth:`to_dict` output; raises :class:`ModelFileError` when invalid."""
        if not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
            raise ModelFileError(f"not a PSM model (expected format '{FORMAT_NAME}')")
        if data.get("version") not in READABLE_VERSIONS:
            raise ModelFileError(
                f"unsupported model version {data.get('version')!r} (this build reads "
                f"{', '.join(map(str, READABLE_VERSIONS))})"
            )
        try:
            dims = data["dimensions"]
            fits = []
            for d, item in enumerate(dims):
                offsets = np.asarray(item["offsets"], dtype=float)
                k = np.asarray(item["k"], dtype=float)
                if offsets.shape != (k.size + 1,) or k.size == 0:
                    raise ModelFileError(f"dimensions[{d}]: offsets must have len(k) + 1 entries")
                fits.append(
                    DimensionFit(
                        knots=offsets,
                        velocities=np.asarray(item["velocities"], dtype=float),
                        k=k,
                        kappa=np.asarray(item["kappa"], dtype=float),
                        durations=np.asarray(item["durations"], dtype=float),
                        cut_indices=np.zeros(k.size + 1, dtype=np.int64),
                        hold=bool(item["hold"]),
                    )
                )
            goal = np.asarray(data["goal"], dtype=float)
            if goal.shape != (len(fits),):
                raise ModelFileError(f"goal has {goal.size} entries for {len(fits)} dimensions")
            params = ModelParameters(**data["parameters"])
            model = cls(
                fits,
                goal=goal,
                start=data["start"],
                demo_duration=data["demo_duration"],
                demo_dt=data["demo_dt"],
                parameters=params,
                cut_times=[item["cut_times"] for item in dims],
            )
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"invalid model file: {type(exc).__name__}: {exc}") from None
        return model

    def save(self, path: str | Path) -> None:
        """Write the model as JSON to ``path`` (exact round trip through :meth:`load`)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> PhaseSpaceModel:
        """Read a model written by :meth:`save`; raises :class:`ModelFileError` when invalid."""
        try:
            data = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise ModelFileError(f"{path}: not valid JSON ({exc})") from None
        return cls.from_dict(data)
