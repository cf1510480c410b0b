"""Mirror-aware optimisation of one level: only what the mirror changed moves.

The rendered scene is the stored working set expanded through every mirror (``mirror.expand``). Adam trains the
Gaussians a mask names (the kept half of the new mirror and a halo of neighbours) and the newest plane, with the
3DGS loss 0.8 L1 + 0.2 (1 - SSIM) and the 3DGS learning rates (positions scaled by the scene's extent), decayed
tenfold over the run. Every other Gaussian stays bit-exact: uploads decoded from quantised formats keep their values
on the source's grids, which the codec exploits. With ``steps`` the forward pass sees the trained attributes
rounded to the codec's grids (straight-through: the gradient passes the rounding unchanged), so the fine-tune
learns values that survive quantisation.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..codec.steps import QuantSteps
from ..metrics import ssim
from ..mirror import expand, expansion_plan
from ..progress import Cancelled, StopFn
from ..render import render
from ..scene import GaussianScene
from ..views import View
from .state import LevelState

LAMBDA_DSSIM = 0.2
FINAL_LR = 0.1  # learning rates decay to this share of their start over a run


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


def _rounded(x: Tensor, step: float) -> Tensor:
    """``x`` on a grid of ``step`` in the forward pass, unchanged in the backward pass."""
    return x + (torch.round(x / step) * step - x).detach()


def fake_quantized(params: dict[str, Tensor], steps: QuantSteps, extent: float) -> dict[str, Tensor]:
    """``params`` as the codec's grids would round them (straight-through); opacity on its alpha grid."""
    out = dict(params)
    out["means"] = _rounded(params["means"], steps.position * max(extent, 1e-12))
    out["scales"] = _rounded(params["scales"], steps.scale)
    out["quats"] = _rounded(params["quats"], steps.rotation)
    out["sh_dc"] = _rounded(params["sh_dc"], steps.dc)
    alpha = torch.sigmoid(params["opacities"])
    alpha = _rounded(alpha, steps.opacity).clamp(1e-4, 1.0 - 1e-4)
    out["opacities"] = torch.log(alpha / (1.0 - alpha))
    if params["sh_rest"].shape[1]:
        step = min(steps.sh) if steps.sh else 1.0
        out["sh_rest"] = _rounded(params["sh_rest"], step)
    return out


def optimize_level(
    state: LevelState,
    views: Sequence[View],
    background: Tensor,
    *,
    iterations: int,
    extent: float,
    trainable: Tensor | None = None,
    train_planes: int = 1,
    steps: QuantSteps | None = None,
    lr: LearningRates = LearningRates(),
    seed: int = 0,
    check_every: int = 0,
    keep_going: Callable[[LevelState], bool] | None = None,
    should_stop: StopFn | None = None,
    on_step: Callable[[int, Tensor], None] | None = None,
) -> tuple[LevelState, int]:
    """Fine-tune ``state`` for at most ``iterations`` Adam steps on ``views``; returns a new, detached state and the
    steps run.

    ``trainable`` [|S|] bool: the stored Gaussians that may move (all when None). The last ``train_planes`` planes
    move too. Every ``check_every`` steps ``keep_going(state so far)`` may end the run early (the caller measures
    whether the last stretch still gained). ``on_step(step, loss)`` gets the loss as a tensor: reading it waits for
    the device, so a caller reads only the steps it reports.
    """
    if iterations == 0 or not views:
        return state.detach(), 0
    params = {k: v.detach().clone().requires_grad_(True) for k, v in state.stored.tensors().items()}
    if trainable is not None:
        frozen = ~trainable.to(state.stored.device)
        for p in params.values():
            # Zero gradients give Adam zero moments: a frozen row's update is exactly zero, its bits untouched.
            p.register_hook(lambda g, frozen=frozen: g.masked_fill(frozen.view(-1, *([1] * (g.dim() - 1))), 0.0))
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
    decay = torch.optim.lr_scheduler.ExponentialLR(optimizer, FINAL_LR ** (1.0 / max(iterations, 1)))
    rng = random.Random(seed)
    order: list[int] = []
    plan = expansion_plan(state.bits)  # the bits never change here: the members of each level are found once

    def planes() -> tuple[Tensor, Tensor]:
        return torch.cat([frozen_n, train_n / train_n.norm(dim=-1, keepdim=True)]), torch.cat([frozen_g, train_g])

    def current() -> LevelState:
        with torch.no_grad():
            normals, offsets = planes()
        stored = GaussianScene(**params).detach().clone()
        return LevelState(stored, normals.detach().clone(), offsets.detach().clone(), state.bits.clone())

    run = 0
    for step in range(iterations):
        if should_stop is not None and should_stop():
            raise Cancelled()
        if not order:
            order = list(range(len(views)))
            rng.shuffle(order)
        view = views[order.pop()]
        cam, target = view.camera, view.image
        normals, offsets = planes()
        shown = fake_quantized(params, steps, extent) if steps is not None else params
        scene, _ = expand(GaussianScene(**shown), normals, offsets, state.bits, plan)
        loss = loss_fn(render(scene, cam, background).image, target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        decay.step()
        run = step + 1
        if on_step is not None:
            on_step(step, loss.detach())
        if check_every and keep_going is not None and run % check_every == 0 and run < iterations:
            if not keep_going(current()):
                break
    return current(), run


def halo(before: GaussianScene, region: Tensor, after: GaussianScene, *, radius: float) -> Tensor:
    """Which Gaussians of ``after`` [M] lie within about ``radius`` of the ``region`` [R] indices of ``before``:
    voxels of side ``radius`` holding a region Gaussian, grown by one voxel, hashed (O(N), no neighbour search)."""
    if region.numel() == 0 or len(after) == 0 or not math.isfinite(radius) or radius <= 0:
        return torch.zeros(len(after), dtype=torch.bool, device=after.device)
    points = before.means.detach()[region.to(before.device)].to(torch.float64)
    origin = points.min(dim=0).values
    cells = torch.floor((points - origin) / radius).to(torch.int64)
    steps = torch.tensor((-1, 0, 1), device=cells.device)
    neighbourhood = torch.cartesian_prod(steps, steps, steps)  # [27, 3]
    marked = torch.unique(_key((cells[None] + neighbourhood[:, None]).reshape(-1, 3)))
    targets = torch.floor((after.means.detach().to(origin.device, torch.float64) - origin) / radius).to(torch.int64)
    return torch.isin(_key(targets), marked).to(after.device)


def _key(cells: Tensor) -> Tensor:
    """One int64 per voxel (2^21 voxels per axis around the origin; offsets outside wrap harmlessly)."""
    c = cells + (1 << 20)
    return (c[:, 0] & 0x1FFFFF) << 42 | (c[:, 1] & 0x1FFFFF) << 21 | (c[:, 2] & 0x1FFFFF)
