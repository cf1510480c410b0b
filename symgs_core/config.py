"""Settings of the compression pipeline: one frozen object, passed down, never mutated."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

Preset = Literal["small", "balanced", "high", "lossless"]
DeviceChoice = Literal["auto", "cpu", "cuda"]
# Each preset's budget (dB) when none is given: what the command line and the service default to.
PRESET_BUDGETS: dict[str, float] = {"small": 1.0, "balanced": 0.3, "high": 0.1, "lossless": 0.0}


@dataclass(frozen=True)
class CompressConfig:
    """What a compression job may spend and must keep.

    preset        attribute codec and reductions (``PRESET_BUDGETS``): ``lossless`` stores float32 and spends the
                  budget on mirrors alone; the others share it between mirrors, pruning, SH reduction and
                  quantisation (``budget.SHARES``), from coarse starting steps (small) to fine ones (high).
    psnr_budget   dB of held-out PSNR all lossy stages together may cost, below the uncompressed scene.
    nominal_psnr  fidelity (dB) a trained scene typically has against its own photographs (3DGS scores about 27.5
                  on Mip-NeRF 360, 29.5 on Deep Blending, 33 on NeRF-Synthetic). Without test images the reference
                  is a render of the input, against which the input scores +inf; the budget then becomes the error
                  that, added to a scene of this nominal quality, would cost ``psnr_budget`` dB.
    max_levels    cap on mirror levels; the scene decides how many below the cap pay for themselves.
    iterations    optimisation steps per level.
    train_views / eval_views  self-supervised camera counts (images given: their own train/test split).
    resolution    longest side, in pixels, of the views rendered for optimisation and evaluation.
    pictures      draw the job's PNG pictures and charts into ``CompressResult.images``.
    """

    preset: Preset = "lossless"
    psnr_budget: float = 0.5
    nominal_psnr: float = 30.0
    max_levels: int = 4
    iterations: int = 200
    train_views: int = 128
    eval_views: int = 8
    resolution: int = 192
    device: DeviceChoice = "auto"
    use_mirrors: bool = True
    pictures: bool = True
    seed: int = 0
    detect: dict = field(default_factory=dict)  # overrides of DetectConfig fields

    def __post_init__(self) -> None:
        if self.preset not in PRESET_BUDGETS:
            raise ValueError(f"preset must be one of {sorted(PRESET_BUDGETS)}, got {self.preset!r}")
        if not 0 <= self.psnr_budget <= 60:
            raise ValueError(f"psnr_budget must be in 0..60 dB, got {self.psnr_budget}")
        if not 0 <= self.max_levels <= 16:
            raise ValueError(f"max_levels must be in 0..16, got {self.max_levels}")
        if not 0 <= self.iterations <= 100_000:
            raise ValueError(f"iterations must be in 0..100000, got {self.iterations}")
        if not (1 <= self.train_views <= 1000 and 1 <= self.eval_views <= 1000):
            raise ValueError("train_views and eval_views must be in 1..1000")
        if not 16 <= self.resolution <= 4096:
            raise ValueError(f"resolution must be in 16..4096, got {self.resolution}")

    def self_supervised_floor(self) -> float:
        """Minimum PSNR (dB) against renders of the input that keeps the loss within the budget."""
        excess = 10.0 ** (self.psnr_budget / 10.0) - 1.0
        return math.inf if excess <= 0 else self.nominal_psnr - 10.0 * math.log10(excess)
