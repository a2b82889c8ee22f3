"""The models of a task's sub-tasks: learned from their demonstrations, or read from files.

A sub-task's model is learned at start from its demonstration (``data/demos/<name>.mcap``, the
end-effector trajectory by forward kinematics, as ``psm learn`` reads it) with the fit options
of the task config, or read from a model file named in the task config. Learning is cached:
:class:`ModelCache` keeps every learned model as ``<cache_dir>/<name>-<key>.json`` where the key
is the SHA-256 of what determines the model — the demonstration's samples (``t``, ``X`` as
float64 bytes), the fit options and the model format version — so a changed demonstration or
option learns anew, and an unchanged one is read back (a damaged cache file is learned again
and replaced).

Example::

    cache = ModelCache(Path("out/models"))
    models = load_models({"reach_bowl": ModelSource(demo=Path("data/demos/reach_bowl.mcap"))},
                         cache)
    ctrl = models["reach_bowl"].controller(goal)
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psm import PhaseSpaceModel
from psm.errors import PSMError
from psm.model import FIT_REVISION, FORMAT_VERSION

__all__ = [
    "DEMOS_DIR", "ModelCache", "ModelSource", "TaskModels", "cache_key", "demo_path", "load_models",
    "load_task_models",
]

#: The committed demonstrations (one MCAP recording per sub-task).
DEMOS_DIR = Path(__file__).resolve().parents[2] / "data" / "demos"

_log = logging.getLogger("psm.planner.models")


@dataclass(frozen=True)
class ModelSource:
    """Where one sub-task's model comes from: a model file, or a demonstration learned with the
    fit options ``options`` (keyword arguments of :meth:`PhaseSpaceModel.fit`; those not given
    keep the model's defaults)."""

    demo: Path | None = None
    model_file: Path | None = None
    options: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if (self.demo is None) == (self.model_file is None):
            raise ValueError("a model source names exactly one of demo and model_file")


def cache_key(t: np.ndarray, X: np.ndarray, options: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of the demonstration's samples ``t (T,) [s]``, ``X (T, D)``, the fit
    options (as sorted JSON), the model format version and the fit's revision (a library whose
    fit learns differently does not reuse the models of another)."""
    h = hashlib.sha256()
    h.update(f"psm-model-v{FORMAT_VERSION}-fit{FIT_REVISION}\0".encode())
    for a in (t, X):
        arr = np.ascontiguousarray(a, dtype=np.float64)
        h.update(repr(arr.shape).encode())
        h.update(arr.tobytes())
    h.update(json.dumps(dict(options), sort_keys=True, default=_json_default).encode())
    return h.hexdigest()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"fit option of type {type(value).__name__} cannot be hashed")


class ModelCache:
    """Learned models on disk, by :func:`cache_key` (see the module docstring)."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self.hits = 0
        self.misses = 0

    def path(self, name: str, key: str) -> Path:
        """The cache file of sub-task ``name`` for ``key``."""
        return self.directory / f"{name}-{key[:32]}.json"

    def get_or_fit(
        self, name: str, t: np.ndarray, X: np.ndarray, options: Mapping[str, Any]
    ) -> PhaseSpaceModel:
        """The model of ``(t, X, options)``: read from the cache, else learned and stored."""
        key = cache_key(t, X, options)
        path = self.path(name, key)
        if path.exists():
            try:
                model = PhaseSpaceModel.load(path)
            except (OSError, ValueError, PSMError) as exc:
                _log.warning("damaged cached model, learning again",
                             extra={"path": str(path), "reason": str(exc)})
            else:
                self.hits += 1
                return model
        self.misses += 1
        model = PhaseSpaceModel.fit(t, X, **dict(options))
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        model.save(tmp)
        os.replace(tmp, path)  # a reader never sees a half-written file
        return model


def load_models(
    sources: Mapping[str, ModelSource], cache: ModelCache | None = None
) -> dict[str, PhaseSpaceModel]:
    """One model per sub-task name. Raises ``FileNotFoundError``, ``DemonstrationError`` (a
    demonstration that does not move) or the model's own errors, each naming the file."""
    from services.learn_cli import check_motion, load_demonstration

    models: dict[str, PhaseSpaceModel] = {}
    for name, src in sources.items():
        if src.model_file is not None:
            models[name] = PhaseSpaceModel.load(src.model_file)
            continue
        assert src.demo is not None
        t, X, _dims = load_demonstration(Path(src.demo))
        check_motion(t, X)
        if cache is None:
            models[name] = PhaseSpaceModel.fit(t, X, **dict(src.options))
        else:
            models[name] = cache.get_or_fit(name, t, X, src.options)
    return models


@dataclass
class TaskModels:
    """What a task's steps run on: the PSM, the orientation profile (demonstrations that carry
    orientations) and the demonstration's figures, per step name."""

    models: dict[str, PhaseSpaceModel]
    profiles: dict[str, Any]
    demos: dict[str, Any]


def demo_path(name: str, demos_dir: Path = DEMOS_DIR) -> Path:
    """The demonstration file of a step: a path as given (it has a suffix or a directory), else
    ``<demos_dir>/<name>.mcap``."""
    p = Path(name)
    return p if (p.suffix or len(p.parts) > 1) else demos_dir / f"{name}.mcap"


def load_task_models(task: Any, cache: ModelCache | None = None, demos_dir: Path = DEMOS_DIR) -> TaskModels:
    """Models, orientation profiles and demonstration figures of every step of ``task``
    (a :class:`~services.planner.task.TaskSpec`). Errors name the file (see :func:`load_models`)."""
    from services.learn_cli import check_motion, check_recording, load_demonstration
    from services.planner.orientation import OrientationProfile
    from services.planner.sequencer import DemoFigures
    from services.robot.recordings import ee_poses

    out = TaskModels({}, {}, {})
    for step in task.steps:
        if step.model_file:
            out.models[step.name] = PhaseSpaceModel.load(Path(step.model_file))
            continue
        path = demo_path(step.demo_name, demos_dir)
        quats = None
        if path.suffix.lower() == ".mcap":
            if not path.exists():
                raise FileNotFoundError(f"{path}: no such file")
            check_recording(path)
            t, X, quats = ee_poses(path)
        else:
            t, X, _dims = load_demonstration(path)
        check_motion(t, X)
        fit = dict(step.fit)
        model = cache.get_or_fit(step.name, t, X, fit) if cache else PhaseSpaceModel.fit(t, X, **fit)
        out.models[step.name] = model
        if X.shape[1] == 3:
            out.demos[step.name] = DemoFigures.of(t, X)
        if quats is not None:
            out.profiles[step.name] = OrientationProfile.fit(t, quats)
    return out
