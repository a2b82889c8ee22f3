"""What a benchmark report records about the computer it ran on, so that two runs can be matched.

A virtual machine may run on different host CPUs from one session to the next. numpy picks its
SIMD kernels at run time from the CPU's features, so the same code on the same inputs can give
different timings and, where a kernel sums in another order, results that differ in the last
digits (seen here: the learner's LASA figures of two runs of the same code differed in the
third digit for a few shapes, while a third run matched the first bit for bit). A report
therefore names the CPU model, its vector extensions, numpy's dispatched SIMD targets and the
numeric libraries' versions.

    from benchmarks.host import host_info, host_line
    info = host_info()        # into the report's JSON
    host_line(info)           # "Intel(R) Xeon(R) Processor, AVX-512; numpy 2.4.6 (SIMD ...), ..."
"""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

#: The CPU flags (``/proc/cpuinfo``) that decide which numeric kernels run.
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl",
              "avx512_vnni", "avx512_bf16", "amx_tile", "asimd", "sve")


def _cpuinfo(path: Path = Path("/proc/cpuinfo")) -> tuple[str, list[str]]:
    """``(model name, flags)`` of the first CPU listed (``("", [])`` where unreadable)."""
    model, flags = "", []
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return model, flags
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key in ("model name", "Model") and not model:
            model = value.strip()
        elif key in ("flags", "Features") and not flags:
            flags = value.split()
        if model and flags:
            break
    return model, flags


def host_info() -> dict[str, Any]:
    """The machine and numeric stack: ``machine``, ``cpus``, ``cpu_model``, ``cpu_simd`` (the
    :data:`SIMD_FLAGS` the CPU has), ``numpy``, ``numpy_simd`` (numpy's run-time dispatch
    targets this CPU supports), ``scipy``, ``python``."""
    import numpy as np

    model, flags = _cpuinfo()
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
        numpy_simd = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    except ImportError:  # another numpy layout: the versions still identify the stack
        numpy_simd = []
    try:
        import scipy
        scipy_version = scipy.__version__
    except ImportError:
        scipy_version = ""
    return {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "cpu_model": model or platform.processor() or "unknown",
        "cpu_simd": [f for f in SIMD_FLAGS if f in flags],
        "numpy": np.__version__,
        "numpy_simd": numpy_simd,
        "scipy": scipy_version,
        "python": platform.python_version(),
    }


def host_line(info: dict[str, Any]) -> str:
    """One line for a report's header, e.g. ``CPU Intel(R) Xeon(R) Processor (avx2, avx512f, ...);
    numpy 2.4.6 (SIMD dispatch: AVX512F, AVX512_SKX), scipy 1.16.3``."""
    simd = ", ".join(info.get("cpu_simd") or []) or "no vector extensions listed"
    dispatch = ", ".join(info.get("numpy_simd") or []) or "baseline only"
    scipy = f", scipy {info['scipy']}" if info.get("scipy") else ""
    return (f"CPU {info.get('cpu_model', 'unknown')} ({simd}); numpy {info.get('numpy')} "
            f"(SIMD dispatch: {dispatch}){scipy}")
