"""The PSNR axis every chart shares: a finite range that fits the figures that matter, lossless ones drawn apart.

A lossless result (identical renders: +inf dB), or one so close that its error is rounding noise (at least
``LOSSLESS_DB``), would stretch the axis until the range where formats differ is unreadable. Such points are drawn
in a band above the finite range, marked "lossless" instead of a number, past a dotted line.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

from matplotlib.axes import Axes

from ..metrics import LOSSLESS_DB

LOSSLESS_LABEL = "lossless"


def is_lossless(psnr: float | None) -> bool:
    """None and +inf stand for identical renders."""
    return psnr is None or not math.isfinite(psnr) or psnr >= LOSSLESS_DB


def psnr_axis(ax: Axes, values: Iterable[float | None], floor: float | None = None) -> Callable[[float | None], float]:
    """Set ``ax``'s y range over the finite PSNRs (and ``floor``); returns the y at which to draw a PSNR, the band
    above the range for lossless ones."""
    values = list(values)
    finite = [v for v in values if v is not None and not is_lossless(v)]  # None is lossless
    finite += [floor] if floor is not None and math.isfinite(floor) else []
    lo, hi = (min(finite), max(finite)) if finite else (0.0, 1.0)
    pad = max(0.08 * (hi - lo), 0.5)
    if not any(is_lossless(v) for v in values):
        ax.set_ylim(lo - pad, hi + pad)
        return lambda v: float(v)  # type: ignore[arg-type]
    top = hi + 2.5 * pad
    ax.set_ylim(lo - pad, top + pad)
    ticks = [t for t in ax.get_yticks() if lo - pad <= t <= hi + pad]
    ax.set_yticks([*ticks, top], [f"{t:g}" for t in ticks] + [LOSSLESS_LABEL])
    ax.axhline(hi + 1.25 * pad, color="#999999", linewidth=0.8, linestyle=":")
    return lambda v: top if is_lossless(v) else float(v)  # type: ignore[arg-type]
