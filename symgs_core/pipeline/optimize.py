"""Mirror-aware optimisation of one level.

The rendered scene is the stored working set expanded through every mirror (``mirror.expand``); Adam trains the
working set's attributes and the newest mirror's plane, with the 3DGS loss 0.8 L1 + 0.2 (1 - SSIM) and the 3DGS
learning rates (positions scaled by the scene's extent).
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..metrics import ssim
from ..mirror import expand
from ..progress import Cancelled, StopFn
from ..render import render
from ..scene import GaussianScene
from ..views import View
from .state import LevelState

LAMBDA_DSSIM = 0.2


@dataclass(frozen=True)
class LearningRates:
    """3DGS learning rates; ``means`` and the plane offset are multiplied by the scene extent."""

    means: float = 1.6e-4
    quats: float = 1e-3
    scales: float = 5e-3
    opacities: float = 2.5e-2
    sh_dc: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20.0
    plane: float = 1e-3


def loss_fn(image: Tensor, target: Tensor) -> Tensor:
    l1 = (image - target).abs().mean()
    return (1.0 - LAMBDA_DSSIM) * l1 + LAMBDA_DSSIM * (1.0 - ssim(image, target))


def optimize_level(
    state: LevelState,
    views: Sequence[View],
    background: Tensor,
    *,
    iterations: int,
    extent: float,
    train_planes: int = 1,
    lr: LearningRates = LearningRates(),
    seed: int = 0,
    should_stop: StopFn | None = None,
    on_step=None,  # noqa: ANN001 - Callable[[int, float], None]: step index, loss
) -> LevelState:
    """Fine-tune ``state`` for ``iterations`` Adam steps on ``views``; returns a new, detached state.

    The last ``train_planes`` mirrors (the newest levels) are trainable along with every stored attribute.
    """
    if iterations == 0 or not views:
        return state.detach()
    params = {k: v.detach().clone().requires_grad_(True) for k, v in state.stored.tensors().items()}
    levels = state.normals.shape[0]
    k = min(train_planes, levels)
    frozen_n, frozen_g = state.normals[: levels - k].detach(), state.offsets[: levels - k].detach()
    train_n = state.normals[levels - k :].detach().clone().requires_grad_(True)
    train_g = state.offsets[levels - k :].detach().clone().requires_grad_(True)
    groups = [
        {"params": [params[name]], "lr": getattr(lr, name) * (extent if name == "means" else 1.0)} for name in params
    ]
    if k:
        groups += [{"params": [train_n], "lr": lr.plane}, {"params": [train_g], "lr": lr.plane * extent}]
    optimizer = torch.optim.Adam(groups, eps=1e-15)
    rng = random.Random(seed)
    order: list[int] = []
    for step in range(iterations):
        if should_stop is not None and should_stop():
            raise Cancelled()
        if not order:
            order = list(range(len(views)))
            rng.shuffle(order)
        cam, target, _ = views[order.pop()]
        normals = torch.cat([frozen_n, train_n / train_n.norm(dim=-1, keepdim=True)])
        offsets = torch.cat([frozen_g, train_g])
        scene, _ = expand(GaussianScene(**params), normals, offsets, state.bits)
        loss = loss_fn(render(scene, cam, background).image, target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if on_step is not None:
            on_step(step, float(loss.detach()))
    with torch.no_grad():
        normals = torch.cat([frozen_n, train_n / train_n.norm(dim=-1, keepdim=True)])
        offsets = torch.cat([frozen_g, train_g])
    return LevelState(GaussianScene(**params).detach(), normals.detach(), offsets.detach(), state.bits.clone())
