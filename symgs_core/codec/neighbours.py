"""Attribute symbols predicted from Gaussians decoded before them, so that only the residual is coded.

Nearby Gaussians of a trained scene have alike sizes, and somewhat alike opacities and colours. A Gaussian's
neighbours here are the nearest (by decoded position) of the ``WINDOW`` Gaussians before it in the coding order of
its own step class: positions are decoded before every other attribute, and a class's rows are on one grid, so a
reader finds the same neighbours, and has decoded their symbols, before it reads the Gaussian's. The prediction is
the mean of the first ``count`` of them (rounded half up, exactly in integers); the first Gaussians of a class,
with fewer before them, average what there is (the very first is predicted 0).

Measured on the archives of the codec benchmark at the high preset (symbols coded as they are against residuals,
the entropy coder's own choice of order-0 models or differences either way): log-scales 4-6% smaller on the fox
capture, the lego, the donut and the plush toy (the mean of 3); opacities 3% on the fox capture and nothing on the
donut; DC colour under 1%, or larger; rotations larger (their components are relative to each one's largest axis).
So each quantising section that takes a prediction codes its symbols both ways and keeps the smaller
(params ``predict``: the count, 0 for none).

Positions are compared in float64 from their decoded float32 values: those differences and squares are exact,
and the sums are rounded the same way on every IEEE machine; equal distances go to the Gaussian nearer in order.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import prange

from ..compiled import compiled, compiled_parallel
from .classes import groups
from .errors import ArchiveError

WINDOW = 32  # Gaussians before one, in its class's coding order, among which its neighbours are sought
MOST = 3  # neighbours a prediction may average (params ``predict`` in 0..MOST)
COUNTS = (1, MOST)  # the predictions an encoder tries beside none: the nearest alone, or the mean of MOST


@compiled_parallel
def _nearest_before(points: np.ndarray, window: int, most: int) -> np.ndarray:  # pragma: no cover - numba
    """[M, most] int64: each row's nearest ``most`` among the ``window`` rows before it, nearest first, -1 where
    fewer."""
    m = points.shape[0]
    out = np.full((m, most), -1, dtype=np.int64)
    for i in prange(m):
        best = np.full(most, np.inf)
        found = 0
        for j in range(i - 1, max(0, i - window) - 1, -1):  # back from i: a tie keeps the nearer in order
            d = 0.0
            for a in range(3):
                diff = points[i, a] - points[j, a]
                d += diff * diff
            if found == most and d >= best[most - 1]:
                continue
            k = min(found, most - 1)
            while k > 0 and best[k - 1] > d:
                best[k] = best[k - 1]
                out[i, k] = out[i, k - 1]
                k -= 1
            best[k] = d
            out[i, k] = j
            found = min(found + 1, most)
    return out


@compiled
def _prediction(symbols: np.ndarray, index: np.ndarray, i: int, col: int, count: int) -> int:  # pragma: no cover
    """Row ``i``'s prediction in column ``col``: the mean of ``symbols`` at its first ``count`` neighbours (those
    it has), rounded half up; 0 without any."""
    used, total = 0, 0
    for k in range(count):
        if index[i, k] >= 0:
            used += 1
            total += symbols[index[i, k], col]
    return (total + used // 2) // used if used else 0


@compiled_parallel
def _residuals(q: np.ndarray, index: np.ndarray, count: int) -> np.ndarray:  # pragma: no cover - numba
    out = np.empty_like(q)
    for i in prange(q.shape[0]):
        for col in range(q.shape[1]):
            out[i, col] = q[i, col] - _prediction(q, index, i, col, count)
    return out


@compiled
def _restore(residuals: np.ndarray, index: np.ndarray, count: int) -> np.ndarray:  # pragma: no cover - numba
    """Inverse of ``_residuals``: row by row, each from rows before it."""
    out = np.empty_like(residuals)
    for i in range(residuals.shape[0]):
        for col in range(residuals.shape[1]):
            out[i, col] = residuals[i, col] + _prediction(out, index, i, col, count)
    return out


@dataclass(frozen=True, eq=False)
class Neighbours:
    """The neighbours a reader finds by the decoded positions ``points`` [N, 3] float32 of the stored set in coding
    order and its step classes [N] (None: one class); searched on first use, so sections that predict nothing cost
    no search."""

    points: np.ndarray
    classes: np.ndarray | None

    @cached_property
    def index(self) -> np.ndarray:
        """[N, MOST] int64: each Gaussian's nearest ``MOST`` among the ``WINDOW`` before it in its class, as indices
        into the whole set (nearest first; -1 where there are fewer)."""
        index = np.full((len(self.points), MOST), -1, dtype=np.int64)
        coords = self.points.astype(np.float64)
        for rows in groups(self.classes, len(self.points)):
            if len(rows):
                local = _nearest_before(np.ascontiguousarray(coords[rows]), WINDOW, MOST)
                index[rows] = np.where(local >= 0, rows[np.maximum(local, 0)], -1)
        return index

    def residuals(self, q: np.ndarray, count: int) -> np.ndarray:
        """Symbols ``q`` [N, C] int64 less their prediction from the first ``count`` neighbours."""
        return _residuals(np.ascontiguousarray(q, dtype=np.int64), self.index, count)

    def restore(self, residuals: np.ndarray, count: int, limit: int, what: str) -> np.ndarray:
        """Inverse of ``residuals``; ArchiveError if a symbol lands ``limit`` cells or more from zero (residuals of
        hostile bytes can add up along the chain)."""
        q = _restore(np.ascontiguousarray(residuals, dtype=np.int64), self.index, count)
        if q.size and int(np.abs(q).max()) >= limit:
            raise ArchiveError("corrupt_section", f"{what}: predicted symbols reach {limit} grid cells")
        return q


def check_count(count: object, codec: str) -> None:
    """ArchiveError unless ``count`` (params ``predict``) is an integer in 0..MOST."""
    if type(count) is not int or not 0 <= count <= MOST:
        raise ArchiveError("bad_header", f"{codec}: parameter predict={count!r:.40} must be an integer in 0..{MOST}")
