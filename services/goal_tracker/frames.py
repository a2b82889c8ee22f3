"""The synthetic camera's settings and its frame grid, free of OpenCV: the camera
(:class:`services.goal_tracker.sources.SyntheticSource`) and the planner's live-goal sync
(:mod:`services.planner.service`) both read them.

Frame ``k`` of a camera at ``fps`` lies at ``round(k · 10⁹ / fps)`` ns on the stack's clock
(:func:`frame_time_ns`, the period an exact fraction: no drift over a long run); at the clock
time ``now`` the frame due is ``⌊now / period⌋`` (:func:`due_frame`).
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Literal

from pydantic import Field

from services.bus.config import ConfigError, Section, Vec3

__all__ = ["DEFAULT_FPS", "SyntheticSection", "due_frame", "frame_period_ns", "frame_time_ns"]

#: The synthetic camera's default frame rate [Hz].
DEFAULT_FPS = 30.0


def frame_period_ns(fps: float) -> Fraction:
    """The frame period [ns] of a camera at ``fps`` [Hz], as an exact fraction."""
    return Fraction(10**9) / Fraction(fps).limit_denominator(10**6)


def frame_time_ns(k: int, period: Fraction) -> int:
    """Time [ns] of frame ``k`` on the grid of ``period`` (:func:`frame_period_ns`)."""
    return round(k * period)


def due_frame(now_ns: int, period: Fraction) -> int:
    """The latest frame of the grid whose time is at or before ``now_ns``."""
    return math.floor(now_ns / period)


class SyntheticSection(Section):
    """``[goal_tracker.synthetic]``: the synthetic camera (astronaut face on a known path)."""

    fps: float = Field(
        DEFAULT_FPS, gt=0.0, le=1000.0,
        description="frame rate, Hz (frame k is the scene at t = k / fps)",
    )
    clock: Literal["wall", "arm"] = Field(
        "wall",
        description="wall: pace with the wall clock; arm: frame times from the arm's "
        "sim time (<prefix>/arm/state), for deterministic lockstep runs",
    )
    frames: int = Field(0, ge=0, description="stop after this many frames (0 = endless)")
    centre_m: Vec3 = Field(
        default_factory=lambda: [0.0, 0.0, 0.9],
        description="path centre, camera frame, m",
    )
    amplitude_m: Vec3 = Field(
        default_factory=lambda: [0.15, 0.06, 0.15],
        description="path amplitude per axis, m",
    )
    frequency_hz: Vec3 = Field(
        default_factory=lambda: [0.10, 0.13, 0.07],
        description="path frequency per axis, Hz",
    )
    phase_rad: Vec3 = Field(default_factory=lambda: [0.0, 0.5, 1.0], description="path phase per axis, rad")
    face_width_m: float = Field(0.16, gt=0.0, description="physical width of the synthetic face box, m")
    hidden_s: list[list[float]] = Field(
        default_factory=list,
        description="time windows [[t0, t1], ...] (s) the face is hidden",
    )
    noise_sigma: float = Field(2.0, ge=0.0, description="sensor noise, grey levels")
    seed: int = Field(0, ge=0, description="background / noise seed")

    def check(self) -> None:
        """Vector lengths, path in front of the camera, windows ordered."""
        if self.centre_m[2] - abs(self.amplitude_m[2]) <= 0.1:
            raise ConfigError("centre_m", "the path must stay > 0.1 m in front of the camera")
        for i, w in enumerate(self.hidden_s):
            if len(w) != 2 or not w[0] < w[1]:
                raise ConfigError(f"hidden_s[{i}]", f"expected [t0, t1] with t0 < t1, got {w}")
