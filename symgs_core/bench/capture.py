"""A Gaussian scene trained from a posed photo capture: ``symgs train`` for users, and the benchmarks that need a real
capture together with the photographs it was trained from (none of the trained scenes the project is tested on comes
with them).

The capture is a COLMAP folder with its structure-from-motion points (``sparse/0/points3D.ply``), or a folder of posed
photographs without them (NeRF-Synthetic, an instant-ngp capture), which starts from random points where the cameras
look (``start_points``). Two schedules, chosen by ``TrainSettings.device``:

cpu   3DGS in outline, at a benchmark's scale: one Gaussian per point (its colour, a size from the distance to its
      three nearest neighbours, opacity 0.1), then rounds of Adam with the 3DGS loss and learning rates
      (``optimize_level``) at 256 px; between rounds the set grows as in 3DGS-MCMC: new Gaussians split off existing
      ones drawn in proportion to their opacity (both halves narrower, moved apart along the parent's longest axis),
      and the nearly transparent ones are relocated there too.
cuda  the 3DGS schedule with gsplat's rasterizer and densification strategies (``train_gsplat``), at the
      photographs' own size.

Either trains on the training split only: the test split is never seen. Each Gaussian is fitted to the photographs
on its own, so mirrored halves of a symmetric object are independent reconstructions, as in any upload.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ..datasets import colmap_model_dir, dataset_frames, dataset_layout, load_dataset
from ..pipeline.optimize import optimize_level
from ..pipeline.state import LevelState
from ..progress import ProgressEvent, ProgressFn
from ..render.projection import quat_to_rotmat
from ..scene import GaussianScene
from ..views import View, dataset_eval_views, evaluate, photo_scale
from .train_start import (
    ITERATIONS,
    RESOLUTION,
    ROUNDS,
    Say,
    TrainSettings,
    capture_extent,
    initial_scene,
    sfm_points,
    start_points,
)

DROP_OPACITY = 0.005  # below this a Gaussian is relocated between rounds
# Bumped whenever training changes what it makes: a cached scene of another version is trained again.
TRAINER_VERSION = 2


def grown(scene: GaussianScene, share: float, generator: torch.Generator) -> GaussianScene:
    """``scene`` with ``share`` of its count split off Gaussians drawn in proportion to opacity: the parent and its
    new half each 0.6 as wide, 0.5 standard deviations either side of where it was along its longest axis, each with
    the opacity that keeps the pair's coverage. The nearly transparent are relocated: they leave, and as many more
    splits are drawn (a start from random points loses most of them in its first round)."""
    alpha = torch.sigmoid(scene.opacities)
    live = alpha >= DROP_OPACITY
    scene, alpha = scene.select(torch.nonzero(live).squeeze(1)), alpha[live]
    count = int(share * len(scene)) + int((~live).sum())
    if count == 0:
        return scene
    parents = torch.multinomial(alpha, min(count, len(scene)), replacement=False, generator=generator)
    longest = scene.scales[parents].argmax(dim=1)
    axis = quat_to_rotmat(scene.quats[parents])[torch.arange(len(parents)), :, longest]  # world direction [k, 3]
    shift = 0.5 * scene.scales[parents].exp().gather(1, longest[:, None]) * axis
    a = alpha[parents]
    half = (1.0 - torch.sqrt(1.0 - a)).clamp(1e-6, 1.0 - 1e-6)  # two halves cover what one did
    tensors = scene.tensors()
    out = {k: v.clone() for k, v in tensors.items()}
    out["means"][parents] -= shift
    out["scales"][parents] += math.log(0.6)
    out["opacities"][parents] = torch.log(half / (1.0 - half))
    children = {k: v[parents].clone() for k, v in out.items()}
    children["means"] += 2 * shift
    return GaussianScene(**{k: torch.cat([out[k], children[k]]) for k in out})


def train_capture(
    folder: str | Path,
    *,
    resolution: int = RESOLUTION,
    rounds: int = ROUNDS,
    iterations: int = ITERATIONS,
    growth: float = 0.5,
    sh_degree: int = 1,
    points: tuple[np.ndarray, np.ndarray] | None = None,
    random_points: int = 20_000,
    seed: int = 0,
    say: Say | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> GaussianScene:
    """The CPU schedule: a scene fitted to the training photographs of the capture ``folder`` (their longest side
    brought to ``resolution``): ``rounds`` rounds of ``iterations`` Adam steps, the set grown by ``growth`` between
    rounds. ``points``: positions [P, 3] and colours [P, 3] to start from (default: the folder's ``sfm_points``, or
    ``random_points`` ``start_points`` where it has none). ``on_step(step, loss)`` after each step, counted over all
    rounds."""
    say = say or (lambda message: None)
    scale, _ = photo_scale(folder, resolution)
    photos = [View(p.camera, p.image, torch.ones(p.image.shape[:2], dtype=torch.bool))
              for p in load_dataset(folder, split="train", background=(0.0, 0.0, 0.0), scale=scale)]  # fmt: skip
    points = points or sfm_points(folder) or start_points([v.camera for v in photos], random_points, seed)
    scene = initial_scene(*points, sh_degree)
    extent = capture_extent([v.camera for v in photos])
    background = torch.zeros(3)
    generator = torch.Generator().manual_seed(seed)
    for r in range(rounds):
        if r:
            scene = grown(scene, growth, generator)
        step = (lambda i, loss, r=r: on_step(r * iterations + i, loss)) if on_step is not None else None
        state, _ = optimize_level(LevelState.plain(scene), photos, background, iterations=iterations, extent=extent,
                                  seed=seed + r, on_step=step)  # fmt: skip
        scene = state.stored
        say(f"round {r + 1}/{rounds}: {len(scene):,} Gaussians")
    return scene


def train(
    folder: str | Path, settings: TrainSettings, *, progress: ProgressFn | None = None, say: Say | None = None
) -> GaussianScene:
    """A scene trained from the capture ``folder`` by ``settings``; ``progress`` hears the share of steps done."""
    if settings.device == "cuda":
        from .train_gsplat import train_gsplat

        return train_gsplat(folder, settings, progress=progress, say=say)
    per_round = settings.iterations // settings.rounds
    total = per_round * settings.rounds

    def on_step(step: int, loss: float) -> None:
        if progress is not None and (step % 10 == 9 or step + 1 == total):
            progress(ProgressEvent("train", None, (step + 1) / total, f"step {step + 1}/{total}, loss {loss:.4f}"))

    return train_capture(folder, resolution=settings.resolution or RESOLUTION, rounds=settings.rounds,
                         iterations=per_round, sh_degree=settings.sh_degree, random_points=settings.random_points,
                         seed=settings.seed, say=say, on_step=on_step)  # fmt: skip


def held_out_psnr(scene: GaussianScene, folder: str | Path, resolution: int | None) -> tuple[float, int]:
    """PSNR (dB, full frame) of ``scene`` on the capture's test split, which training never sees, at the training
    ``resolution`` (None: the photographs' own), drawn on black; and how many photographs that is."""
    side = resolution or max(max(f.camera.width, f.camera.height) for f in dataset_frames(folder, "test"))
    background = torch.zeros(3, device=scene.device)
    views = dataset_eval_views(folder, scene, eval=1000, resolution=side, background=background)
    return evaluate(scene, views, background, with_ssim=False).psnr, len(views)


def capture_key(folder: str | Path, settings: TrainSettings) -> str:
    """SHA-256 of what a trained capture depends on: the photographs' bytes and names, the transforms files or the
    COLMAP model (cameras, poses, points), the training settings and ``TRAINER_VERSION``. A capture moved or
    renamed keeps its key; one photograph or pose changed, or another schedule, gets another."""
    root = Path(folder)
    h = hashlib.sha256(json.dumps({"trainer": TRAINER_VERSION, **asdict(settings)}, sort_keys=True).encode())
    if dataset_layout(root) == "nerf_synthetic":
        described = sorted(p for p in root.glob("*.json") if p.name.startswith("transforms")
                           or p.name == "dataparser_transforms.json")  # fmt: skip
    else:
        model = colmap_model_dir(root)
        described = sorted(p for p in model.iterdir() if p.is_file()) if model is not None else []
    photographs = sorted({f.path for f in dataset_frames(root, "all")})
    for file in described + photographs:
        h.update(str(file.relative_to(root)).encode() + b"\0")
        with file.open("rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def cached_path(folder: str | Path, cache: str | Path, settings: TrainSettings) -> Path:
    """Where ``cached_capture`` keeps the scene ``settings`` train from ``folder``: named by the schedule and the
    start of ``capture_key``."""
    steps = f"{settings.rounds}x{settings.iterations // settings.rounds}" if settings.device == "cpu" else (
        f"{settings.device}-{settings.strategy}-{settings.iterations}")  # fmt: skip
    return Path(cache) / f"trained-{steps}-{capture_key(folder, settings)[:16]}.ply"


def cached_capture(
    folder: str | Path, cache: str | Path, settings: TrainSettings | None = None, *, say: Say | None = None
) -> Path:
    """``train(folder, settings)`` saved in the folder ``cache`` under its ``capture_key``: trained on the first
    call, read from there on later ones (training takes minutes, and benchmarks of one capture should score one
    scene; a capture changed since is trained again)."""
    from ..export import save_scene

    settings = settings or TrainSettings()
    ply = cached_path(folder, cache, settings)
    if not ply.is_file():
        say = say or (lambda message: None)
        t0 = time.perf_counter()
        scene = train(folder, settings, say=say)
        ply.parent.mkdir(parents=True, exist_ok=True)
        save_scene(scene, ply)
        say(f"trained {len(scene):,} Gaussians in {time.perf_counter() - t0:.0f} s")
    return ply
