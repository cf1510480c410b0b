"""When a fine-tune's stretches stop: a mirror level's (``levels.tune``) and the upload's own against its
photographs (``refine``) run in stretches of a quarter of their steps and stop after one that gains too little, or
from which, by the rate model, the archive could no longer shrink."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..views import ViewSet, evaluate
from .encode import Rate
from .state import LevelState

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


class Stretches:
    """A fine-tune's ``keep_going`` (``optimize_level``) for ``iterations`` steps in stretches of a quarter of them,
    from a state of fitting PSNR ``start``: each stretch's end is rendered on the fitting views, and the fine-tune goes
    on while the stretch gained at least ``MIN_GAIN_DB`` and, with ``pace``, while that says it may still pay (``cut``
    then tells that the pace stopped it)."""

    def __init__(self, views: ViewSet, start: float, iterations: int, pace: Pace | None = None) -> None:
        self.views, self.pace = views, pace
        self.every = max(iterations // 4, 1)
        self.left = math.ceil(iterations / self.every)
        self.best, self.cut = start, False
        self.judged: tuple[int, float] | None = None  # (steps, fitting PSNR) at the last stretch's end

    def __call__(self, so_far: LevelState) -> bool:
        psnr = self._fitting(so_far)
        steps = self.every if self.judged is None else self.judged[0] + self.every
        self.judged = (steps, psnr)
        gained, self.best = psnr - self.best, max(self.best, psnr)
        self.left -= 1
        if self.pace is not None and not self.pace(self.best, gained, self.left):
            self.cut = True
            return False
        return gained >= MIN_GAIN_DB

    def fitting_psnr(self, tuned: LevelState, run: int) -> float:
        """The fitting PSNR of the state the fine-tune returned after ``run`` steps: the last stretch's, when the
        fine-tune stopped there, else rendered."""
        if self.judged is not None and self.judged[0] == run:
            return self.judged[1]
        return self._fitting(tuned)

    def _fitting(self, state: LevelState) -> float:
        return evaluate(state.expanded(), self.views.fit, self.views.background, with_ssim=False).worst
