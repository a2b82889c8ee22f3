"""Threads of a service process: the native libraries' worker pools (OpenBLAS, OpenCV), the
real-time scheduling class of the control loop's processes and the machine's CPU wake-up
latency (:class:`CpuLatencyRequest`).

OpenBLAS (bundled with numpy and, separately, with scipy) and OpenCV start a pool of worker
threads per process and hand even tiny operations to it: scipy's LAPACK ``potri`` on the arm's
6×6 matrix runs ``dlauum`` in parallel. After each call the pool's threads busy-wait for the
next piece of work; a loop that calls the library every 2 ms therefore keeps a worker on the
CPU all the time (measured: the idle arm at ~100 % of a core, ~7 % with one thread). The
services do small operations at a high rate, so they run these libraries single-threaded.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import struct
from collections.abc import Iterator
from typing import Any

#: Setter symbols of the OpenBLAS builds in use (plain, numpy's ILP64 and scipy's prefixed ones).
_OPENBLAS_SETTERS = (
    "openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "scipy_openblas_set_num_threads64_",
)


def _loaded_libraries(fragment: str) -> list[str]:
    """Paths of the shared objects mapped into this process whose name contains ``fragment``."""
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if ".so" in line}
    except OSError:
        return []
    return sorted(p for p in paths if fragment in p.rsplit("/", 1)[-1].lower())


#: Getter symbols matching :data:`_OPENBLAS_SETTERS`.
_OPENBLAS_GETTERS = tuple(name.replace("_set_", "_get_") for name in _OPENBLAS_SETTERS)


def openblas_thread_controls() -> list[tuple[str, Any, Any]]:
    """``(path, get, set)`` of every OpenBLAS loaded so far: its thread-count getter (None when
    the build has none) and setter. Linux only (reads ``/proc/self/maps``); elsewhere ``[]``."""
    out = []
    for path in _loaded_libraries("openblas"):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in zip(_OPENBLAS_GETTERS, _OPENBLAS_SETTERS, strict=True):
            setter = getattr(lib, set_name, None)
            if setter is not None:
                setter.argtypes, setter.restype = [ctypes.c_int], None
                getter = getattr(lib, get_name, None)
                if getter is not None:
                    getter.restype = ctypes.c_int
                out.append((path, getter, setter))
                break
    return out


def limit_blas_threads(n: int = 1) -> list[str]:
    """Set every OpenBLAS loaded so far to ``n`` threads; returns the libraries changed.

    Call it after numpy/scipy's linear algebra is imported (a library loaded later keeps its
    default). Linux only (reads ``/proc/self/maps``); elsewhere it does nothing."""
    changed = []
    for path, _, setter in openblas_thread_controls():
        setter(int(n))
        changed.append(path)
    return changed


@contextlib.contextmanager
def blas_threads(n: int = 1) -> Iterator[None]:
    """Run the block (or the decorated function) with every OpenBLAS loaded so far at ``n``
    threads, then restore each one's count. A computation that must round as a service's does
    (the services run BLAS on one thread: :func:`limit_blas_threads`) runs in it: OpenBLAS's
    threaded kernels sum in another order, so even small products can differ in the last bit."""
    previous = [(setter, int(getter())) for _, getter, setter in openblas_thread_controls()
                if getter is not None]
    for setter, _ in previous:
        setter(int(n))
    try:
        yield
    finally:
        for setter, count in previous:
            setter(count)


def limit_opencv_threads(n: int = 1) -> None:
    """Run OpenCV's parallel loops on ``n`` threads (1: on the calling thread, no pool)."""
    import cv2

    cv2.setNumThreads(int(n))


def set_realtime_priority(priority: int, clock: str = "realtime") -> str:
    """Switch the calling process to ``SCHED_FIFO`` at ``priority`` (threads created afterwards,
    e.g. Zenoh's, inherit it). Returns ``""`` on success, else why it was not possible.

    Only on the ``realtime`` clock: a lockstep loop has no deadline and runs as fast as it can,
    so at real-time priority it would take the CPU from every other process (the goal tracker,
    the recorder) for as long as it runs."""
    if priority <= 0 or clock != "realtime":
        return ""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        return f"cannot set SCHED_FIFO priority {priority}: {exc}"
    return ""


#: The kernel's PM QoS interface for the CPUs' wake-up latency (docs/arm.md#cpu-wake-up-latency).
CPU_DMA_LATENCY = "/dev/cpu_dma_latency"


class CpuLatencyRequest:
    """Asks the kernel to keep every CPU's wake-up latency at most ``latency_us`` [µs] while this
    object is open: the PM QoS request of ``/dev/cpu_dma_latency`` (held as long as the file
    stays open, dropped when it is closed or the process ends), as ``cyclictest`` does. The
    cpuidle governor then uses no idle state with a longer exit latency; at 0 an idle CPU polls
    instead of halting. That costs power (and, in a virtual machine, the host's CPU time) and
    buys faster wake-ups: a thread woken by a timer or a socket does not wait for its CPU to
    leave an idle state, or on a virtual CPU for the hypervisor to resume it.

    ``latency_us`` < 0: no request (the machine's idle states apply). :attr:`problem` is ``""``
    when the request is held, else why it could not be made (no permission: root or write
    access to the file is needed)."""

    def __init__(self, latency_us: int, path: str = CPU_DMA_LATENCY) -> None:
        self.latency_us = int(latency_us)
        self.problem = ""
        self._fd: int | None = None
        if self.latency_us < 0:
            return
        try:
            fd = os.open(path, os.O_WRONLY)
        except OSError as exc:
            self.problem = f"cannot request a CPU wake-up latency of {self.latency_us} us: {exc}"
            return
        try:
            os.write(fd, struct.pack("=i", self.latency_us))
        except OSError as exc:
            os.close(fd)
            self.problem = f"cannot request a CPU wake-up latency of {self.latency_us} us: {exc}"
            return
        self._fd = fd

    @property
    def held(self) -> bool:
        """True while the request is in force."""
        return self._fd is not None

    def close(self) -> None:
        """Drop the request (idempotent)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None
