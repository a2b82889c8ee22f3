"""The demonstrations shipped under ``data/demos/``: the paper's five feeding sub-tasks and the
cylinder-rolling strike (paper §IV-B, IV-D), as guided Panda motions.

Scene (base frame of the Panda, metres; the robot stands on the table, table top at z = 0,
x forward, y to the robot's left):

========== ======================== =====================================================
place      position (m)             note
========== ======================== =====================================================
neutral    (0.40, 0.00, 0.40)       hand pointing down above the table centre
spoon      (0.50, -0.25, 0.06)      grasp point of the spoon handle, right of the robot
bowl       (0.55, 0.20, 0.10)       rim height of the bowl, left of the robot
person     (0.35, 0.50, 0.45)       the person's mouth, seated at the robot's left
cylinder   (0.45, -0.10, 0.04)      contact point; the cylinder is rolled along +y
========== ======================== =====================================================

Every demonstration keeps the hand pointing down (the ``ready`` orientation), starts and ends
at rest, and carries seeded tremor (0.2 mm RMS at 8–12 Hz, 1 mm RMS drift at 0.3–1.5 Hz).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.arm.teach import Tremor, ViaPointPath, extract_ee_trajectory

NEUTRAL = (0.40, 0.00, 0.40)
SPOON = (0.50, -0.25, 0.06)
BOWL = (0.55, 0.20, 0.10)
PERSON = (0.35, 0.50, 0.45)
CYLINDER_CONTACT = (0.45, -0.10, 0.04)


@dataclass(frozen=True)
class DemoSpec:
    """One demonstration: a name, a description, via-points ``(K, 3)`` m, leg durations
    ``(K-1,)`` s, optional via velocities ``(K, 3)`` m/s, the goal (last point) and a seed."""

    name: str
    description: str
    points: tuple[tuple[float, float, float], ...]
    durations: tuple[float, ...]
    velocities: tuple[tuple[float, float, float], ...] | None = None
    seed: int = 0

    @property
    def goal(self) -> tuple[float, float, float]:
        """Goal position (the last via-point), m."""
        return self.points[-1]

    def path(self) -> ViaPointPath:
        """The minimum-jerk path through the via-points."""
        return ViaPointPath(
            np.array(self.points),
            np.array(self.durations),
            None if self.velocities is None else np.array(self.velocities),
        )

    def tremor(self) -> Tremor:
        """Seeded human-like tremor for this demonstration."""
        return Tremor(seed=self.seed)


# Cylinder strike: approach slowly, touch at 5 cm/s, accelerate to 0.5 m/s along +y over 20 cm
# (pushing the cylinder), then stop. Leg durations follow 2·distance/(v0+v1) so the speed
# changes monotonically on each leg.
_STRIKE_V = ((0.0, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 0.0))

DEMOS: dict[str, DemoSpec] = {
    d.name: d
    for d in (
        DemoSpec(
            "grasp_spoon",
            "neutral -> above the spoon -> down to the spoon's handle",
            (NEUTRAL, (0.48, -0.20, 0.20), SPOON),
            (1.6, 1.2),
            seed=1,
        ),
        DemoSpec(
            "back_to_neutral",
            "spoon -> lift -> neutral",
            (SPOON, (0.48, -0.18, 0.22), NEUTRAL),
            (1.2, 1.5),
            seed=2,
        ),
        DemoSpec(
            "reach_bowl",
            "neutral -> above the bowl -> into the bowl",
            (NEUTRAL, (0.52, 0.14, 0.26), BOWL),
            (1.5, 1.1),
            seed=3,
        ),
        DemoSpec(
            "scoop",
            "bowl rim -> dip -> drag through the bowl -> lift out",
            (BOWL, (0.56, 0.22, 0.06), (0.60, 0.25, 0.07), (0.61, 0.26, 0.16)),
            (0.8, 0.9, 0.8),
            seed=4,
        ),
        DemoSpec(
            "reach_person",
            "out of the bowl -> up and over -> to the person's mouth",
            ((0.61, 0.26, 0.16), (0.52, 0.38, 0.38), PERSON),
            (1.4, 1.4),
            seed=5,
        ),
        DemoSpec(
            "cylinder_strike",
            "approach the cylinder slowly, touch at 0.05 m/s, accelerate to 0.5 m/s along +y, stop",
            (
                (0.45, -0.35, 0.15),
                CYLINDER_CONTACT,
                (0.45, 0.10, 0.04),
                (0.45, 0.25, 0.06),
            ),
            (2.0, 2 * 0.20 / 0.55, 2 * 0.15 / 0.5),
            _STRIKE_V,
            seed=6,
        ),
    )
}

#: Order of the feeding task (paper Fig. 7).
FEEDING_SEQUENCE: tuple[str, ...] = (
    "grasp_spoon",
    "back_to_neutral",
    "reach_bowl",
    "scoop",
    "reach_person",
)


def trajectory_from_recording(path: str | Path, *, topic: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """End-effector trajectory ``t (T,)`` s, ``X (T, 3)`` m of a recording (``psm teach`` or
    any run of the arm), by forward kinematics from the recorded joint positions; see
    :func:`services.arm.teach.extract_ee_trajectory`. Used by ``psm learn DEMO.mcap``."""
    return extract_ee_trajectory(path, topic=topic)
