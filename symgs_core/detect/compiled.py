"""Compiling the detection kernels (numba)."""

from __future__ import annotations

from numba import njit


def compiled(fn):  # noqa: ANN001, ANN201 - a numba kernel
    """``fn`` compiled on first use and cached between processes; without a writable cache location, compiled in
    memory. One thread: the kernels are short next to the KD-tree queries, and on a shared machine waiting for a
    second thread costs more than it saves."""
    try:
        return njit(cache=True, nogil=True)(fn)
    except RuntimeError:
        return njit(nogil=True)(fn)
