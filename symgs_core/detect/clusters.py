"""Clusters of Gaussians that could be mirror images of each other: same colour, opacity and (sorted) sizes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import prange
from torch import Tensor

from ..compiled import compiled, compiled_parallel
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
    """HSV [N, 3] in [0, 1] of RGB [N, 3] in [0, 1]; hue 0 for greys. On the CPU, in float32."""
    c = rgb.detach().float().cpu().contiguous().numpy()
    out = np.empty_like(c)
    _hsv_kernel(c, out)
    return torch.from_numpy(out).to(rgb.device)


def cluster(attrs: Attributes, colour_bins: int, opacity_bins: int, scale_bins: int) -> Clusters:
    """Bin HSV colour, opacity and each sorted log-scale, and group Gaussians by their joint bin."""
    # Sizes binned over the scene's own range, so that a uniform scaling of the scene bins the same way.
    flat = attrs.log_scales.flatten()
    sample = flat[:: max(1, flat.numel() // 200_000)]
    lo, hi = torch.quantile(sample, torch.tensor([0.01, 0.99], dtype=sample.dtype, device=sample.device)).tolist()
    # Bin widths as float32, as torch divided float32 values by them before.
    widths = np.array([1.0 / colour_bins, 1.0 / opacity_bins, max(hi - lo, 1e-12) / scale_bins], dtype=np.float32)
    cpu = lambda t: t.detach().float().cpu().contiguous().numpy()  # noqa: E731
    key = np.empty(len(attrs.opacity), dtype=np.int64)
    bins = np.array([colour_bins, opacity_bins, scale_bins])
    _key_kernel(cpu(attrs.rgb), cpu(attrs.opacity), cpu(attrs.log_scales), bins, np.float32(lo), widths, key)
    # torch's sort, whose order of equal keys (not always stable) decides the pairs drawn from each cluster.
    sorted_key, order = torch.sort(torch.from_numpy(key))
    _, sizes = torch.unique_consecutive(sorted_key, return_counts=True)
    starts = torch.cumsum(sizes, 0) - sizes
    device = attrs.rgb.device
    return Clusters(order.to(device), starts.to(device), sizes.to(device))


@compiled
def _hsv(r, g, b):  # noqa: ANN001, ANN202
    """HSV of one float32 RGB, operation for operation as torch computed it before (float32 throughout)."""
    zero = np.float32(0.0)
    v = max(r, g, b)
    c = v - min(r, g, b)
    h = zero
    if c > zero:
        if r == v:  # equal maxima give the same hue whichever formula serves
            h = (g - b) / c  # in [-1, 1]: taken modulo 6, as torch did
            if h < zero:
                h = h + np.float32(6.0)
        elif g == v:
            h = (b - r) / c + np.float32(2.0)
        else:
            h = (r - g) / c + np.float32(4.0)
        h = h / np.float32(6.0)
    s = c / v if v > zero else zero
    return h, s, v


@compiled
def _hsv_kernel(rgb, out):  # noqa: ANN001, ANN202
    """HSV [N, 3] of RGB [N, 3] into out."""
    for n in range(rgb.shape[0]):
        out[n, 0], out[n, 1], out[n, 2] = _hsv(rgb[n, 0], rgb[n, 1], rgb[n, 2])


@compiled
def _bin_of(value, lo, width, bins):  # noqa: ANN001, ANN202
    """floor((value - lo) / width) clamped to 0..bins - 1 (float32 value, lo and width)."""
    return int(min(max(math.floor((value - lo) / width), 0.0), bins - 1))


@compiled_parallel
def _key_kernel(rgb, opacity, log_scales, bins, lo, widths, key):  # noqa: ANN001, ANN202
    """Joint bin [N] of hue, saturation, value (bins[0] each), opacity (bins[1]) and the three sorted log-scales
    (bins[2] each, from lo in steps widths[2])."""
    zero = np.float32(0.0)
    for n in prange(rgb.shape[0]):
        h, s, v = _hsv(rgb[n, 0], rgb[n, 1], rgb[n, 2])
        k = int(math.floor(h * np.float32(bins[0]))) % bins[0]  # hue wraps around
        k = k * bins[0] + _bin_of(s, zero, widths[0], bins[0])
        k = k * bins[0] + _bin_of(v, zero, widths[0], bins[0])
        k = k * bins[1] + _bin_of(opacity[n], zero, widths[1], bins[1])
        for axis in range(3):
            k = k * bins[2] + _bin_of(log_scales[n, axis], lo, widths[2], bins[2])
        key[n] = k
