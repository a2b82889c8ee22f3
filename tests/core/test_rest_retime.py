"""Rest retiming (``rest_retime``): a motion held still for a while goes on at its nominal pace.

The demonstration: x a minimum-jerk stroke of 0.4 m over 2 s; y dips to -6 cm (a reversal, at
rest, at t = 1 s) and then rises by 16 cm, both halves 1 s long. Held still (v = 0, position
kept) for 0.4 s at any time, the motion should end 0.4 s late: nominal duration + hold.
"""

from __future__ import annotations

import numpy as np
import pytest
from trajectories import minimum_jerk

from psm import PhaseSpaceModel

DT = 0.002
DURATION = 2.0
HOLD_S = 0.4


def _demo() -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, DURATION + DT / 2, DT)
    s = t / DURATION
    x = 0.4 * minimum_jerk(t, DURATION)
    first = -0.06 * np.sin(np.pi * s) ** 2
    second = -0.06 + 0.16 * minimum_jerk(t - 0.5 * DURATION, 0.5 * DURATION)
    return t, np.column_stack([x, np.where(s < 0.5, first, second)])


class _Hold:
    """Held still (position kept, v = 0) from ``t0`` [s] for :data:`HOLD_S`."""

    def __init__(self, t0: float) -> None:
        self.t0, self._x = t0, None

    def __call__(self, t: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.t0 <= t < self.t0 + HOLD_S:
            if self._x is None:
                self._x = x.copy()
            return self._x.copy(), np.zeros_like(v)
        return x, v


@pytest.fixture(scope="module")
def model() -> PhaseSpaceModel:
    t, x = _demo()
    return PhaseSpaceModel.fit(t, x)


@pytest.mark.parametrize("t0", [0.3, 0.45, 0.8, 1.2])
def test_a_held_motion_ends_one_hold_late(model: PhaseSpaceModel, t0: float) -> None:
    _t, x = _demo()
    r = model.rollout(dt=DT, max_duration=8.0, disturbance=_Hold(t0), rest_retime=True)
    assert r.done
    assert np.abs(r.x[-1] - x[-1]).max() < 1e-3
    assert DURATION + HOLD_S - 0.02 <= r.t[-1] <= DURATION + HOLD_S + 0.1, r.t[-1]


def test_without_it_a_dimension_held_short_of_its_reversal_crawls(model: PhaseSpaceModel) -> None:
    # Held at 0.8 s, y is 1 cm short of its reversal (at rest there): from rest it crawls on the
    # stability margin, and the synchronisation holds x back for it.
    r = model.rollout(dt=DT, max_duration=8.0, disturbance=_Hold(0.8), rest_retime=False)
    assert r.done and r.t[-1] > DURATION + HOLD_S + 0.5, r.t[-1]


def test_it_is_on_by_default_and_leaves_an_undisturbed_motion_alone(model: PhaseSpaceModel) -> None:
    a = model.rollout(dt=DT)
    b = model.rollout(dt=DT, rest_retime=True)
    c = model.rollout(dt=DT, rest_retime=False)
    assert np.array_equal(a.x, b.x)
    assert len(c.x) == len(a.x) and np.abs(c.x - a.x).max() < 1e-6
