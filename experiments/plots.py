"""The plots of the experiments and of ``psm report``: functions of arrays, written as PNG.

Every plot has a ``*_figure`` function that builds a :class:`matplotlib.figure.Figure` from arrays
(no pyplot, no global state: safe in threads and in tests, which inspect the drawn lines) and a
``plot_*`` function that writes it to a PNG file (Agg, :data:`DPI`) and returns the path::

    from experiments import plots
    plots.plot_trajectories(out / "traj.png", [plots.Curve("run", t, X), plots.Curve("demo", td, Xd)])
    lines = plots.pstf_lines(model)                       # the model's segments (Fig. 3)
    plots.plot_phase_space(out / "phase.png", [plots.PhaseCurve("demo", x, v, a)], lines)
    plots.plot_time_to_go(out / "sync.png", t, plots.time_to_go_along(model, x, v, dt, goal))

What each shows (the paper's figures in parentheses):

* :func:`trajectories_figure` -- each dimension over time, a run against its demonstration;
* :func:`path_figure` -- the 3-D path and its top view (x--y);
* :func:`phase_space_figure` -- position--velocity and position--acceleration per dimension, with
  the PSTF of every segment drawn as its line ``a = c0 + k (x - m)`` over ``[x_c, x_n]`` (Fig. 3);
* :func:`time_to_go_figure` -- each dimension's time to completion ``t_e`` over time and its lag
  behind the slowest one, ``t_E - t_e``, converging together (Fig. 5, the synchronisation);
* :func:`cylinder_phase_figure` -- position--velocity of the strike dimension, one panel per method,
  several starts each, with the demonstration and the contact position (Fig. 10).

Units are given by the caller (``unit``, default m) and appear in every axis label.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "DPI",
    "Curve",
    "PSTFLine",
    "PhaseCurve",
    "cylinder_phase_figure",
    "path_figure",
    "phase_space_figure",
    "plot_cylinder_phase",
    "plot_path",
    "plot_phase_space",
    "plot_time_to_go",
    "plot_trajectories",
    "pstf_lines",
    "save_figure",
    "time_to_go_along",
    "time_to_go_figure",
    "trajectories_figure",
]

#: Resolution of every PNG [dots per inch].
DPI = 120
DIMS = ("x", "y", "z")
#: The colour of each dimension (x red, y blue, z green, as in the paper's Fig. 5).
DIM_COLOURS = ("C3", "C0", "C2", "C1", "C4", "C5")


@dataclass(frozen=True)
class Curve:
    """A trajectory: ``t (T,)`` [s], ``x (T, D)`` [unit]; ``style``: matplotlib line options."""

    label: str
    t: ArrayLike
    x: ArrayLike
    style: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PhaseCurve:
    """A phase-space curve: positions ``x (T, D)`` [unit], velocities ``v (T, D)`` [unit/s] and
    accelerations ``a (T, D)`` [unit/s²] (either may be None: that panel row is left out for it)."""

    label: str
    x: ArrayLike
    v: ArrayLike | None = None
    a: ArrayLike | None = None
    style: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PSTFLine:
    """One segment's PSTF in the position--acceleration plane: ``a = c0 + k (x - m)`` for ``x``
    from ``x_c`` to ``x_n`` [unit], with ``c0 = (v_n² - v_c²)/(2Δ)`` [unit/s²], ``m = (x_c + x_n)/2``,
    ``k`` [1/s²]; ``v_c``, ``v_n`` [unit/s] are the via-point velocities at its two ends."""

    x_c: float
    x_n: float
    v_c: float
    v_n: float
    k: float

    @property
    def c0(self) -> float:
        """The acceleration at the segment's mid-point [unit/s²]."""
        return (self.v_n**2 - self.v_c**2) / (2.0 * (self.x_n - self.x_c))

    @property
    def m(self) -> float:
        """The segment's mid-point [unit]."""
        return 0.5 * (self.x_c + self.x_n)

    def acceleration(self, x: ArrayLike) -> NDArray[np.float64]:
        """The PSTF's acceleration at positions ``x`` [unit/s²]."""
        return self.c0 + self.k * (np.asarray(x, dtype=float) - self.m)


