"""Reachable workspace check: a goal outside it is published as invalid with the reason."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from psm.errors import ParameterError

_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Workspace:
    """Axis-aligned box in the robot base frame, optionally intersected with a spherical shell
    around ``centre`` (e.g. the shoulder): ``min_radius ≤ |p − centre| ≤ max_radius``. Metres.
    """

    lower: tuple[float, float, float] = (0.1, -0.6, 0.0)
    upper: tuple[float, float, float] = (0.9, 0.6, 1.2)
    centre: tuple[float, float, float] = (0.0, 0.0, 0.3)
    min_radius: float = 0.0
    max_radius: float = math.inf

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lower, float), np.asarray(self.upper, float)
        if lo.shape != (3,) or hi.shape != (3,) or np.asarray(self.centre, float).shape != (3,):
            raise ParameterError("workspace lower, upper and centre must be 3-vectors")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ParameterError("workspace bounds must be finite")
        if np.any(lo >= hi):
            raise ParameterError(f"workspace lower {tuple(lo)} must be < upper {tuple(hi)}")
        if not (0 <= self.min_radius < self.max_radius):
            raise ParameterError(
                f"workspace needs 0 <= min_radius < max_radius, got {self.min_radius}, {self.max_radius}"
            )

    def violation(self, p: ArrayLike) -> str | None:
        """None when ``p`` (3,) is reachable, otherwise a one-line reason naming the bound."""
        q = np.asarray(p, dtype=float).reshape(3)
        if not np.all(np.isfinite(q)):
            return "goal is not finite"
        for i, axis in enumerate(_AXES):
            if q[i] < self.lower[i]:
                return f"outside workspace: {axis}={q[i]:.3f} m < min {self.lower[i]:.3f} m"
            if q[i] > self.upper[i]:
                return f"outside workspace: {axis}={q[i]:.3f} m > max {self.upper[i]:.3f} m"
        r = float(np.linalg.norm(q - np.asarray(self.centre, dtype=float)))
        if r < self.min_radius:
            return f"outside workspace: distance {r:.3f} m < min_radius {self.min_radius:.3f} m"
        if r > self.max_radius:
            return f"outside workspace: distance {r:.3f} m > max_radius {self.max_radius:.3f} m"
        return None

    def clamp(self, p: ArrayLike) -> np.ndarray:
        """Nearest point of the box (the shell is not applied), for display only."""
        return np.clip(np.asarray(p, dtype=float), self.lower, self.upper)
