"""Fixtures of the in-process planner tests: the shipped feeding task and its learned models."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.bus.config import read_toml
from services.planner.models import ModelCache, TaskModels, load_task_models
from services.tasks.feeding import DEFAULT_FEEDING_CONFIG, FeedingConfig, parse_feeding

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def feeding() -> FeedingConfig:
    """The shipped scene and task (configs/feeding.toml)."""
    return parse_feeding(read_toml(DEFAULT_FEEDING_CONFIG))


@pytest.fixture(scope="module")
def models(feeding: FeedingConfig) -> TaskModels:
    """Its models, learned from the committed demonstrations (cached in out/models)."""
    return load_task_models(feeding.task, ModelCache(ROOT / "out" / "models"))
