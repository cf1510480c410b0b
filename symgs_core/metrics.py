"""Image fidelity: PSNR and SSIM, differentiable (SSIM is part of the training loss).

Images are [H, W, 3] or [B, H, W, 3] (channels last, as the renderer returns them); the result is one value per
image: a scalar for [H, W, 3], shape [B] for a batch.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import Tensor

# Wang et al. 2004: 11x11 Gaussian window, sigma 1.5, K1 = 0.01, K2 = 0.03.
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _check_pair(img: Tensor, ref: Tensor) -> None:
    if img.shape != ref.shape:
        raise ValueError(f"image shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    if img.dim() not in (3, 4) or img.shape[-1] != 3:
        raise ValueError(f"expected images [H, W, 3] or [B, H, W, 3], got {tuple(img.shape)}")


# A PSNR at or above this is float rounding, not a loss: charts draw it with the lossless results and rate-distortion
# curves do not interpolate towards it.
LOSSLESS_DB = 100.0


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] images; +inf for a perfect match."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def psnr_to_mse(psnr: float) -> float:
    """The mean squared error on [0, 1] images of a PSNR in dB; 0 for +inf."""
    return 0.0 if math.isinf(psnr) and psnr > 0 else 10.0 ** (-psnr / 10.0)


def psnr(img: Tensor, ref: Tensor, max_val: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB per image; +inf for identical images."""
    _check_pair(img, ref)
    mse = ((img - ref) ** 2).mean(dim=(-3, -2, -1))
    return 10.0 * torch.log10(max_val**2 / mse)


@lru_cache(maxsize=8)
def _gaussian_1d(dtype: torch.dtype, device: torch.device) -> Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64, device="cpu") - (SSIM_WINDOW - 1) / 2
    w = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return (w / w.sum()).to(dtype=dtype, device=device)


def _blur(x: Tensor) -> Tensor:
    """Gaussian-weighted local means over valid 11x11 windows: [B, C, H, W] -> [B, C, H-10, W-10]."""
    c = x.shape[1]
    w = _gaussian_1d(x.dtype, x.device)
    x = F.conv2d(x, w.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(x, w.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def ssim(img: Tensor, ref: Tensor, max_val: float = 1.0) -> Tensor:
    """Structural similarity per image (Wang et al. 2004), over the valid region, mean over channels.

    Gaussian 11x11 window with sigma 1.5, population (weighted) variances; the same definition as
    scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.
    """
    _check_pair(img, ref)
    if min(img.shape[-3], img.shape[-2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {tuple(img.shape)}")
    batched = img.dim() == 4
    x = (img if batched else img[None]).permute(0, 3, 1, 2)
    y = (ref if batched else ref[None]).permute(0, 3, 1, 2)
    c1 = (SSIM_K1 * max_val) ** 2
    c2 = (SSIM_K2 * max_val) ** 2
    # One convolution pass over the five stacked moments.
    moments = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1))
    mu_x, mu_y, xx, yy, xy = moments.chunk(5, dim=1)
    var_x = xx - mu_x**2
    var_y = yy - mu_y**2
    cov = xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    value = (num / den).mean(dim=(1, 2, 3))
    return value if batched else value[0]
