"""Analytic motions shared by the PSM core tests (imported by name: ``tests/core`` is on the path)."""

from __future__ import annotations

import numpy as np


def minimum_jerk(t: np.ndarray, duration: float) -> np.ndarray:
    """Minimum-jerk phase ``s(t) ∈ [0, 1]`` over ``duration`` [s]: 0 before, 1 after, at rest (zero
    velocity and acceleration) at both ends. ``t``: any shape [s]."""
    s = np.clip(t / duration, 0.0, 1.0)
    return 10 * s**3 - 15 * s**4 + 6 * s**5
