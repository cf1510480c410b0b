"""When a fine-tune's stretches stop: a mirror level's (``levels.tune``) and the upload's own against its
photographs (``refine``) run in stretches of a quarter of their steps and stop after one that gains too little, or
from which, by the rate model, the archive could no longer shrink."""

from __future__ import annotations

from dataclasses import dataclass

from .encode import Rate

# A fine-tune goes on in stretches of a quarter of ``iterations`` while each stretch gains at least this much.
MIN_GAIN_DB = 0.05


@dataclass(frozen=True)
class Pace:
    """Whether a fine-tune may still pay from where a stretch left it: were every stretch to come to gain as much as
    the last (a fine-tune's stretches gain less and less as its learning rates decay, so that is the most it may
    reach), would the state hold the floor and, by the rate model (``rate``; None: the floor alone), make an archive
    smaller than ``best_bytes``? ``now``: the archive of the state the fine-tune starts from (fitting PSNR ``psnr``),
    scaled to the Gaussians it keeps."""

    floor: float
    rate: Rate | None
    psnr: float
    now: float
    best_bytes: int

    def __call__(self, reached: float, gained: float, stretches_left: int) -> bool:
        reach = reached + max(gained, 0.0) * stretches_left
        if reach < self.floor:
            return False
        return self.rate is None or self.now * self.rate(self.psnr, reach) < self.best_bytes
