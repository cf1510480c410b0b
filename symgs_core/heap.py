"""The C heap while a job runs: freed blocks kept for reuse instead of handed back to the system at once.

A job at a million Gaussians allocates and frees arrays of tens to hundreds of MB for every render and every rate
estimate (projected Gaussians, per-intersection gradients, float64 copies of a million SH rows). glibc maps each block
above its mmap threshold (32 MiB at most) afresh and unmaps it when freed, so the kernel zeroes every page again on
first touch: at 1M Gaussians, 39 s of system time in 270 s of CPU. While a job runs (``kept``), blocks come from the
heap and freed ones stay there (``mallopt``: no mmap, no trimming): 9 s of system time, the job 0.83x the wall time,
for a peak 15% higher (2.87 -> 3.30 GiB; BENCHMARKS "Scale"). When the last job of the process ends, the heap's free
pages go back to the system (``malloc_trim``), so an idle worker holds no more than it did before. The same values
are computed either way; with another C library nothing changes.

Every thread allocates from the one heap (``one_arena``). glibc gives a thread that allocates while another holds the
heap an arena of its own, and with nothing trimmed each arena keeps its own high-water mark: what the coding threads
freed (a section's layouts and their zstd output, a rung's trial encodes) could not serve the main thread, nor what
it freed (the rate model, after the levels) the coding threads. A trainer-like 1M scene with SH degree 3 (BENCHMARKS,
"Scale: a scene as a trainer writes it") peaked at 3.7-4.8 GiB over three runs with one arena and at 5.95 GiB with
glibc's arenas, at the same code and the same bytes; the time changed within the machine's noise.
"""

from __future__ import annotations

import ctypes
import functools
import platform
import threading
from collections.abc import Iterator
from contextlib import contextmanager

# mallopt parameters and glibc's defaults (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8
_DEFAULT_TRIM_THRESHOLD, _DEFAULT_MMAP_MAX = 128 * 1024, 65536
_KEEP_UP_TO = (1 << 31) - 1  # bytes of free heap top kept (mallopt takes an int)

_lock = threading.Lock()
_jobs = 0  # jobs of this process inside ``kept``: the heap returns to the defaults when the last one leaves


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The process's own C library where it is glibc (the calls below are glibc's)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt.argtypes, libc.malloc_trim.argtypes = [ctypes.c_int, ctypes.c_int], [ctypes.c_size_t]
    except (OSError, AttributeError):
        return None
    return libc


@functools.cache
def one_arena() -> None:
    """Every thread of this process allocates from the main heap from now on. For the process's life: glibc fixes
    the limit once a thread has been given an arena under it. A thread that already has an arena keeps it, so a
    process that forks its job processes (a Celery worker) calls this before it starts a thread: a fork's child
    hands its parent's idle arenas to its own new threads before any limit applies."""
    libc = _glibc()
    if libc is not None:
        libc.mallopt(_M_ARENA_MAX, 1)


@contextmanager
def kept() -> Iterator[None]:
    """Freed memory stays in the heap inside the block (every thread of the process); on leaving the last one, the
    default limits are back and the free pages are returned to the system. Two settings are not glibc's defaults
    after: the one arena (``one_arena``), and, once a limit has been set, glibc no longer raises its mmap threshold
    as large blocks are freed (it stays where it had reached), so blocks of up to 32 MiB may still be mapped on their
    own."""
    global _jobs
    libc = _glibc()
    if libc is None:
        yield
        return
    with _lock:
        if _jobs == 0:
            one_arena()
            libc.mallopt(_M_MMAP_MAX, 0)
            libc.mallopt(_M_TRIM_THRESHOLD, _KEEP_UP_TO)
        _jobs += 1
    try:
        yield
    finally:
        with _lock:
            _jobs -= 1
            if _jobs == 0:
                libc.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX)
                libc.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_THRESHOLD)
                libc.malloc_trim(0)
