"""Compiling numba kernels: the detection's and the codec's neighbour predictions."""

from __future__ import annotations

from numba import njit


def compiled(fn):  # noqa: ANN001, ANN201 - a numba kernel
    """``fn`` compiled on first use and cached between processes; without a writable cache location, compiled in
    memory. One thread: for short kernels, and those whose output order depends on the order they run in."""
    try:
        return njit(cache=True, nogil=True)(fn)
    except RuntimeError:
        return njit(nogil=True)(fn)


def compiled_parallel(fn):  # noqa: ANN001, ANN201 - a numba kernel
    """``compiled``, with ``numba.prange`` loops split over the cores: for passes over every Gaussian or pair whose
    rows are independent (the result does not depend on how they are split)."""
    try:
        return njit(cache=True, nogil=True, parallel=True)(fn)
    except RuntimeError:
        return njit(nogil=True, parallel=True)(fn)
