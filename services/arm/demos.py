"""The demonstrations shipped under ``data/demos/``: the paper's five feeding sub-tasks and the
cylinder-rolling strike (paper §IV-B, IV-D), as guided Panda motions.

The scene (neutral pose, spoon, bowl, person, cylinder) and the order of the feeding sub-tasks
are configuration: ``configs/feeding.toml``, loaded by :func:`services.tasks.feeding.load_feeding`.
The via-points of each demonstration are given here relative to those scene positions
(:func:`build_demos`), so moving an object in the file moves the demonstrations that use it.
Each via-point is rounded to 1 µm, which keeps it equal to the decimal coordinates it
describes (``0.50 + 0.14`` is not exactly ``0.64`` in binary floating point).

Every demonstration keeps the hand pointing down (the ``ready`` orientation), starts and ends
at rest, and carries seeded tremor (0.2 mm RMS at 8–12 Hz, 1 mm RMS drift at 0.3–1.5 Hz).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.arm.teach import Tremor, ViaPointPath
from services.tasks.feeding import FeedingScene, Vec3, load_feeding


@dataclass(frozen=True)
class DemoSpec:
    """One demonstration: a name, a description, via-points ``(K, 3)`` m, leg durations
    ``(K-1,)`` s, optional via velocities ``(K, 3)`` m/s, the goal (last point) and a seed."""

    name: str
    description: str
    points: tuple[Vec3, ...]
    durations: tuple[float, ...]
    velocities: tuple[Vec3, ...] | None = None
    seed: int = 0

    @property
    def goal(self) -> Vec3:
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


def _at(place: Vec3, offset: Vec3 = (0.0, 0.0, 0.0)) -> Vec3:
    """``place + offset`` (m), each coordinate rounded to 1 µm."""
    return (
        round(place[0] + offset[0], 6),
        round(place[1] + offset[1], 6),
        round(place[2] + offset[2], 6),
    )


#: Cylinder strike: distance pushed along +y while accelerating from 0.05 to 0.5 m/s (m), and
#: the braking distance after it (m), rising 2 cm.
STRIKE_PUSH = 0.20
STRIKE_STOP = 0.15

#: Via velocities of the strike (m/s): at rest, touch at 0.05 m/s, 0.5 m/s at the end of the
#: push, at rest.
_STRIKE_V: tuple[Vec3, ...] = ((0.0, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 0.0))


def build_demos(scene: FeedingScene) -> dict[str, DemoSpec]:
    """The demonstrations for a scene, by name (feeding sub-tasks, then ``cylinder_strike``).

    Leg durations are in s; the strike's push and stop legs last ``2·distance/(v0 + v1)`` so
    the speed changes monotonically on each leg.
    """
    neutral, spoon, bowl, person, cyl = (
        scene.neutral,
        scene.spoon,
        scene.bowl,
        scene.person,
        scene.cylinder_contact,
    )
    scoop_out = _at(bowl, (0.06, 0.06, 0.06))  # lifted out of the bowl, above its far rim
    demos = (
        DemoSpec(
            "grasp_spoon",
            "neutral -> above the spoon -> down to the spoon's handle",
            (_at(neutral), _at(spoon, (-0.02, 0.05, 0.14)), _at(spoon)),
            (1.6, 1.2),
            seed=1,
        ),
        DemoSpec(
            "back_to_neutral",
            "spoon -> lift -> neutral",
            (_at(spoon), _at(spoon, (-0.02, 0.07, 0.16)), _at(neutral)),
            (1.2, 1.5),
            seed=2,
        ),
        DemoSpec(
            "reach_bowl",
            "neutral -> above the bowl -> into the bowl",
            (_at(neutral), _at(bowl, (-0.03, -0.06, 0.16)), _at(bowl)),
            (1.5, 1.1),
            seed=3,
        ),
        DemoSpec(
            "scoop",
            "bowl rim -> dip -> drag through the bowl -> lift out",
            (_at(bowl), _at(bowl, (0.01, 0.02, -0.04)), _at(bowl, (0.05, 0.05, -0.03)), scoop_out),
            (0.8, 0.9, 0.8),
            seed=4,
        ),
        DemoSpec(
            "reach_person",
            "out of the bowl -> up and over -> to the person's mouth",
            (scoop_out, _at(person, (0.17, -0.12, -0.07)), _at(person)),
            (1.4, 1.4),
            seed=5,
        ),
        DemoSpec(
            "cylinder_strike",
            "approach the cylinder slowly, touch at 0.05 m/s, accelerate to 0.5 m/s along +y, stop",
            (
                _at(cyl, (0.0, -0.25, 0.11)),
                _at(cyl),
                _at(cyl, (0.0, STRIKE_PUSH, 0.0)),
                _at(cyl, (0.0, STRIKE_PUSH + STRIKE_STOP, 0.02)),
            ),
            (2.0, 2 * STRIKE_PUSH / (0.05 + 0.5), 2 * STRIKE_STOP / (0.5 + 0.0)),
            _STRIKE_V,
            seed=6,
        ),
    )
    return {d.name: d for d in demos}


def load_demos(path: str | Path | None = None) -> dict[str, DemoSpec]:
    """:func:`build_demos` for the scene of a feeding config (default ``configs/feeding.toml``).

    Raises:
        FileNotFoundError, services.tasks.feeding.FeedingConfigError: see
            :func:`~services.tasks.feeding.load_feeding`.
    """
    return build_demos(load_feeding(path).scene)
