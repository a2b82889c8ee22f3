"""Fingerprints of learned models, to check that a change to the fit leaves every result as it was.

Usage::

    PYTHONPATH=$PWD .venv/bin/python scripts/fit_fingerprints.py save /tmp/ref.json     # before
    PYTHONPATH=$PWD .venv/bin/python scripts/fit_fingerprints.py compare /tmp/ref.json  # after

Each case is ``PhaseSpaceModel.fit`` of one demonstration; its fingerprint is the SHA-256 of the
model's ``to_dict()`` as JSON (every float written exactly), or of the error it raises. Cases: the
learner benchmark's 5,000-sample 3-D reach (both ``k_fit`` modes), demo 0 of every LASA shape,
every recording in ``data/demos/*.mcap`` (defaults and a tight tolerance), and 400 seeded random
1–5-D demonstrations (reaches, sines, random walks, holds, non-uniform time stamps) with random
smoothing, segments, ``k_fit``, tolerances, ``max_segments`` and ``min_speed_ratio``. The
reference file is the caller's (it is not committed). Exit status 1 when a fingerprint differs.
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "core")]

from fingerprints import save_or_compare  # noqa: E402
from trajectories import minimum_jerk  # noqa: E402

from benchmarks.learner import list_shapes, load_shape, min_jerk_reach  # noqa: E402
from psm import PhaseSpaceModel  # noqa: E402
from services.learn_cli import load_demonstration  # noqa: E402

Case = tuple[str, np.ndarray, np.ndarray, dict[str, Any]]


def fingerprint(t: np.ndarray, X: np.ndarray, **options: Any) -> tuple[str, bool]:
    """``(SHA-256 hex digest, raised)`` of the model fitted to ``t (T,)`` [s], ``X (T, D)``."""
    try:
        text = json.dumps(PhaseSpaceModel.fit(t, X, **options).to_dict(), sort_keys=True)
        raised = False
    except Exception as exc:  # the error is part of the result
        text, raised = f"{type(exc).__name__}: {exc}", True
    return hashlib.sha256(text.encode()).hexdigest(), raised


def _random_case(rng: np.random.Generator, i: int) -> Case:
    D = int(rng.integers(1, 6))
    T = int(rng.choice([20, 60, 200, 600, 1500, 3000, 5000]))
    dt = float(rng.choice([0.001, 0.002, 0.005, 0.01]))
    t = np.arange(T) * dt
    if rng.random() < 0.15:
        t = np.cumsum(rng.uniform(0.5, 1.5, T)) * dt
    s = minimum_jerk(t - t[0], t[-1] - t[0])
    kind = rng.integers(0, 3)
    cols = []
    for _ in range(D):
        if kind == 0:
            cols.append(rng.uniform(-0.3, 0.3) * s + rng.uniform(-1, 1))
        elif kind == 1:
            cols.append(0.1 * np.sin(2 * np.pi * rng.uniform(0.3, 2.5) * s + rng.uniform(0, 6)))
        else:
            cols.append(np.cumsum(rng.normal(0, 1e-3, T)))
    X = np.stack(cols, axis=1)
    if rng.random() < 0.2:
        X[:, int(rng.integers(0, D))] = 0.2  # a hold
    X = X + rng.normal(0.0, float(rng.choice([0.0, 1e-5, 2e-4, 1e-3])), X.shape)
    options: dict[str, Any] = {"smoothing": float(rng.choice([0.0, 0.005, 0.02, 0.05]))}
    r = rng.random()
    if r < 0.15:
        options["segments"] = int(rng.integers(1, 12))
    elif r < 0.22:
        options["segments"] = sorted(rng.uniform(0.1, 0.9, 3) * (t[-1] - t[0]))
    if rng.random() < 0.3:
        options["k_fit"] = "least_squares"
    if rng.random() < 0.4:
        options["auto_tolerance"] = float(rng.choice([1e-4, 1e-3, 2e-2]))
    if rng.random() < 0.3:
        options["max_segments"] = int(rng.integers(1, 40))
    if rng.random() < 0.2:
        options["min_speed_ratio"] = float(rng.choice([0.2, 0.8]))
    if rng.random() < 0.2:
        options["hold_tolerance"] = float(rng.choice([1e-5, 1e-2]))
    if D == 1 and rng.random() < 0.5:
        X = X[:, 0]
    return f"random_{i}", t, X, options


def cases() -> Iterator[Case]:
    """Every demonstration checked, as ``(name, t, X, fit options)``."""
    demo = min_jerk_reach(5000, 3, 5.0, noise=2e-4, seed=5)
    yield "benchmark_5k", demo.t, demo.x, {}
    yield "benchmark_5k_least_squares", demo.t, demo.x, {"k_fit": "least_squares"}
    for name in list_shapes():
        lasa = load_shape(name)[0]
        yield f"lasa_{name}", lasa.t, lasa.x, {}
    for path in sorted((ROOT / "data" / "demos").glob("*.mcap")):
        t, X, _ = load_demonstration(path)
        yield f"mcap_{path.stem}", t, X, {}
        yield f"mcap_{path.stem}_tight", t, X, {"auto_tolerance": 1e-3, "max_segments": 12}
    rng = np.random.default_rng(20261122)
    for i in range(400):
        yield _random_case(rng, i)


def digests() -> dict[str, str]:
    """Every case's digest by name (printing how many cases there are and how many raise)."""
    with np.errstate(all="ignore"):
        results = {name: fingerprint(t, X, **options) for name, t, X, options in cases()}
    print(f"{len(results)} cases, {sum(r for _, r in results.values())} raise (their errors are compared)")
    return {name: digest for name, (digest, _) in results.items()}


def main() -> int:
    return save_or_compare(sys.argv[1:], __doc__ or "", digests)


if __name__ == "__main__":
    sys.exit(main())
