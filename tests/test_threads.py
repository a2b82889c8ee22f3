"""BLAS thread limits: a block at one thread rounds as a service does, and the count comes back."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from services.threads import _OPENBLAS_GETTERS, _loaded_libraries, blas_threads


def _counts() -> list[int]:
    out = []
    for path in _loaded_libraries("openblas"):
        lib = ctypes.CDLL(path)
        for name in _OPENBLAS_GETTERS:
            getter = getattr(lib, name, None)
            if getter is not None:
                getter.restype = ctypes.c_int
                out.append(int(getter()))
                break
    return out


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
