"""The CUDA schedule of ``capture.train``: 3DGS's, with gsplat's rasterizer and its densification strategies.

It follows 3DGS and gsplat's own trainer (``examples/simple_trainer.py`` of gsplat 1.5.3): one random training
photograph a step, at its own size or the chosen resolution; the loss 0.8 L1 + 0.2 (1 - SSIM); Adam with 3DGS's
learning rates, the positions' scaled by the scene extent and decayed exponentially to a hundredth over the run; the
SH degree raised by one every 1,000 steps up to the scene's; gsplat's ``DefaultStrategy`` (3DGS's clone, split and
prune) or ``MCMCStrategy`` (3DGS-MCMC's relocation and growth, with its opacity and scale regularisers and its
brighter, smaller start), every step count of the schedule scaled with the run's length as gsplat's trainer scales
them (``steps_scaler``). Photographs with alpha are laid, with the render, on a random colour a step (nerfstudio's
random background; ``random_background`` False: on black): the scene learns no backdrop, and cannot leave
transparent what they show opaque. Opaque photographs carry their own surroundings, which the scene must learn: their
renders are drawn on black, as the CPU schedule draws them (a random colour behind them would have to be painted over
wherever the photographs show a flat backdrop).

gsplat (the optional ``gpu`` extra) is imported inside ``train_gsplat``; its kernels compile on first use.
"""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ..datasets import composite, load_photographs
from ..pipeline.optimize import loss_fn
from ..progress import ProgressEvent, ProgressFn
from ..render.projection import LOW_PASS
from ..scene import GaussianScene
from ..views import photo_scale
from .train_start import GPU_ITERATIONS, Say, TrainSettings, capture_extent, initial_scene, sfm_points, start_points

if TYPE_CHECKING:
    from ..cameras import Camera

# 3DGS's learning rates, as gsplat's trainer names its parameters; "means" is multiplied by the scene extent.
LEARNING_RATES = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3, "shN": 2.5e-3 / 20}
MEANS_DECAY = 0.01  # the positions' learning rate ends at this share of its start
SH_EVERY = 1000  # steps between SH degrees, at the 30,000-step schedule
# Each strategy's start: opacity, and width as a multiple of the distance to the three nearest neighbours.
START = {"default": (0.1, 1.0), "mcmc": (0.5, 0.1)}
MCMC_REGULARISER = 0.01  # weight of the mean opacity and of the mean scale in the MCMC loss
MIN_REFINE_EVERY = 10  # steps between densifications, however short the run: each needs gradients gathered over some
REPORT_EVERY = 100  # steps between progress reports (each reads the loss back from the GPU)


