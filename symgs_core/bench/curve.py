"""Our rate-distortion curve and what it says at another format's fidelity.

The curve is the Pareto front of our runs' (bytes, PSNR) points: a run that another beats on both counts is not
on it. Between two neighbouring points of the front, log bytes are linear in PSNR (the usual rate-distortion
reading: each dB costs a fixed fraction more bytes). Outside the front's PSNR range nothing is inferred: the
interpolation never extrapolates, and a figure it cannot give is None. A lossless run (+inf dB, or at least
``metrics.LOSSLESS_DB``, where the error is float rounding) is no point of the curve: nothing lies between it and the
lossy runs to interpolate along; it still counts as reaching any PSNR (``smallest_reaching``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from ..metrics import LOSSLESS_DB

Point = tuple[float, float | None]  # (bytes, PSNR dB); PSNR +inf: identical renders, None: no figure


def front(points: Iterable[Point]) -> list[tuple[float, float]]:
    """The lossy points no other point beats (fewer or equal bytes at higher or equal PSNR, one strictly), by
    increasing PSNR; bytes then increase too. A PSNR of None (no figure) is left out."""
    finite = {(b, p) for b, p in points if p is not None and p < LOSSLESS_DB and b > 0}
    ordered = sorted(finite, key=lambda x: (x[1], -x[0]))
    kept: list[tuple[float, float]] = []
    for b, p in reversed(ordered):  # from the highest PSNR down: keep a point only if it is smaller than all above
        if not kept or b < kept[-1][0]:
            kept.append((b, p))
    return kept[::-1]


def size_at(points: Iterable[Point], psnr: float) -> float | None:
    """Bytes on the curve at ``psnr`` dB (log-bytes interpolation between the front's neighbours); None outside the
    front's PSNR range or when the front is empty."""
    curve = front(points)
    if not curve or not curve[0][1] <= psnr <= curve[-1][1]:
        return None
    for (b0, p0), (b1, p1) in zip(curve, curve[1:]):
        if p0 <= psnr <= p1:
            t = 0.0 if p1 == p0 else (psnr - p0) / (p1 - p0)
            return math.exp(math.log(b0) + t * (math.log(b1) - math.log(b0)))
    return curve[0][0]  # a one-point front, at exactly its PSNR


def smallest_reaching(points: Iterable[Point], psnr: float) -> float | None:
    """The fewest bytes with which the curve reaches at least ``psnr`` dB: an actual point at or above it, or the
    interpolated size at it, whichever is smaller; None when no point reaches it."""
    points = list(points)
    reached = [b for b, p in points if p is not None and p >= psnr]
    candidates = reached + ([s] if (s := size_at(points, psnr)) is not None else [])
    return min(candidates) if candidates else None


def spans(points: Iterable[Point], psnr: float) -> bool:
    return size_at(points, psnr) is not None
