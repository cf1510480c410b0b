"""Clusters of Gaussians that could be mirror images of each other: same colour, opacity and (sorted) sizes."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..scene import GaussianScene
from ..sh import C0


@dataclass(frozen=True)
class Attributes:
    """Per-Gaussian attributes that a mirror leaves unchanged."""

    rgb: Tensor  # [N, 3] DC colour in [0, 1]
    opacity: Tensor  # [N] activated opacity
    log_scales: Tensor  # [N, 3] log-scales sorted ascending (axis order is arbitrary, so twins may differ in it)


@dataclass(frozen=True)
class Clusters:
    """Gaussians grouped by attribute bin; ``order`` lists them cluster after cluster."""

    order: Tensor  # [N] Gaussian indices, grouped by cluster
    starts: Tensor  # [K] position in ``order`` where each cluster begins
    sizes: Tensor  # [K] Gaussians per cluster


def attributes(scene: GaussianScene) -> Attributes:
    return Attributes(
        rgb=(0.5 + C0 * scene.sh_dc).clamp(0.0, 1.0),
        opacity=torch.sigmoid(scene.opacities),
        log_scales=scene.scales.sort(dim=1).values,
    )


def rgb_to_hsv(rgb: Tensor) -> Tensor:
    """HSV [N, 3] in [0, 1] of RGB [N, 3] in [0, 1]; hue 0 for greys."""
    r, g, b = rgb.unbind(-1)
    v, arg = rgb.max(dim=-1)
    c = v - rgb.min(dim=-1).values
    safe = torch.where(c > 0, c, torch.ones_like(c))
    h = torch.stack([(g - b) / safe % 6.0, (b - r) / safe + 2.0, (r - g) / safe + 4.0], dim=-1)
    h = torch.where(c > 0, h.gather(-1, arg[..., None])[..., 0] / 6.0, torch.zeros_like(v))
    s = torch.where(v > 0, c / torch.where(v > 0, v, torch.ones_like(v)), torch.zeros_like(v))
    return torch.stack([h, s, v], dim=-1)


def _bin(values: Tensor, lo: float, hi: float, bins: int) -> Tensor:
    width = max(hi - lo, 1e-12) / bins
    return ((values - lo) / width).floor().clamp(0, bins - 1).long()


def cluster(attrs: Attributes, colour_bins: int, opacity_bins: int, scale_bins: int) -> Clusters:
    """Bin HSV colour, opacity and each sorted log-scale, and group Gaussians by their joint bin."""
    hsv = rgb_to_hsv(attrs.rgb)
    hue = (hsv[:, 0] * colour_bins).floor().long() % colour_bins  # hue wraps around
    sat = _bin(hsv[:, 1], 0.0, 1.0, colour_bins)
    val = _bin(hsv[:, 2], 0.0, 1.0, colour_bins)
    opa = _bin(attrs.opacity, 0.0, 1.0, opacity_bins)
    # Sizes binned over the scene's own range, so that a uniform scaling of the scene bins the same way.
    flat = attrs.log_scales.flatten()
    sample = flat[:: max(1, flat.numel() // 200_000)]
    lo, hi = torch.quantile(sample, torch.tensor([0.01, 0.99], dtype=sample.dtype, device=sample.device)).tolist()
    sc = _bin(attrs.log_scales, lo, hi, scale_bins)
    key = torch.zeros_like(hue)
    for part, bins in ((hue, colour_bins), (sat, colour_bins), (val, colour_bins), (opa, opacity_bins)):
        key = key * bins + part
    for axis in range(3):
        key = key * scale_bins + sc[:, axis]
    sorted_key, order = torch.sort(key)
    _, sizes = torch.unique_consecutive(sorted_key, return_counts=True)
    starts = torch.cumsum(sizes, 0) - sizes
    return Clusters(order, starts, sizes)