def train_gsplat(
    folder: str | Path, settings: TrainSettings, *, progress: ProgressFn | None = None, say: Say | None = None
) -> GaussianScene:
    """A scene trained on CUDA from the training photographs of the capture ``folder`` by ``settings``."""
    try:
        import gsplat
        from gsplat.strategy import DefaultStrategy, MCMCStrategy
    except ImportError as err:
        raise RuntimeError("training on CUDA needs gsplat, the optional 'gpu' extra: pip install 'symgs[gpu]'") from err
    if not torch.cuda.is_available():
        raise RuntimeError("training on CUDA needs a CUDA device, and none is available")
    say = say or (lambda message: None)
    device = torch.device("cuda")
    scale = 1.0 if settings.resolution is None else photo_scale(folder, settings.resolution)[0]
    photos = load_photographs(folder, split="train", scale=scale)
    cameras: list[Camera] = [p.camera.to(device) for p in photos]
    targets = [(p.colour.to(device), None if p.alpha is None else p.alpha.to(device)) for p in photos]
    extent = capture_extent(cameras)
    points = sfm_points(folder) or start_points([p.camera for p in photos], settings.random_points, settings.seed)
    del photos

    opacity, width = START[settings.strategy]
    start = initial_scene(*points, settings.sh_degree)
    params = torch.nn.ParameterDict({
        "means": start.means, "scales": start.scales + math.log(width), "quats": start.quats,
        "opacities": torch.full_like(start.opacities, math.log(opacity / (1.0 - opacity))),
        "sh0": start.sh_dc[:, None, :], "shN": start.sh_rest,
    }).to(device)  # fmt: skip
    optimizers = {
        name: torch.optim.Adam([{"params": params[name], "lr": lr * (extent if name == "means" else 1.0),
                                 "name": name}], eps=1e-15)  # fmt: skip
        for name, lr in LEARNING_RATES.items()
    }
    decay = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], MEANS_DECAY ** (1.0 / settings.iterations))
    factor = settings.iterations / GPU_ITERATIONS  # gsplat's steps_scaler
    every = max(MIN_REFINE_EVERY, int(100 * factor))
    strategy: DefaultStrategy | MCMCStrategy
    if settings.strategy == "mcmc":
        strategy = MCMCStrategy(refine_start_iter=int(500 * factor), refine_stop_iter=int(25_000 * factor),
                                refine_every=every)  # fmt: skip
        state = strategy.initialize_state()
    else:
        strategy = DefaultStrategy(refine_start_iter=int(500 * factor), refine_stop_iter=int(15_000 * factor),
                                   reset_every=max(every, int(3000 * factor)), refine_every=every)  # fmt: skip
        state = strategy.initialize_state(scene_scale=extent)
    strategy.check_sanity(params, optimizers)

    sh_every = max(1, int(SH_EVERY * factor))
    shuffle = random.Random(settings.seed)
    colours = torch.Generator(device=device).manual_seed(settings.seed)
    black = torch.zeros(3, device=device)
    order: list[int] = []
    say(f"training {len(params['means']):,} Gaussians on {len(cameras)} photographs, {settings.iterations} steps")
    for step in range(settings.iterations):
        if not order:
            order = list(range(len(cameras)))
            shuffle.shuffle(order)
        index = order.pop()
        camera, (colour, alpha) = cameras[index], targets[index]
        shows_through = settings.random_background and alpha is not None
        background = torch.rand(3, generator=colours, device=device) if shows_through else black
        rendered, _, info = gsplat.rasterization(
            means=params["means"],
            quats=params["quats"],
            scales=params["scales"].exp(),
            opacities=params["opacities"].sigmoid(),
            colors=torch.cat([params["sh0"], params["shN"]], dim=1),  # [N, K, 3]
            viewmats=camera.viewmat[None],  # [1, 4, 4]
            Ks=camera.K[None],  # [1, 3, 3]
            width=camera.width,
            height=camera.height,
            near_plane=camera.near,
            eps2d=LOW_PASS,
            sh_degree=min(step // sh_every, settings.sh_degree),
            packed=False,
            backgrounds=background[None],  # [1, 3]
            rasterize_mode="classic",
        )
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = loss_fn(rendered[0], composite(colour, alpha, background))
        if settings.strategy == "mcmc":
            loss = loss + MCMC_REGULARISER * (params["opacities"].sigmoid().mean() + params["scales"].exp().mean())
        loss.backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        decay.step()
        if isinstance(strategy, MCMCStrategy):
            strategy.step_post_backward(params, optimizers, state, step, info, lr=decay.get_last_lr()[0])
        else:
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        done = step + 1
        if progress is not None and (done % REPORT_EVERY == 0 or done == settings.iterations):
            count, value = len(params["means"]), float(loss.detach())
            message = f"step {done}/{settings.iterations}, {count:,} Gaussians, loss {value:.4f}"
            progress(ProgressEvent("train", None, done / settings.iterations, message))
    with torch.no_grad():
        return GaussianScene(
            means=params["means"].detach().clone(),
            quats=torch.nn.functional.normalize(params["quats"].detach(), dim=-1),
            scales=params["scales"].detach().clone(),
            opacities=params["opacities"].detach().clone(),
            sh_dc=params["sh0"][:, 0, :].detach().clone(),
            sh_rest=params["shN"].detach().clone(),
        )
