"""PSNR and SSIM against independent oracles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from symgs_core.metrics import psnr, ssim


def ssim_by_windows(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM straight from the definition: weighted statistics of every full 11x11 window, mean over channels."""
    r = np.arange(11) - 5.0
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * 1.5**2))
    w = g / g.sum()
    c1, c2 = 0.01**2, 0.03**2
    h, wd, _ = a.shape
    values = []
    for c in range(3):
        for i in range(h - 10):
            for j in range(wd - 10):
                pa, pb = a[i : i + 11, j : j + 11, c], b[i : i + 11, j : j + 11, c]
                ma, mb = (w * pa).sum(), (w * pb).sum()
                va, vb = (w * (pa - ma) ** 2).sum(), (w * (pb - mb) ** 2).sum()
                cov = (w * (pa - ma) * (pb - mb)).sum()
                values.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(values))


def noisy_pair(h: int, w: int, seed: int, noise: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    ref = np.stack([np.sin(6 * xx) * 0.4 + 0.5, yy, (xx + yy) / 2], axis=-1)
    img = np.clip(ref + rng.normal(scale=noise, size=ref.shape), 0, 1)
    return img, ref


def test_psnr_matches_the_formula() -> None:
    img, ref = noisy_pair(20, 30, seed=0)
    mse = np.mean((img - ref) ** 2)
    expected = 10 * math.log10(1 / mse)
    assert psnr(torch.from_numpy(img), torch.from_numpy(ref)).item() == pytest.approx(expected, rel=1e-12)
    got255 = psnr(torch.from_numpy(img * 255), torch.from_numpy(ref * 255), max_val=255.0).item()
    assert got255 == pytest.approx(expected, rel=1e-12)
    assert psnr(torch.from_numpy(ref), torch.from_numpy(ref)).item() == math.inf


@pytest.mark.parametrize(("h", "w", "seed"), [(11, 11, 1), (17, 23, 2), (24, 14, 3)])
def test_ssim_matches_the_windowed_definition(h: int, w: int, seed: int) -> None:
    img, ref = noisy_pair(h, w, seed)
    got = ssim(torch.from_numpy(img), torch.from_numpy(ref)).item()
    assert got == pytest.approx(ssim_by_windows(img, ref), abs=1e-12)


def test_ssim_matches_scikit_image() -> None:
    metrics = pytest.importorskip("skimage.metrics")
    for seed, noise in ((4, 0.02), (5, 0.2)):
        img, ref = noisy_pair(64, 80, seed, noise)
        expected = metrics.structural_similarity(
            img, ref, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1
        )
        got = ssim(torch.from_numpy(img), torch.from_numpy(ref)).item()
        assert got == pytest.approx(expected, abs=1e-10)
        got32 = ssim(torch.from_numpy(img).float(), torch.from_numpy(ref).float()).item()
        assert got32 == pytest.approx(expected, abs=2e-5)


def test_batches_give_one_value_per_image() -> None:
    pairs = [noisy_pair(16, 20, seed, noise) for seed, noise in ((6, 0.05), (7, 0.3))]
    img = torch.from_numpy(np.stack([p[0] for p in pairs]))
    ref = torch.from_numpy(np.stack([p[1] for p in pairs]))
    s, p = ssim(img, ref), psnr(img, ref)
    assert s.shape == (2,) and p.shape == (2,)
    for i in range(2):
        assert s[i].item() == pytest.approx(ssim(img[i], ref[i]).item(), abs=1e-14)
        assert p[i].item() == pytest.approx(psnr(img[i], ref[i]).item(), abs=1e-12)
    assert s[0] > s[1] and p[0] > p[1]  # more noise, lower fidelity


def test_ssim_of_identical_images_is_one() -> None:
    _, ref = noisy_pair(15, 15, 8)
    assert ssim(torch.from_numpy(ref), torch.from_numpy(ref)).item() == pytest.approx(1.0, abs=1e-12)


def test_ssim_is_differentiable() -> None:
    img, ref = noisy_pair(12, 13, 9)
    x = torch.from_numpy(img).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ssim(t, torch.from_numpy(ref)), (x,), eps=1e-6, atol=1e-7, fast_mode=True)
    loss = 0.8 * (x - torch.from_numpy(ref)).abs().mean() + 0.2 * (1 - ssim(x, torch.from_numpy(ref)))
    loss.backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


@pytest.mark.parametrize(
    ("a", "b", "message"),
    [
        ((10, 10, 3), (10, 10, 3), "at least 11x11"),
        ((12, 12, 3), (12, 13, 3), "shapes differ"),
        ((12, 12), (12, 12), "expected images"),
        ((12, 12, 4), (12, 12, 4), "expected images"),
    ],
)
def test_bad_shapes_are_refused(a: tuple[int, ...], b: tuple[int, ...], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ssim(torch.zeros(a), torch.zeros(b))
