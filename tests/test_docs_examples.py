"""The Python examples of the README and ``docs/`` run against the code as it is.

Every fenced ``python`` block is executed. The examples are sketches of an API, so some use names
they do not define (a demonstration ``t, X``, a start ``x0``, a goal); :data:`GIVEN` supplies
those, and a service example's ``run_service`` only receives the service it would run (the
skeleton's own tests start services on a bus). A block that this module does not know fails
:func:`test_every_example_is_run`, so a new example is run from the day it is written.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def python_blocks(page: Path) -> list[str]:
    """The fenced ``python`` blocks of ``page``, in order."""
    return BLOCK.findall(page.read_text())


def _demonstration() -> dict[str, Any]:
    """A 2 s minimum-jerk reach in 3-D sampled at 2 ms (``t (T,)`` [s], ``X (T, 3)`` [m]), a start
    and two goals near it, and a collision stop on its first axis."""
    t = np.linspace(0.0, 2.0, 1001)
    s = t / t[-1]
    blend = 10 * s**3 - 15 * s**4 + 6 * s**5
    start, end = np.array([0.30, -0.20, 0.10]), np.array([0.55, 0.15, 0.35])
    X = start + blend[:, None] * (end - start)
    return {"t": t, "X": X, "x0": start + 0.02, "goal": end, "new_goal": end + np.array([0.05, -0.05, 0.0]),
            "dim": 0, "x_ob": 0.5, "side": 1.0}


def _recording(tmp: Path) -> dict[str, Any]:
    """``run.mcap`` in the working directory: two arm states on ``psm/arm/state``."""
    from experiments.harness import TraceWriter
    from services.bus.messages import ArmState

    with TraceWriter(tmp / "run.mcap") as w:
        for tick in (0, 1):
            w.write("psm/arm/state", ArmState(stamp_ns=2_000_000 * tick, tick=tick), 2_000_000 * tick)
    return {}


def _echo_service(tmp: Path) -> dict[str, Any]:
    """What the skeleton example of ``docs/architecture.md`` takes from its module."""
    from services.bus.config import load_config
    from services.bus.echo import EchoConfig
    from services.bus.runtime import Service, ServiceApp

    return {"ServiceApp": ServiceApp, "Service": Service, "EchoConfig": EchoConfig,
            "load_config": load_config}


#: (page relative to the repository, index of the block on it) → the names the block uses
#: without defining them.
GIVEN: dict[tuple[str, int], Callable[[Path], dict[str, Any]]] = {
    ("README.md", 0): lambda tmp: _demonstration(),
    ("docs/psm.md", 0): lambda tmp: _demonstration(),
    ("docs/arm.md", 0): lambda tmp: {},
    ("docs/bus.md", 0): lambda tmp: {},
    ("docs/bus.md", 1): lambda tmp: {},
    ("docs/bus.md", 2): _recording,
    ("docs/architecture.md", 0): _echo_service,
}


def _examples() -> list[Any]:
    return [pytest.param(str(page.relative_to(ROOT)), i, code, id=f"{page.relative_to(ROOT)}[{i}]")
            for page in PAGES for i, code in enumerate(python_blocks(page))]


def test_every_example_is_run() -> None:
    assert {tuple(p.values[:2]) for p in _examples()} == set(GIVEN)


@pytest.mark.parametrize(("page", "index", "code"), _examples())
def test_the_example_runs(page: str, index: int, code: str, tmp_path: Path,
                          monkeypatch: pytest.MonkeyPatch) -> None:
    import services.bus.runtime as runtime

    ran: list[Any] = []
    monkeypatch.setattr(runtime, "run_service", lambda app, **_: ran.append(app) or 0)
    # The examples name repository files relative to its root ("configs/stack.toml") and write
    # or read their own files ("model.json", "run.mcap") in the working directory.
    names = GIVEN[(page, index)](tmp_path)
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, Any] = {"__name__": f"example_{index}", "run_service": runtime.run_service, **names}
    exec(compile(code, f"{page}[{index}]", "exec"), namespace)
    if "run_service(" in code:  # a service example builds its service and hands it over
        assert len(ran) == 1 and isinstance(ran[0], runtime.ServiceApp), ran
