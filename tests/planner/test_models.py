"""The planner's models: learned from the committed demonstrations, cached by content."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from psm import PhaseSpaceModel
from services.planner.models import DEMOS_DIR, ModelCache, ModelSource, cache_key, load_models

DEMO = DEMOS_DIR / "reach_bowl.mcap"


def test_a_learned_model_is_cached_by_content(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sources = {"reach_bowl": ModelSource(demo=DEMO)}
    first = load_models(sources, ModelCache(tmp_path))["reach_bowl"]
    files = list(tmp_path.glob("reach_bowl-*.json"))
    assert len(files) == 1

    def no_fit(*_a: object, **_k: object) -> None:
        raise AssertionError("a cached model was learned again")

    monkeypatch.setattr(PhaseSpaceModel, "fit", no_fit)
    cache = ModelCache(tmp_path)
    again = load_models(sources, cache)["reach_bowl"]
    assert (cache.hits, cache.misses) == (1, 0)
    assert again.to_dict() == first.to_dict()


def test_other_options_or_samples_learn_anew(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    t = np.linspace(0.0, 1.0, 501)
    X = np.column_stack([0.1 * (3 * t**2 - 2 * t**3), 0.05 * t])
    cache = ModelCache(tmp_path)
    a = cache.get_or_fit("reach", t, X, {})
    cache.get_or_fit("reach", t, X, {"smoothing": 0.01})
    X2 = X.copy()
    X2[100, 0] += 1e-9
    cache.get_or_fit("reach", t, X2, {})
    assert (cache.hits, cache.misses) == (0, 3)
    assert len(list(tmp_path.glob("reach-*.json"))) == 3
    assert cache_key(t, X, {}) != cache_key(t, X2, {})
    assert cache_key(t, X, {"smoothing": 0.01}) == cache_key(t.copy(), X.copy(), {"smoothing": 0.01})
    assert cache.get_or_fit("reach", t, X, {}).to_dict() == a.to_dict()
    assert cache.hits == 1
    # a library whose fit learns differently does not reuse another's models
    import services.planner.models as models

    key = cache_key(t, X, {})
    monkeypatch.setattr(models, "FIT_REVISION", models.FIT_REVISION + 1)
    assert cache_key(t, X, {}) != key


def test_a_damaged_cache_file_is_learned_again(tmp_path: Path) -> None:
    t = np.linspace(0.0, 1.0, 501)
    X = (0.2 * (3 * t**2 - 2 * t**3))[:, None]
    cache = ModelCache(tmp_path)
    good = cache.get_or_fit("reach", t, X, {})
    path = cache.path("reach", cache_key(t, X, {}))
    path.write_text("{ not json")
    again = cache.get_or_fit("reach", t, X, {})
    assert cache.misses == 2 and again.to_dict() == good.to_dict()
    assert PhaseSpaceModel.load(path).to_dict() == good.to_dict()  # replaced


def test_a_model_file_is_read_as_it_is(tmp_path: Path) -> None:
    t = np.linspace(0.0, 1.0, 501)
    model = PhaseSpaceModel.fit(t, (0.1 * t)[:, None])
    model.save(tmp_path / "m.json")
    loaded = load_models({"x": ModelSource(model_file=tmp_path / "m.json")})["x"]
    assert loaded.to_dict() == model.to_dict()


def test_a_source_names_one_origin() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        ModelSource()
    with pytest.raises(ValueError, match="exactly one"):
        ModelSource(demo=DEMO, model_file=Path("m.json"))