def pstf_lines(model: Any, goal: ArrayLike | None = None) -> list[list[PSTFLine]]:
    """Per dimension, the PSTF line of every segment of ``model`` (a
    :class:`psm.PhaseSpaceModel`), with the goal-relative via-points placed at ``goal (D,)``
    (default: the demonstration's goal; zeros give goal-relative positions). Segments of zero
    length (a dimension that does not move at all) have no line and are left out."""
    g = np.asarray(model.goal if goal is None else goal, dtype=float).ravel()
    out: list[list[PSTFLine]] = []
    for d, (vp, k) in enumerate(zip(model.via_points, model.k, strict=True)):
        pos = g[d] + vp.position
        lines = [
            PSTFLine(float(pos[j]), float(pos[j + 1]), float(vp.velocity[j]), float(vp.velocity[j + 1]),
                     float(k[j]))
            for j in range(len(k))
            if pos[j + 1] != pos[j]
        ]
        out.append(lines)
    return out


def time_to_go_along(
    model: Any,
    x: ArrayLike,
    v: ArrayLike,
    dt: float | ArrayLike,
    goal: ArrayLike,
    **controller_options: Any,
) -> NDArray[np.float64]:
    """The controller's time to completion ``t_e`` along given states: a fresh
    ``model.controller(goal[0], **controller_options)`` is stepped on each state ``x, v (T, D)``
    [unit, unit/s] with period ``dt`` [s] (scalar or ``(T,)``); ``goal`` is ``(D,)`` or the goal
    in force at each state ``(T, D)`` (a row of NaN: the goal was unknown there, the controller is
    not stepped and ``t_e`` is NaN). Returns ``(T, D)`` [s], each row as of after that state's step."""
    X, V = np.atleast_2d(np.asarray(x, dtype=float)), np.atleast_2d(np.asarray(v, dtype=float))
    T, D = X.shape
    G = np.asarray(goal, dtype=float)
    G = np.broadcast_to(G, (T, D)) if G.ndim == 1 else G
    dts = np.broadcast_to(np.asarray(dt, dtype=float), (T,))
    out = np.full((T, D), np.nan)
    ctrl = None
    current: NDArray[np.float64] | None = None
    for i in range(T):
        if not np.all(np.isfinite(G[i])):
            continue
        if ctrl is None:
            ctrl = model.controller(G[i], **controller_options)
            current = G[i].copy()
        elif not np.array_equal(G[i], current):
            ctrl.set_goal(G[i])
            current = G[i].copy()
        ctrl.step(X[i], V[i], float(dts[i]))
        out[i] = ctrl.time_to_go
    return out


