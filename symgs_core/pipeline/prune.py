"""Model no more than the scene needs: drop Gaussians the renders do not miss, and SH bands nobody sees change.

Both measure with the renderer on the training views and are judged on the held-out views against a PSNR floor
(the share of the budget ``budget.split_budget`` gives them); each tries thresholds from bold to timid and keeps the
boldest that stays above its floor, or nothing.

* Contribution of a stored Gaussian: the sum, over training views and over every copy the mirrors make of it, of
  its blending weight alpha * T at each pixel (the gradient of the composited image of ones with respect to a
  per-Gaussian feature of one). Gaussians below a threshold of that weight are removed.
* View dependence of band l of a Gaussian: the mean over directions of its squared colour, ||c_l||^2 / (4 pi)
  (the real SH basis is orthonormal over the sphere), weighted by its contribution. A Gaussian keeps the lowest
  degree whose dropped bands stay below a threshold; dropped bands become exact zeros, which the SH codec stores
  as a per-Gaussian degree (``codec.quantize.ShRestCodec``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..cameras import Camera
from ..mirror import expand
from ..render import render
from ..views import View, evaluate
from .optimize import optimize_level
from .state import LevelState

C0 = 0.28209479177387814


@dataclass
class StageResult:
    """What one reduction did: the state it leaves, how many items it removed, the held-out PSNR after it."""

    state: LevelState
    removed: int
    psnr: float
    threshold: float | None


def contributions(state: LevelState, cameras: list[Camera]) -> Tensor:
    """Total blending weight [|S|] of each stored Gaussian (all its mirror copies) over ``cameras``, in pixels.

    Rendered as a white scene over black: a pixel's red value is then the sum of its blending weights, and its
    gradient with respect to a Gaussian's DC red coefficient is C0 times that Gaussian's weight there.
    """
    scene, origin = expand(state.stored.detach(), state.normals, state.offsets, state.bits)
    dc = torch.full_like(scene.sh_dc, 0.5 / C0).requires_grad_(True)
    white = scene.with_(sh_dc=dc, sh_rest=torch.zeros_like(scene.sh_rest))
    total = torch.zeros(len(scene), dtype=torch.float64)
    for cam in cameras:
        image = render(white, cam, torch.zeros(3, device=scene.device)).image
        (grad,) = torch.autograd.grad(image[..., 0].sum(), dc)
        total += grad[:, 0].detach().double().cpu() / C0
    per_stored = torch.zeros(len(state.stored), dtype=torch.float64)
    per_stored.index_add_(0, origin.cpu(), total)
    return per_stored


def band_energy(sh_rest: Tensor) -> Tensor:
    """Mean squared colour over directions [N, degree] of each SH band 1..degree of ``sh_rest`` [N, K, 3]."""
    degree = {0: 0, 3: 1, 8: 2, 15: 3}[sh_rest.shape[1]]
    bands = [sh_rest[:, lvl * lvl - 1 : (lvl + 1) ** 2 - 1, :].pow(2).sum(dim=(1, 2)) for lvl in range(1, degree + 1)]
    if not bands:
        return sh_rest.new_zeros(len(sh_rest), 0)
    return torch.stack(bands, dim=1) / (4.0 * math.pi)


def truncate_sh(sh_rest: Tensor, degrees: Tensor) -> Tensor:
    """``sh_rest`` [N, K, 3] with the bands above each Gaussian's degree [N] set to zero."""
    k = sh_rest.shape[1]
    band_of = torch.tensor([math.isqrt(i + 1) for i in range(k)], device=sh_rest.device)  # row -> band 1..3
    keep = band_of[None, :] <= degrees.to(sh_rest.device)[:, None]
    return sh_rest * keep[:, :, None].to(sh_rest.dtype)


def prune(
    state: LevelState,
    train: Sequence[View],
    test: Sequence[View],
    background: Tensor,
    *,
    floor: float,
    extent: float,
    iterations: int = 0,
    thresholds: tuple[float, ...] = (0.5, 0.1, 0.02, 0.004),
) -> StageResult | None:
    """Remove stored Gaussians whose total weight over the training views is below a threshold (pixels).

    ``thresholds`` are tried boldest first; the first removal that keeps the held-out PSNR at or above ``floor``,
    as it is or, when it misses by less than 1 dB, after ``iterations`` Adam steps of fine-tuning (planes frozen),
    is returned; None if none does.
    """
    weight = contributions(state, [view.camera for view in train])
    for t in thresholds:
        keep = weight >= t
        removed = int((~keep).sum())
        if removed == 0 or removed == len(keep):
            continue
        pruned = LevelState(state.stored.select(keep.to(state.stored.device)), state.normals, state.offsets,
                            state.bits[keep.to(state.bits.device)])  # fmt: skip
        value = evaluate(pruned.expanded(), test, background).worst
        if floor - 1.0 < value < floor and iterations:  # a short fine-tune may win back a small loss, not more
            pruned = optimize_level(pruned, train, background, iterations=iterations, extent=extent, train_planes=0)
            value = evaluate(pruned.expanded(), test, background).worst
        if value >= floor:
            return StageResult(pruned, removed, value, t)
    return None


def reduce_sh(
    state: LevelState,
    train: Sequence[View],
    test: Sequence[View],
    background: Tensor,
    *,
    floor: float,
    thresholds: tuple[float, ...] = (1e-2, 1e-3, 1e-4, 1e-5),
) -> StageResult | None:
    """Lower each Gaussian's SH degree while weight x dropped band energy stays below a threshold.

    The threshold is in pixel x squared-colour units summed over the training views; boldest first, the first that
    keeps the held-out PSNR at or above ``floor`` is returned (``removed``: bands dropped); None if none does.
    """
    stored = state.stored
    degree = stored.sh_degree
    if degree == 0:
        return None
    weight = contributions(state, [view.camera for view in train]).to(stored.sh_rest.dtype)
    energy = band_energy(stored.sh_rest.detach()).cpu()  # [N, degree]
    # Cost of truncating to degree d: the energy of bands d+1..degree.
    tail = torch.flip(torch.cumsum(torch.flip(energy, [1]), dim=1), [1])  # tail[:, l-1] = sum of bands l..degree
    cost = torch.cat([tail, torch.zeros(len(energy), 1, dtype=tail.dtype)], dim=1) * weight[:, None]  # [N, degree+1]
    for t in thresholds:
        degrees = (cost <= t).to(torch.int64).argmax(dim=1)  # lowest degree whose dropped bands cost <= t
        removed = int((degree - degrees).sum())
        if removed == 0:
            continue
        sh_rest = truncate_sh(stored.sh_rest.detach(), degrees)
        reduced = LevelState(stored.with_(sh_rest=sh_rest), state.normals, state.offsets, state.bits)
        value = evaluate(reduced.expanded(), test, background).worst
        if value >= floor:
            return StageResult(reduced, removed, value, t)
    return None
