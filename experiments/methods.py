"""PSM and movement_primitives DMPs side by side: fitted on one demonstration, rolled out at its dt,
under the same perturbations (used by :mod:`experiments.cylinder` and :mod:`experiments.robustness`).

Fitting is the learner benchmark's (:func:`benchmarks.learner.fit_psm` with the library defaults,
:func:`benchmarks.learner.fit_dmp`: execution time = the demonstration's duration, step = its dt,
the library's default gains). Rollouts are Cartesian point masses, as in that benchmark: the PSM
through ``PhaseSpaceModel.rollout`` (:func:`benchmarks.learner.run_psm`), a DMP stepped with its own
``step`` (:func:`rollout_dmp`; the ``rk4-cython`` step of ``DMP``, the Euler step of
``DMPWithFinalVelocity``), so a perturbation can act on its state between steps exactly as the
PSM rollout's ``disturbance`` does: ``disturbance(t, x, v) -> (x, v)`` before each step, and
``goal_fn(t) -> goal``.

Methods (:data:`METHODS`):

* ``psm`` -- ``PhaseSpaceModel.fit(t, X)`` and ``rollout`` defaults (each dimension's speed
  peaks and dips kept as via-points; a dimension brought to rest inside a segment goes on at its
  nominal pace);
* ``psm_before`` -- the defaults before 2026-12-03: ``velocity_extrema=False`` and the
  controller's ``rest_retime=False`` (the before/after of that change);
* ``dmp10`` / ``dmp50`` -- ``movement_primitives.dmp.DMP`` with 10 / 50 weights per dimension;
* ``dmp50_scaled`` -- DMP-50 with its forcing term scaled per dimension by
  ``(g - x₀) / (g_demo - x₀_demo)``, the amplitude scaling of the original DMP formulation
  (Ijspeert et al.): a start closer to the goal gives a smaller, slower motion. A dimension that
  barely moves in the demonstration (``|g_demo - x₀_demo| < 1 cm`` or 1 % of the largest
  range) is not scaled (the formulation is singular there);
* ``dmp_fv`` -- ``movement_primitives.dmp.DMPWithFinalVelocity`` (50 weights) on the whole
  demonstration (it ends at rest, so its final velocity is 0);
* ``dmp_fv_strike`` -- ``DMPWithFinalVelocity`` (50 weights) on the demonstration up to its speed
  peak, so its goal is the strike: the peak's position with the peak's velocity. After its
  execution time it brakes at the constant deceleration that stops it where the demonstration
  stops (the distance to the demonstrated goal along its velocity), as a robot must stop after
  a strike.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from benchmarks.learner import Demo, Run, fit_dmp, fit_psm, run_psm

__all__ = [
    "DEMO_DIR",
    "METHODS",
    "PSM_KEYS",
    "Hold",
    "Method",
    "PushAgainstMotion",
    "fit_method",
    "load_arm_demo",
    "rollout_dmp",
    "run_method",
    "write_tracks_mcap",
]

FloatArray = NDArray[np.float64]
Disturbance = Callable[[float, FloatArray, FloatArray], tuple[FloatArray, FloatArray]]
GoalFn = Callable[[float], FloatArray]

DEMO_DIR = Path(__file__).resolve().parents[1] / "data" / "demos"


@dataclass(frozen=True)
class Method:
    """A learner: ``key``, printed ``label``, plot ``color``."""

    key: str
    label: str
    color: str


METHODS: dict[str, Method] = {
    m.key: m
    for m in (
        Method("psm", "PSM", "tab:blue"),
        Method("psm_before", "PSM-before", "tab:cyan"),
        Method("dmp10", "DMP-10", "tab:orange"),
        Method("dmp50", "DMP-50", "tab:red"),
        Method("dmp50_scaled", "DMP-50 f·(g−x₀)", "tab:brown"),
        Method("dmp_fv", "DMP-FV", "tab:green"),
        Method("dmp_fv_strike", "DMP-FV to the strike", "tab:purple"),
    )
}
#: The PSM methods of :data:`METHODS` (rolled out by ``PhaseSpaceModel.rollout``).
PSM_KEYS = ("psm", "psm_before")
DMP_FV_WEIGHTS = 50
#: A demonstrated dimension moving less than this [unit] (or 1 % of the largest range) is not
#: amplitude-scaled by ``dmp50_scaled``.
SCALE_MIN_AMPLITUDE = 0.01


def load_arm_demo(name: str) -> Demo:
    """The end-effector path of ``data/demos/<name>.mcap`` by forward kinematics: ``t (T,)`` [s],
    ``x (T, 3)`` [m] (base frame)."""
    from services.robot.recordings import ee_trajectory

    t, x = ee_trajectory(DEMO_DIR / f"{name}.mcap")
    return Demo(t=np.asarray(t, float), x=np.asarray(x, float))


@dataclass
class _Fitted:
    """A fitted learner with what its rollout needs."""

    key: str
    model: Any
    demo: Demo
    extra: dict[str, Any]


def fit_method(key: str, demo: Demo) -> _Fitted:
    """Fit method ``key`` of :data:`METHODS` on ``demo``."""
    if key == "psm":
        return _Fitted(key, fit_psm(demo), demo, {})
    if key == "psm_before":
        return _Fitted(key, fit_psm(demo, velocity_extrema=False), demo, {})
    if key in ("dmp10", "dmp50", "dmp50_scaled"):
        return _Fitted(key, fit_dmp(demo, 10 if key == "dmp10" else 50), demo, {})
    if key in ("dmp_fv", "dmp_fv_strike"):
        from movement_primitives.dmp import DMPWithFinalVelocity

        t, x = demo.t, demo.x
        extra: dict[str, Any] = {}
        if key == "dmp_fv_strike":
            speed = np.linalg.norm(np.gradient(x, t, axis=0), axis=1)
            k = int(np.argmax(speed))
            extra = {"strike_index": k, "strike_time": float(t[k])}
            t, x = t[: k + 1], x[: k + 1]
        dmp = DMPWithFinalVelocity(
            n_dims=x.shape[1],
            execution_time=float(t[-1] - t[0]),
            dt=demo.dt,
            n_weights_per_dim=DMP_FV_WEIGHTS,
        )
        dmp.imitate(t, x)
        return _Fitted(key, dmp, demo, extra)
    raise ValueError(f"unknown method {key!r}; known: {', '.join(METHODS)}")


def rollout_dmp(
    dmp: Any,
    x0: FloatArray,
    dt: float,
    duration: float,
    goal: FloatArray | None = None,
    disturbance: Disturbance | None = None,
    goal_fn: GoalFn | None = None,
) -> Run:
    """Step a fitted DMP from rest at ``x0 (D,)`` for ``duration`` [s] at ``dt`` [s] (the DMP's own
    ``dt_`` is set to it) towards ``goal`` (default: the learned one). Before each step
    ``disturbance(t, x, v)`` may change the state and ``goal_fn(t)`` the goal (the DMP is
    re-configured with it when it changes). Returns positions and velocities at ``t = i dt``.

    From the DMP's execution time on, its forcing term is off (a copy of the DMP runs with zero
    weights): in the DMP's formulation the forcing term vanishes with the phase and the
    spring-damper alone holds the goal, but movement_primitives normalises the basis functions, so
    past the last centre it keeps ``z·w_last`` (the largest weight, fitted where ``z = 0.01``),
    and the state drifts off the goal (DMP-50 on the cylinder strike: 13 cm within 1 s).
    """
    from movement_primitives.dmp import DMP

    x0 = np.asarray(x0, float).copy()
    dmp = copy.deepcopy(dmp)
    tau = float(dmp.execution_time_)
    dmp.dt_ = dt
    dmp.configure(start_y=x0.copy(), start_yd=np.zeros_like(x0))
    if goal is not None:
        dmp.configure(goal_y=np.asarray(goal, float).copy())
    dmp.reset()
    dmp.initialized = True
    def step(y: FloatArray, yd: FloatArray) -> tuple[FloatArray, FloatArray]:
        if isinstance(dmp, DMP):
            return dmp.step(y, yd, step_function="rk4-cython")
        return dmp.step(y, yd)

    n = math.floor(duration / dt + 1e-9) + 1
    ts = np.arange(n) * dt
    xs = np.empty((n, len(x0)))
    vs = np.empty((n, len(x0)))
    x, v = x0.copy(), np.zeros_like(x0)
    last_goal = np.array(dmp.goal_y, float)
    for i in range(n):
        t = float(ts[i])
        if disturbance is not None:
            x, v = disturbance(t, x.copy(), v.copy())
            dmp.current_y[:] = x
            dmp.current_yd[:] = v
        if goal_fn is not None:
            g = np.asarray(goal_fn(t), float)
            if not np.array_equal(g, last_goal):
                dmp.configure(goal_y=g.copy())
                last_goal = g
        xs[i], vs[i] = x, v
        if t + dt > tau + 1e-9 and np.any(dmp.forcing_term.weights_):
            dmp.forcing_term.weights_ = np.zeros_like(dmp.forcing_term.weights_)
        if i + 1 < n:
            x, v = step(x, v)
    return Run(t=ts, x=xs, done=False, wall_s=0.0, v=vs)


def _brake(run: Run, goal: FloatArray, dt: float, max_duration: float) -> Run:
    """``run`` continued from its last state at the constant deceleration along its velocity that
    stops it after the distance to ``goal`` along that velocity (at most until ``max_duration``)."""
    x1, v1 = run.x[-1], run.v[-1] if run.v is not None else np.zeros_like(run.x[-1])
    speed = float(np.linalg.norm(v1))
    if speed < 1e-9:
        return run
    u = v1 / speed
    dist = max(float(np.dot(goal - x1, u)), 1e-3)
    b = speed * speed / (2.0 * dist)
    t_stop = speed / b
    n = int(min(t_stop, max(max_duration - run.t[-1], 0.0)) / dt)
    tau = np.arange(1, n + 1) * dt
    s = np.minimum(tau, t_stop)
    xb = x1 + np.outer(speed * s - 0.5 * b * s * s, u)
    vb = np.outer(np.maximum(speed - b * tau, 0.0), u)
    return Run(
        t=np.concatenate([run.t, run.t[-1] + tau]),
        x=np.vstack([run.x, xb]),
        done=False,
        wall_s=run.wall_s,
        v=np.vstack([run.v, vb]) if run.v is not None else None,
    )


def run_method(
    fitted: _Fitted,
    x0: FloatArray,
    duration: float,
    goal: FloatArray | None = None,
    disturbance: Disturbance | None = None,
    goal_fn: GoalFn | None = None,
) -> Run:
    """Roll ``fitted`` out from rest at ``x0 (D,)`` at the demonstration's dt for up to
    ``duration`` [s] (a PSM stops earlier once it holds its goal), towards ``goal`` (default:
    the demonstrated one), with the optional ``disturbance`` / ``goal_fn`` (see the module
    docstring). Returns ``t (N,)`` [s], ``x (N, D)``, ``v (N, D)``."""
    import time

    dt = fitted.demo.dt
    t0 = time.perf_counter()
    x0 = np.asarray(x0, float)
    if fitted.key in PSM_KEYS:
        opts: dict[str, Any] = {}
        if disturbance is not None:
            opts["disturbance"] = disturbance
        if fitted.key == "psm_before":
            opts["rest_retime"] = False
        if goal_fn is not None:
            opts["goal_fn"] = goal_fn
        elif goal is not None:
            g = np.asarray(goal, float)
            opts["goal_fn"] = lambda _t: g
        return run_psm(fitted.model, x0, dt, duration, **opts)
    dmp = fitted.model
    if fitted.key == "dmp50_scaled":
        dmp = _amplitude_scaled(dmp, fitted.demo, x0, goal)
    if fitted.key == "dmp_fv_strike":
        t_strike = float(fitted.extra["strike_time"])
        run = rollout_dmp(dmp, x0, dt, min(t_strike, duration), None, disturbance, None)
        run = _brake(run, fitted.demo.x[-1] if goal is None else np.asarray(goal, float), dt, duration)
    elif fitted.key == "dmp_fv":
        # Past its execution time the final-velocity constraint has no goal trajectory: it stops
        # there (at rest on the goal when undisturbed) and is braked to rest if still moving.
        tau = float(dmp.execution_time_)
        run = rollout_dmp(dmp, x0, dt, min(tau, duration), goal, disturbance, goal_fn)
        run = _brake(run, fitted.demo.x[-1] if goal is None else np.asarray(goal, float), dt, duration)
    else:
        run = rollout_dmp(dmp, x0, dt, duration, goal, disturbance, goal_fn)
    run.wall_s = time.perf_counter() - t0
    return run


def _amplitude_scaled(dmp: Any, demo: Demo, x0: FloatArray, goal: FloatArray | None) -> Any:
    """A copy of ``dmp`` whose forcing weights are scaled per dimension by
    ``(g - x₀) / (g_demo - x₀_demo)`` (dimensions that barely move in the demo: 1)."""
    g = demo.x[-1] if goal is None else np.asarray(goal, float)
    amp_demo = demo.x[-1] - demo.x[0]
    floor = max(SCALE_MIN_AMPLITUDE, 0.01 * float(np.ptp(demo.x, axis=0).max()))
    scale = np.where(np.abs(amp_demo) >= floor, (g - x0) / np.where(amp_demo == 0, 1.0, amp_demo), 1.0)
    out = copy.deepcopy(dmp)
    out.forcing_term.weights_ = out.forcing_term.weights_ * scale[:, None]
    return out


class Hold:
    """The motion held still (``v = 0`` at the position reached) for ``duration`` [s] from ``t0``
    [s]: someone stops the arm; the learner's clock runs on."""

    def __init__(self, t0: float, duration: float) -> None:
        self.t0, self.t1 = t0, t0 + duration
        self._x: FloatArray | None = None

    def __call__(self, t: float, x: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        if self.t0 <= t < self.t1:
            if self._x is None:
                self._x = x.copy()
            return self._x.copy(), np.zeros_like(v)
        return x, v


class PushAgainstMotion:
    """A push against the motion: from ``t0`` [s] for ``duration`` [s] a constant acceleration
    against the velocity at ``t0`` (its direction then), totalling ``delta_v`` [unit/s] of
    velocity change (``delta_v / duration`` per second, applied step by step)."""

    def __init__(self, t0: float, duration: float, delta_v: float) -> None:
        self.t0, self.duration, self.delta_v = t0, duration, delta_v
        self._u: FloatArray | None = None
        self._last_t: float | None = None

    def __call__(self, t: float, x: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        # Each call adds the push over the part of the window since the previous call.
        last, self._last_t = self._last_t, t
        t1 = self.t0 + self.duration
        if last is None or t <= self.t0 or last >= t1:
            return x, v
        if self._u is None:
            speed = float(np.linalg.norm(v))
            self._u = -v / speed if speed > 0 else np.zeros_like(v)
        span = min(t, t1) - max(last, self.t0)
        return x, v + self._u * (self.delta_v / self.duration) * span


def write_tracks_mcap(
    path: Path,
    tracks: dict[str, tuple[FloatArray, FloatArray]],
    metadata: dict[str, str],
    rate_hz: float = 50.0,
) -> Path:
    """Write position tracks as ``foxglove.PoseInFrame`` (frame ``base``, identity orientation)
    with the recorder's MCAP sink: ``tracks[key] = (t (N,) [s], x (N, 3) [m])``, one channel per
    key, at most ``rate_hz`` samples per second, log time = the track's time."""
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    from services.bus.messages import encode
    from services.bus.recorder import McapSink

    sink = McapSink(path, overwrite=True, metadata=metadata, library="psm-dataflow experiments")
    try:
        for key, (t, x) in tracks.items():
            step = max(1, round(1.0 / (rate_hz * max(float(np.median(np.diff(t))), 1e-9))))
            idx = list(range(0, len(t), step))
            if idx[-1] != len(t) - 1:
                idx.append(len(t) - 1)
            for i in idx:
                ns = round(float(t[i]) * 1e9)
                msg = PoseInFrame(frame_id="base")
                msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)
                p = msg.pose.position
                p.x, p.y, p.z = (
                    (float(c) for c in x[i][:3])
                    if len(x[i]) >= 3
                    else (float(x[i][0]), float(x[i][1]) if len(x[i]) > 1 else 0.0, 0.0)
                )
                msg.pose.orientation.w = 1.0
                payload, encoding = encode(msg)
                sink.write(key, encoding, payload, ns)
    finally:
        sink.close()
    return path