# ---------------------------------------------------------------------------------------- helpers
def _new_figure(width: float, height: float) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def save_figure(fig: Any, path: str | Path, dpi: int = DPI) -> Path:
    """Write ``fig`` as PNG to ``path`` (folders created); returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, format="png")
    return out


def _as_2d(a: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(a, dtype=float)
    return arr[:, None] if arr.ndim == 1 else arr


def _dim_names(D: int, dims: Sequence[str] | None) -> list[str]:
    names = list(dims) if dims is not None else list(DIMS[:D]) + [f"x{d}" for d in range(3, D)]
    if len(names) < D:
        raise ValueError(f"{D} dimensions but only {len(names)} names: {names}")
    return names[:D]


def _marks(ax: Any, marks: Mapping[str, float] | None, label: bool = True) -> None:
    for j, (name, when) in enumerate((marks or {}).items()):
        ax.axvline(float(when), color=f"C{(j + 5) % 10}", ls="-.", lw=1.0, label=name if label else None)


def _style(curve_style: Mapping[str, Any], i: int) -> dict[str, Any]:
    style = {"lw": 1.4, "color": f"C{i % 10}"}
    style.update(curve_style)
    return style


# ---------------------------------------------------------------------------------------- figures
def trajectories_figure(
    curves: Sequence[Curve],
    *,
    dims: Sequence[str] | None = None,
    unit: str = "m",
    title: str = "",
    goal: ArrayLike | None = None,
    marks: Mapping[str, float] | None = None,
) -> Any:
    """Each dimension over time (one panel per dimension, stacked): every curve's ``x[:, d]``
    against its ``t``; ``goal (D,)`` (optional) as a dotted line; ``marks``: labelled times [s]
    as vertical lines."""
    if not curves:
        raise ValueError("no curve to plot")
    D = _as_2d(curves[0].x).shape[1]
    names = _dim_names(D, dims)
    fig = _new_figure(7.0, 1.9 * D + 0.8)
    axes = fig.subplots(D, 1, sharex=True, squeeze=False)[:, 0]
    for i, c in enumerate(curves):
        X = _as_2d(c.x)
        t = np.asarray(c.t, dtype=float)
        for d in range(D):
            axes[d].plot(t, X[:, d], label=c.label, **_style(c.style, i))
    for d in range(D):
        if goal is not None:
            axes[d].axhline(float(np.asarray(goal, dtype=float).ravel()[d]), color="0.4", ls=":", lw=1.0,
                            label="goal")
        _marks(axes[d], marks, label=d == 0)
        axes[d].set_ylabel(f"{names[d]} [{unit}]")
        axes[d].grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def path_figure(
    curves: Sequence[Curve],
    *,
    dims: Sequence[str] | None = None,
    unit: str = "m",
    title: str = "",
    points: Mapping[str, ArrayLike] | None = None,
) -> Any:
    """The path in space: 3-D (for D ≥ 3) and the top view (first two dimensions); ``points``:
    labelled positions ``(D,)`` to mark (goals, start)."""
    if not curves:
        raise ValueError("no curve to plot")
    D = _as_2d(curves[0].x).shape[1]
    if D < 2:
        raise ValueError("a path needs at least 2 dimensions")
    names = _dim_names(D, dims)
    fig = _new_figure(10.0 if D >= 3 else 5.5, 4.6)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d") if D >= 3 else None
    ax2 = fig.add_subplot(1, 2, 2) if D >= 3 else fig.add_subplot(1, 1, 1)
    for i, c in enumerate(curves):
        X = _as_2d(c.x)
        st = _style(c.style, i)
        if ax3 is not None:
            ax3.plot(X[:, 0], X[:, 1], X[:, 2], label=c.label, **st)
        ax2.plot(X[:, 0], X[:, 1], label=c.label, **st)
    for j, (label, p) in enumerate((points or {}).items()):
        q = np.asarray(p, dtype=float).ravel()
        marker = "*osD^v"[j % 6]
        if ax3 is not None:
            ax3.scatter([q[0]], [q[1]], [q[2]], marker=marker, s=60, color="k", label=label)
        ax2.scatter([q[0]], [q[1]], marker=marker, s=60, color="k", label=label)
    if ax3 is not None:
        ax3.set_xlabel(f"{names[0]} [{unit}]")
        ax3.set_ylabel(f"{names[1]} [{unit}]")
        ax3.set_zlabel(f"{names[2]} [{unit}]")
        ax3.set_title("3-D path", fontsize=9)
    ax2.set_xlabel(f"{names[0]} [{unit}]")
    ax2.set_ylabel(f"{names[1]} [{unit}]")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_title(f"top view ({names[0]}–{names[1]})", fontsize=9)
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def phase_space_figure(
    curves: Sequence[PhaseCurve],
    lines: Sequence[Sequence[PSTFLine]] | None = None,
    *,
    dims: Sequence[str] | None = None,
    unit: str = "m",
    title: str = "",
) -> Any:
    """Per dimension (columns): position--velocity (top row) and position--acceleration (bottom
    row). ``lines[d]``: the PSTF lines of dimension ``d`` (:func:`pstf_lines`), drawn on the
    acceleration row over each segment's interval, with their via-points ``(x, v)`` marked on the
    velocity row. Each drawn PSTF line carries the ``gid`` ``"pstf-<d>-<j>"`` (segment ``j``)."""
    if not curves:
        raise ValueError("no curve to plot")
    D = _as_2d(curves[0].x).shape[1]
    names = _dim_names(D, dims)
    fig = _new_figure(3.6 * D + 0.6, 6.4)
    axes = fig.subplots(2, D, squeeze=False)
    for i, c in enumerate(curves):
        X = _as_2d(c.x)
        st = _style(c.style, i)
        for d in range(D):
            if c.v is not None:
                axes[0, d].plot(X[:, d], _as_2d(c.v)[:, d], label=c.label, **st)
            if c.a is not None:
                axes[1, d].plot(X[:, d], _as_2d(c.a)[:, d], label=c.label, **st)
    for d in range(D):
        for j, ln in enumerate(lines[d] if lines is not None and d < len(lines) else []):
            xs = np.array([ln.x_c, ln.x_n])
            axes[1, d].plot(xs, ln.acceleration(xs), color="C1", lw=2.2, alpha=0.85, gid=f"pstf-{d}-{j}",
                            label="PSTF per segment" if j == 0 else None)
            axes[0, d].plot(xs, [ln.v_c, ln.v_n], "o", color="C1", ms=3.5,
                            label="via-points" if j == 0 else None)
        axes[0, d].set_title(names[d], fontsize=10)
        axes[0, d].set_xlabel(f"{names[d]} [{unit}]")
        axes[0, d].set_ylabel(f"velocity [{unit}/s]")
        axes[1, d].set_xlabel(f"{names[d]} [{unit}]")
        axes[1, d].set_ylabel(f"acceleration [{unit}/s²]")
        for ax in axes[:, d]:
            ax.grid(alpha=0.3)
            ax.axhline(0.0, color="0.6", lw=0.6)
    axes[0, 0].legend(fontsize=7, loc="best")
    axes[1, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def time_to_go_figure(
    t: ArrayLike,
    time_to_go: ArrayLike,
    *,
    dims: Sequence[str] | None = None,
    recorded: tuple[ArrayLike, ArrayLike] | None = None,
    marks: Mapping[str, float] | None = None,
    title: str = "",
) -> Any:
    """The synchronisation: each dimension's time to completion ``t_e (T, D)`` [s] over ``t (T,)``
    [s] (top) and its lag behind the slowest dimension, ``t_E - t_e`` with ``t_E = max_d t_e``
    (bottom), which the synchronisation drives to zero. ``recorded = (t_s (S,), t_e (S, D))``:
    values reported by the running controller, drawn as markers over the lines. ``marks``:
    labelled times [s] drawn as vertical lines (e.g. when the goal was reached)."""
    tt = np.asarray(t, dtype=float)
    te = _as_2d(time_to_go)
    D = te.shape[1]
    names = _dim_names(D, dims)
    fig = _new_figure(7.0, 5.6)
    ax_te, ax_lag = fig.subplots(2, 1, sharex=True)
    finite = np.where(np.isfinite(te), te, -np.inf)
    t_E = finite.max(axis=1) if te.size else np.zeros(0)
    t_E = np.where(np.isfinite(t_E), t_E, np.nan)  # no dimension known at that time
    for d in range(D):
        col = DIM_COLOURS[d % len(DIM_COLOURS)]
        ax_te.plot(tt, te[:, d], color=col, lw=1.4, label=f"{names[d]}")
        ax_lag.plot(tt, t_E - te[:, d], color=col, lw=1.4, label=f"{names[d]}")
    if recorded is not None:
        ts, tes = np.asarray(recorded[0], dtype=float), _as_2d(recorded[1])
        for d in range(min(D, tes.shape[1])):
            col = DIM_COLOURS[d % len(DIM_COLOURS)]
            ax_te.plot(ts, tes[:, d], "o", color=col, ms=3, mfc="none",
                       label="reported by the planner" if d == 0 else None)
    _marks(ax_te, marks)
    _marks(ax_lag, marks, label=False)
    ax_te.set_ylabel("time to go $t_e$ [s]")
    ax_lag.set_ylabel("lag $t_E - t_e$ [s]")
    ax_lag.set_xlabel("time [s]")
    for ax in (ax_te, ax_lag):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def cylinder_phase_figure(
    runs: Mapping[str, Sequence[tuple[ArrayLike, ArrayLike]]],
    demo: tuple[ArrayLike, ArrayLike] | None = None,
    *,
    contact: float | None = None,
    target_speed: float | None = None,
    dim: str = "y",
    unit: str = "m",
    run_labels: Sequence[str] | None = None,
    title: str = "",
) -> Any:
    """The cylinder strike (Fig. 10): for each method (one panel each, shared axes), the
    position--velocity curves ``(x (T,), v (T,))`` of the strike dimension from several starts
    (labelled by ``run_labels``), the demonstration in black, the contact position as a vertical
    line and, optionally, the speed the strike needs at contact as a horizontal one."""
    if not runs:
        raise ValueError("no method to plot")
    n = len(runs)
    fig = _new_figure(4.2 * n + 0.4, 4.2)
    axes = fig.subplots(1, n, sharex=True, sharey=True, squeeze=False)[0]
    for ax, (method, curves) in zip(axes, runs.items(), strict=True):
        if demo is not None:
            ax.plot(np.asarray(demo[0], float), np.asarray(demo[1], float), color="k", lw=2.0,
                    label="demonstration")
        for i, (x, v) in enumerate(curves):
            label = run_labels[i] if run_labels is not None and i < len(run_labels) else f"start {i + 1}"
            ax.plot(np.asarray(x, float), np.asarray(v, float), lw=1.2, color=f"C{i % 10}", label=label)
        if contact is not None:
            ax.axvline(contact, color="C3", ls="--", lw=1.2, label="contact")
        if target_speed is not None:
            ax.axhline(target_speed, color="0.3", ls=":", lw=1.2, label="needed speed")
        ax.set_title(method, fontsize=10)
        ax.set_xlabel(f"{dim} [{unit}]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"velocity {dim} [{unit}/s]")
    axes[0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


# ---------------------------------------------------------------------------------------- writers
def plot_trajectories(path: str | Path, curves: Sequence[Curve], **kwargs: Any) -> Path:
    """:func:`trajectories_figure` written to ``path`` (PNG)."""
    return save_figure(trajectories_figure(curves, **kwargs), path)


def plot_path(path: str | Path, curves: Sequence[Curve], **kwargs: Any) -> Path:
    """:func:`path_figure` written to ``path`` (PNG)."""
    return save_figure(path_figure(curves, **kwargs), path)


def plot_phase_space(
    path: str | Path, curves: Sequence[PhaseCurve], lines: Sequence[Sequence[PSTFLine]] | None = None,
    **kwargs: Any,
) -> Path:
    """:func:`phase_space_figure` written to ``path`` (PNG)."""
    return save_figure(phase_space_figure(curves, lines, **kwargs), path)


def plot_time_to_go(path: str | Path, t: ArrayLike, time_to_go: ArrayLike, **kwargs: Any) -> Path:
    """:func:`time_to_go_figure` written to ``path`` (PNG)."""
    return save_figure(time_to_go_figure(t, time_to_go, **kwargs), path)


def plot_cylinder_phase(
    path: str | Path,
    runs: Mapping[str, Sequence[tuple[ArrayLike, ArrayLike]]],
    demo: tuple[ArrayLike, ArrayLike] | None = None,
    **kwargs: Any,
) -> Path:
    """:func:`cylinder_phase_figure` written to ``path`` (PNG)."""
    return save_figure(cylinder_phase_figure(runs, demo, **kwargs), path)
