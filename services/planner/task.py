"""The task a planner runs, as data: a sequence of steps (sub-tasks), each one PSM towards a goal.

A task file (``configs/feeding.toml``) has the scene (named static positions) and the task::

    [task]
    name = "feeding"
    on_goal_lost = "hold"              # or "neutral": see TaskSpec

    [[task.steps]]
    name = "grasp_spoon"               # also the demonstration data/demos/grasp_spoon.mcap
    goal = "spoon"                     # a scene position, or a live goal (live = true)
    gripper = "close"                  # a gripper action once the step is done
    controller = { start_shift = true } # PhaseSpaceModel.controller options
    fit = {}                           # PhaseSpaceModel.fit options

    [[task.steps]]
    name = "scoop"
    goal = "bowl"
    offset_m = [0.06, 0.06, 0.06]      # the step's goal is the bowl + this offset

The fit and controller options are passed to :meth:`psm.PhaseSpaceModel.fit` and
:meth:`psm.PhaseSpaceModel.controller`, whose signatures are their only definition: an unknown
option is an error naming it, and an option that is not given keeps the model's default.
"""

from __future__ import annotations

import inspect
from typing import Any, Literal

from pydantic import Field, field_validator

from services.bus.config import ConfigError, Section, Vec3

__all__ = ["StepSpec", "TaskSpec", "WorkspaceSpec"]


def _option_names(fn: Any, skip: int) -> frozenset[str]:
    params = list(inspect.signature(fn).parameters.values())[skip:]
    return frozenset(p.name for p in params if p.kind is not inspect.Parameter.VAR_KEYWORD)


def _check_options(value: dict[str, Any], allowed: frozenset[str], what: str) -> dict[str, Any]:
    unknown = sorted(set(value) - allowed)
    if unknown:
        raise ValueError(f"unknown {what} option {unknown[0]!r} (known: {', '.join(sorted(allowed))})")
    return value


class StepSpec(Section):
    """One step of a task (an entry of ``[[task.steps]]``)."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_\-]+$", description="step name (events, status)")
    demo: str = Field(
        "",
        description="demonstration: a name under data/demos (default: the step's name) or a file path",
    )
    model_file: str = Field("", description="a saved model (psm learn -o) instead of a demonstration")
    goal: str = Field(min_length=1, description="scene position or live goal name the step reaches")
    live: bool = Field(False, description="the goal comes from the bus (<prefix>/goals/<goal>)")
    offset_m: Vec3 = Field(
        default_factory=lambda: [0.0, 0.0, 0.0], description="the step's goal = goal position + this, m"
    )
    position_tolerance_m: float = Field(0.01, gt=0.0, description="done within this distance of the goal, m")
    velocity_tolerance_mps: float = Field(
        0.03, gt=0.0, description="... and this speed relative to the goal's, m/s"
    )
    dwell_s: float = Field(0.0, ge=0.0, description="hold the goal this long once reached, s")
    follow_s: float = Field(0.0, ge=0.0, description="live goal: keep following it this long once reached, s")
    timeout_s: float = Field(
        0.0, ge=0.0, description="abort the task if the step takes longer, s (0 = 3x the demonstration + 5 s)"
    )
    gripper: Literal["", "open", "close"] = Field("", description="gripper action when the step is done")
    orientation: Literal["demo", "hold"] = Field(
        "demo",
        description="demo: the orientation follows the demonstration over t_e; hold: keep the start one",
    )
    fit: dict[str, Any] = Field(default_factory=dict, description="PhaseSpaceModel.fit options")
    controller: dict[str, Any] = Field(default_factory=dict, description="PhaseSpaceModel.controller options")

    @field_validator("fit")
    @classmethod
    def _fit_options(cls, value: dict[str, Any]) -> dict[str, Any]:
        from psm import PhaseSpaceModel

        return _check_options(value, _option_names(PhaseSpaceModel.fit, 2), "fit")

    @field_validator("controller")
    @classmethod
    def _controller_options(cls, value: dict[str, Any]) -> dict[str, Any]:
        from psm import PhaseSpaceModel

        allowed = _option_names(PhaseSpaceModel.controller, 2)
        if "goal" in value:
            raise ValueError("the goal is the step's goal, not a controller option")
        return _check_options(value, allowed, "controller")

    def check(self) -> None:
        """At most one model source."""
        if self.demo and self.model_file:
            raise ConfigError("model_file", "give either demo or model_file, not both")

    @property
    def demo_name(self) -> str:
        """The demonstration (name or path) the step learns from."""
        return self.demo or self.name


class WorkspaceSpec(Section):
    """The box goals must lie in (``[task.workspace]``); a goal outside it is never used."""

    lower_m: Vec3 = Field(default_factory=lambda: [0.15, -0.7, 0.0], description="m, base frame")
    upper_m: Vec3 = Field(default_factory=lambda: [0.9, 0.7, 0.9], description="m, base frame")

    def check(self) -> None:
        """Every lower bound below its upper bound."""
        if any(lo >= hi for lo, hi in zip(self.lower_m, self.upper_m, strict=True)):
            raise ConfigError("lower_m", "must be below upper_m on every axis")

    def contains(self, p: Any) -> bool:
        """True if position ``p (3,)`` [m] is inside the box."""
        return all(lo <= float(c) <= hi for lo, c, hi in zip(self.lower_m, p, self.upper_m, strict=True))


class TaskSpec(Section):
    """The ``[task]`` table: the steps and how the sequencer treats goals."""

    name: str = Field("feeding", min_length=1, description="task name (events, status)")
    steps: list[StepSpec] = Field(min_length=1, description="the steps, in order")
    on_goal_lost: Literal["hold", "neutral"] = Field(
        "hold",
        description="a live goal lost or invalid: hold the motion where it is, or go to the neutral position",
    )
    neutral: str = Field("neutral", description="scene position of on_goal_lost = neutral")
    neutral_model: str = Field(
        "back_to_neutral", description="step whose model drives on_goal_lost = neutral"
    )
    goal_timeout_s: float = Field(
        0.5, gt=0.0, description="a live goal not updated for this long (stack clock) is lost, s"
    )
    goal_event_m: float = Field(
        0.02, gt=0.0, description="a GOAL_CHANGED event when the goal in use moved this far since the last, m"
    )
    orientation_dim: int = Field(
        2, ge=0, le=2, description="dimension whose t_e drives the orientation (2 = z, as in the paper)"
    )
    hold_omega: float = Field(
        8.0, gt=0.0, description="natural frequency of the critically damped hold, rad/s"
    )
    hold_max_accel: float = Field(3.0, gt=0.0, description="acceleration limit of the hold, m/s^2")
    workspace: WorkspaceSpec = Field(default_factory=WorkspaceSpec)

    def check(self) -> None:
        """Step names are unique."""
        names = [s.name for s in self.steps]
        for i, n in enumerate(names):
            if n in names[:i]:
                raise ConfigError(f"steps[{i}].name", f"duplicate step name {n!r}")

    @property
    def sequence(self) -> tuple[str, ...]:
        """The step names, in order."""
        return tuple(s.name for s in self.steps)

    def step(self, name: str) -> StepSpec:
        """The step called ``name``; ``KeyError`` if there is none."""
        for s in self.steps:
            if s.name == name:
                return s
        raise KeyError(name)
