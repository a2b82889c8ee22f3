"""BLAS thread limits: a block at one thread rounds as a service does, and the count comes back."""

from __future__ import annotations

import numpy as np
import pytest

from services.threads import blas_threads, openblas_thread_controls


def _counts() -> list[int]:
    return [int(get()) for _, get, _ in openblas_thread_controls() if get is not None]


def test_blas_threads_sets_the_count_inside_the_block_and_restores_it() -> None:
    np.ones((4, 4)) @ np.ones((4, 4))  # numpy's OpenBLAS is loaded
    before = _counts()
    if not before:
        pytest.skip("no OpenBLAS with a thread-count getter in this process")
    with blas_threads(1):
        assert _counts() == [1] * len(before)
    assert _counts() == before
    with pytest.raises(RuntimeError), blas_threads(1):
        raise RuntimeError("restored on error too")
    assert _counts() == before

    @blas_threads(1)
    def inside() -> list[int]:
        return _counts()

    assert inside() == [1] * len(before) and _counts() == before
