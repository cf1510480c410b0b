"""Morton (Z-order) codes of 3D grid cells: the 21 bits of each coordinate interleaved into one non-negative int64
(x lowest), so that cells near each other mostly sort near each other. The codec codes positions by them
(``codec.morton``); detection walks its points in their order (``detect.membership``)."""

from __future__ import annotations

import numpy as np

AXIS_BITS = 21  # 3 x 21 bits fill a non-negative int64


def _spread(v: np.ndarray) -> np.ndarray:
    """Each of the low 21 bits of ``v`` (int64) moved to bit 3k."""
    v = v.astype(np.int64) & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    return (v | (v << 2)) & 0x1249249249249249


def _compact(v: np.ndarray) -> np.ndarray:
    """Inverse of ``_spread``: bits 3k of ``v`` gathered into the low 21 bits."""
    v = v & 0x1249249249249249
    v = (v | (v >> 2)) & 0x10C30C30C30C30C3
    v = (v | (v >> 4)) & 0x100F00F00F00F00F
    v = (v | (v >> 8)) & 0x1F0000FF0000FF
    v = (v | (v >> 16)) & 0x1F00000000FFFF
    return (v | (v >> 32)) & 0x1FFFFF


def interleave(cells: np.ndarray) -> np.ndarray:
    """Morton codes [N] int64 of grid cells [N, 3] (each coordinate in 0 .. 2^21 - 1)."""
    return _spread(cells[:, 0]) | (_spread(cells[:, 1]) << 1) | (_spread(cells[:, 2]) << 2)


def deinterleave(codes: np.ndarray) -> np.ndarray:
    """Grid cells [N, 3] int64 of Morton codes [N]."""
    return np.stack([_compact(codes), _compact(codes >> 1), _compact(codes >> 2)], axis=1)
