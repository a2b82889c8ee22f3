"""BLAS thread limits: a block at one thread rounds as a service does, and the count comes back.
The CPU wake-up latency request: held while open (read back from the kernel), dropped on close."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import pytest

from services.threads import CPU_DMA_LATENCY, CpuLatencyRequest, blas_threads, openblas_thread_controls


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


def _current_latency_us() -> int:
    with open(CPU_DMA_LATENCY, "rb") as f:
        return int(struct.unpack("=i", f.read(4))[0])


def test_a_cpu_latency_request_holds_while_open_and_is_dropped_on_close() -> None:
    if not os.access(CPU_DMA_LATENCY, os.W_OK):
        pytest.skip(f"{CPU_DMA_LATENCY} is not writable here (root is needed)")
    before = _current_latency_us()
    req = CpuLatencyRequest(7)
    try:
        assert req.held and req.problem == ""
        assert _current_latency_us() <= 7  # the kernel keeps the smallest request in force
    finally:
        req.close()
    req.close()  # idempotent
    assert not req.held
    assert _current_latency_us() == before


def test_no_request_below_zero_and_a_failed_one_says_why(tmp_path: Path) -> None:
    off = CpuLatencyRequest(-1)
    assert not off.held and off.problem == ""
    missing = CpuLatencyRequest(0, path=str(tmp_path / "no" / "such" / "file"))
    assert not missing.held
    assert missing.problem.startswith("cannot request a CPU wake-up latency of 0 us: ")
    target = tmp_path / "latency"
    target.write_bytes(b"")
    written = CpuLatencyRequest(25, path=str(target))  # what is written: a native int32
    written.close()
    assert target.read_bytes() == struct.pack("=i", 25)
