"""Shared demonstrations for the PSM core tests (deterministic, analytic)."""

from __future__ import annotations

import numpy as np
import pytest
from trajectories import minimum_jerk


@pytest.fixture
def reach_demo() -> tuple[np.ndarray, np.ndarray]:
    """A 3-D reach of 2 s at 500 Hz: x monotone, y out and back, z with two reversals [m]."""
    t = np.arange(0.0, 2.0 + 1e-9, 0.002)
    s = minimum_jerk(t, 2.0)
    X = np.stack([0.4 * s, 0.2 * np.sin(np.pi * s), 0.1 * np.sin(2 * np.pi * s)], axis=1)
    return t, X


@pytest.fixture
def noisy_reach_demo(reach_demo: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The reach with 50 µm white measurement noise (seeded)."""
    t, X = reach_demo
    rng = np.random.default_rng(7)
    return t, X + rng.normal(0.0, 5e-5, X.shape)
