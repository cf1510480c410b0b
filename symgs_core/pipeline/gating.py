"""Colour agreement of a mirror's two sides, to keep asymmetric details out of a level.

Real captures are only approximately symmetric: a logo, a scratch or a different lighting on one side. Geometry alone
marks such regions as mirrored, and the reflected copy then paints the wrong colour there. Gating compares each
right (to be dropped) Gaussian with the reflected left Gaussians around it; where they disagree, the right Gaussian
is kept (it becomes *out*) and the left Gaussians whose reflection would land on it are not reflected.
"""

from __future__ import annotations

import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ..devices import HOST
from ..mirror import Plane, reflect
from ..scene import GaussianScene
from ..sh import C0

# Neighbours whose colours are averaged: enough to smooth one noisy Gaussian, few enough to stay local.
_NEIGHBOURS = 4


def _base_rgb(scene: GaussianScene) -> Tensor:
    return (C0 * scene.sh_dc + 0.5).clamp(0.0, 1.0)


def colour_mismatch(scene: GaussianScene, plane: Plane, left: Tensor, right: Tensor) -> tuple[Tensor, Tensor]:
    """Per right Gaussian [R], the largest RGB channel difference (view-independent colour) to the opacity-weighted
    mean of its nearest reflected left Gaussians; and per left Gaussian [L], the position in ``right`` of the right
    Gaussian nearest to its reflection."""
    if left.numel() == 0 or right.numel() == 0:
        return torch.zeros(right.numel(), device=HOST), torch.zeros(left.numel(), dtype=torch.long, device=HOST)
    with torch.no_grad():
        mirrored = reflect(scene.select(left).detach().to(HOST), plane.tensor(HOST)[0], plane.offset)
        dropped = scene.select(right).detach().to(HOST)
    k = min(_NEIGHBOURS, left.numel())
    _, near = cKDTree(mirrored.means.numpy()).query(dropped.means.numpy(), k=k)
    near = torch.from_numpy(near).reshape(len(dropped), k)
    weight = torch.sigmoid(mirrored.opacities)[near] + 1e-6
    mean_rgb = (_base_rgb(mirrored)[near] * weight[..., None]).sum(1) / weight.sum(1, keepdim=True)
    mismatch = (_base_rgb(dropped) - mean_rgb).abs().amax(dim=1)
    _, nearest_right = cKDTree(dropped.means.numpy()).query(mirrored.means.numpy(), k=1)
    return mismatch, torch.from_numpy(nearest_right).reshape(-1)


def gated(
    left: Tensor, right: Tensor, mismatch: Tensor, nearest_right: Tensor, threshold: float
) -> tuple[Tensor, Tensor]:
    """``left`` and ``right`` [indices] with the right Gaussians whose mismatch exceeds ``threshold`` kept, and the
    left Gaussians landing nearest to a kept one no longer reflected."""
    agree = mismatch <= threshold
    return left[agree[nearest_right]], right[agree]
