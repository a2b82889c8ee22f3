"""Fixtures of the experiment tests: the shipped feeding task, its models and the stack's settings."""

from __future__ import annotations

from typing import Any

import pytest


@pytest.fixture(scope="module")
def feeding() -> Any:
    """The shipped scene and task (configs/feeding.toml)."""
    from services.tasks.feeding import load_feeding

    return load_feeding()


@pytest.fixture(scope="module")
def models(feeding: Any) -> Any:
    """Its models, learned from the committed demonstrations (cached in out/models)."""
    from experiments.harness import feeding_models

    return feeding_models(feeding.task)


@pytest.fixture(scope="module")
def settings() -> Any:
    """The settings of configs/stack.toml."""
    from experiments.harness import stack_settings

    return stack_settings()
