"""Fingerprints of the online controller's outputs, to check that a change to its hot path leaves
every command as it was (the controller's counterpart of ``scripts/fit_fingerprints.py``).

Usage::

    PYTHONPATH=$PWD .venv/bin/python scripts/controller_fingerprints.py save /tmp/ref.json     # before
    PYTHONPATH=$PWD .venv/bin/python scripts/controller_fingerprints.py compare /tmp/ref.json  # after

Each case is a closed loop of ``PSMController.step`` (the returned acceleration integrated over
``dt`` as ``rollout`` does) from a start near the demonstrated one; its fingerprint is the SHA-256
of every step's acceleration (exact bytes), modes, segments, times to go and ``done`` flag.
Models: demo 0 of twelve LASA shapes (2-D), the first 1, 3, 5 and 7 coordinates of the scale
experiment's 7-D reach, the learner benchmark's 3-D reach. Controller options: the defaults, the
paper's eq. 14 synchronisation, start shift with start retiming, rest and segment retiming off,
no synchronisation. Perturbations: none, velocity pushes every 97 ticks, two goal jumps, collision
stops (random positions, sides and missing stops, then cleared), a goal moving with a known
velocity. 425 cases, ~10 s. The reference file is the caller's (it is not committed). Exit status
1 when a fingerprint differs.
"""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from fingerprints import save_or_compare  # noqa: E402

from benchmarks.learner import list_shapes, load_shape, min_jerk_reach  # noqa: E402
from experiments.scale import slice_demo, via_point_reach  # noqa: E402
from psm import PhaseSpaceModel  # noqa: E402

OPTIONS: dict[str, dict[str, Any]] = {
    "defaults": {},
    "brake": {"sync_mode": "brake"},
    "shift_retime": {"start_shift": True, "start_retime": True},
    "no_retiming": {"rest_retime": False, "segment_retime": False},
    "no_sync": {"sync_gain": 0.0},
}
PERTURBATIONS = ("none", "pushes", "goal_jumps", "stops", "moving_goal")


def closed_loop(
    model: PhaseSpaceModel, x0: np.ndarray, dt: float, n_steps: int, rng: np.random.Generator,
    options: dict[str, Any], perturbation: str,
) -> str:
    """SHA-256 hex digest of ``n_steps`` controller steps from ``x0 (D,)`` at rest, ``dt`` [s]."""
    h = hashlib.sha256()
    ctrl = model.controller(None, **options)
    D = model.dim
    x, v = np.array(x0, dtype=float), np.zeros(D)
    goal = np.array(ctrl.goal)
    for k in range(n_steps):
        goal_velocity = None
        if perturbation == "moving_goal":
            goal_velocity = 0.05 * np.sin(np.arange(D) + k * dt)
            goal = goal + goal_velocity * dt
            ctrl.set_goal(goal)
        elif perturbation == "goal_jumps" and k in (n_steps // 5, n_steps // 2):
            goal = goal + rng.normal(0.0, 0.05, D)
            ctrl.set_goal(goal)
        elif perturbation == "stops" and k == n_steps // 4:
            stops = x + rng.normal(0.0, 0.03, D)
            stops[rng.random(D) < 0.3] = np.nan
            ctrl.set_stops(stops, rng.choice([1.0, -1.0, np.nan], D))
        elif perturbation == "stops" and k == n_steps // 2:
            ctrl.clear_stops()
        elif perturbation == "pushes" and k % 97 == 50:
            v = v + rng.normal(0.0, 0.2, D)
        a = ctrl.step(x, v, dt) if goal_velocity is None else ctrl.step(x, v, dt, goal_velocity)
        h.update(a.tobytes())
        h.update(repr((ctrl.modes, ctrl.segment_tuple, ctrl.time_to_go_tuple, ctrl.done)).encode())
        x = x + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        if ctrl.done and perturbation not in ("moving_goal", "pushes"):
            break
    return h.hexdigest()


def models() -> Iterator[tuple[str, PhaseSpaceModel, np.ndarray, float, int]]:
    """``(name, model, demonstrated start (D,), dt [s], samples)`` of every model checked."""
    for name in list_shapes()[:12]:
        demo = load_shape(name)[0]
        yield f"lasa_{name}", PhaseSpaceModel.fit(demo.t, demo.x), demo.x[0], demo.dt, len(demo.t)
    reach = via_point_reach(np.random.default_rng([1, 1]), 7)
    for dim in (1, 3, 5, 7):
        demo = slice_demo(reach, dim)
        yield f"reach_{dim}d", PhaseSpaceModel.fit(demo.t, demo.x), demo.x[0], demo.dt, len(demo.t)
    demo = min_jerk_reach(1001, 3, 2.0, noise=1e-4, seed=3)
    yield "benchmark_reach", PhaseSpaceModel.fit(demo.t, demo.x), demo.x[0], demo.dt, len(demo.t)


def fingerprints() -> dict[str, str]:
    """Every case's digest, by ``model/options/perturbation`` (printing how many cases there are)."""
    rng = np.random.default_rng(7)
    out = {}
    for name, model, x0, dt, samples in models():
        for opt_name, options in OPTIONS.items():
            for perturbation in PERTURBATIONS:
                offset = rng.normal(0.0, 0.02, len(x0)) * (np.abs(x0).max() + 1e-3)
                out[f"{name}/{opt_name}/{perturbation}"] = closed_loop(
                    model, x0 + offset, dt, min(2 * samples, 3000), rng, options, perturbation
                )
    print(f"{len(out)} cases")
    return out


def main() -> int:
    return save_or_compare(sys.argv[1:], __doc__ or "", fingerprints)


if __name__ == "__main__":
    sys.exit(main())
