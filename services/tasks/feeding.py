"""The feeding scene and task, loaded from ``configs/feeding.toml``.

The file has two tables (positions in m, in the base frame ``scene.frame_id``: table top
z = 0, x forward, y to the robot's left)::

    [scene]
    frame_id = "base"
    neutral = [0.40, 0.00, 0.40]
    spoon = [0.50, -0.25, 0.06]
    bowl = [0.55, 0.20, 0.10]
    person = [0.35, 0.50, 0.45]
    cylinder_contact = [0.45, -0.10, 0.04]

    [task]                             # services.planner.task.TaskSpec
    name = "feeding"
    [[task.steps]]
    name = "grasp_spoon"
    goal = "spoon"
    ...

:func:`load_feeding` validates it at load (unknown keys, missing keys, a position that is not
three finite numbers, no steps, a static goal that is not a scene position) and raises
:class:`FeedingConfigError` with one line naming the field, e.g.
``configs/feeding.toml: scene.spoon: expected 3 finite numbers (m), got [0.5, -0.25]``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from services.bus.config import ConfigError, config_error, read_toml
from services.planner.task import TaskSpec

#: The feeding configuration shipped with the repository.
DEFAULT_FEEDING_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "feeding.toml"

#: A position ``(x, y, z)`` in m.
Vec3 = tuple[float, float, float]


class FeedingConfigError(ValueError):
    """The feeding configuration cannot be read or is invalid (one line naming the field)."""


def _vec3(value: Any) -> Vec3:
    """``value`` as a 3-tuple of finite floats; raises ``ValueError`` otherwise."""
    ok = (
        isinstance(value, list | tuple)
        and len(value) == 3
        and all(isinstance(c, int | float) and not isinstance(c, bool) for c in value)
        and all(math.isfinite(c) for c in value)
    )
    if not ok:
        raise ValueError(f"expected 3 finite numbers (m), got {value!r}")
    return (float(value[0]), float(value[1]), float(value[2]))


class FeedingScene(BaseModel):
    """Where things are: positions ``(3,)`` in m in the base frame ``frame_id``.

    Attributes:
        frame_id: base frame of the positions.
        neutral: neutral pose of the hand (pointing down) above the table centre.
        spoon: grasp point of the spoon's handle.
        bowl: the bowl, at rim height.
        person: the person's mouth.
        cylinder_contact: contact point on the cylinder (rolled along +y).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    frame_id: str = "base"
    neutral: Vec3
    spoon: Vec3
    bowl: Vec3
    person: Vec3
    cylinder_contact: Vec3

    @field_validator("neutral", "spoon", "bowl", "person", "cylinder_contact", mode="before")
    @classmethod
    def _position(cls, value: Any) -> Vec3:
        return _vec3(value)

    @field_validator("frame_id")
    @classmethod
    def _frame(cls, value: str) -> str:
        if not value:
            raise ValueError("must not be empty")
        return value

    def positions(self) -> dict[str, Vec3]:
        """Every named position of the scene, m."""
        return {name: getattr(self, name) for name in type(self).model_fields if name != "frame_id"}


class FeedingConfig(BaseModel):
    """``configs/feeding.toml``: the :class:`FeedingScene` and the task
    (:class:`~services.planner.task.TaskSpec`); :func:`parse_feeding` also checks that every
    static goal is a scene position."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scene: FeedingScene
    task: TaskSpec


def parse_feeding(data: dict[str, Any], source: str = "feeding config") -> FeedingConfig:
    """Validate an already parsed TOML document.

    Raises:
        FeedingConfigError: ``"SOURCE: field.path: message"``.
    """
    try:
        cfg = FeedingConfig.model_validate(data)
    except ValidationError as exc:
        err = config_error(exc)
        raise FeedingConfigError(f"{source}: {err.path}: {err.reason}") from None
    positions = cfg.scene.positions()
    for i, step in enumerate(cfg.task.steps):
        if not step.live and step.goal not in positions:
            raise FeedingConfigError(
                f"{source}: task.steps[{i}].goal: {step.goal!r} is not a scene position "
                f"({', '.join(positions)}; a goal from the bus needs live = true)"
            )
    if cfg.task.on_goal_lost == "neutral" and cfg.task.neutral not in positions:
        raise FeedingConfigError(f"{source}: task.neutral: {cfg.task.neutral!r} is not a scene position")
    return cfg


def load_feeding(path: str | Path | None = None) -> FeedingConfig:
    """Load and validate the feeding configuration (default :data:`DEFAULT_FEEDING_CONFIG`).

    Raises:
        FileNotFoundError: the file does not exist.
        FeedingConfigError: not TOML, or a field is missing, unknown or invalid.
    """
    p = DEFAULT_FEEDING_CONFIG if path is None else Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    try:
        data = read_toml(p)
    except ConfigError as exc:
        raise FeedingConfigError(exc.reason) from None
    return parse_feeding(data, str(p))


def static_person_task(feeding_toml: str) -> str:
    """The feeding task file's text with every live step made static (``live = false``: its
    goal is the scene position of the same name), for runs that must not depend on the camera
    and the goal tracker. Raises ``ValueError`` if the text has no live step."""
    out, n = re.subn(r"(?m)^(\s*live\s*=\s*)true\b", r"\1false", feeding_toml)
    if n == 0:
        raise ValueError("no live step in the task file")
    return out


__all__ = [
    "DEFAULT_FEEDING_CONFIG",
    "FeedingConfig",
    "FeedingConfigError",
    "FeedingScene",
    "Vec3",
    "load_feeding",
    "parse_feeding",
    "static_person_task",
]
