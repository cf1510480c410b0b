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
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from plyfile import PlyData
from scipy.spatial import cKDTree

from ..cameras import Camera
from ..datasets import colmap_model_dir, dataset_frames, dataset_layout, load_dataset
from ..pipeline.optimize import optimize_level
from ..pipeline.state import LevelState
from ..progress import ProgressEvent, ProgressFn
from ..render.projection import quat_to_rotmat
from ..scene import GaussianScene
from ..sh import C0
from ..views import View, dataset_eval_views, evaluate, photo_scale

START_OPACITY = 0.1
DROP_OPACITY = 0.005  # below this a Gaussian is relocated between rounds
# The benchmarks' training (``bench_pipeline --captures``): 3,000 Adam steps in all, the set grown by half each round.
ROUNDS, ITERATIONS = 5, 600
RESOLUTION = 256  # px, the photographs' longest side in training
GPU_ITERATIONS = 30_000  # 3DGS's schedule
# A rig whose cameras all look within this angle of their mean direction faces its subject from one side (a wall, an
# LLFF scene); one that turns further round it (NeRF-Synthetic, a walk round an object) orbits it.
FACING_DEG = 75.0
# The depths, in multiples of each camera's distance to where the rig looks, a facing rig's random start spans.
FACING_DEPTHS = (0.5, 1.5)
# Bumped whenever training changes what it makes: a cached scene of another version is trained again.
TRAINER_VERSION = 2
Say = Callable[[str], None]
Strategy = Literal["default", "mcmc"]


@dataclass(frozen=True)
class TrainSettings:
    """How a capture is trained (each field is in ``cached_capture``'s key). Build it with ``for_device``.

    device        "cpu": the reduced schedule; "cuda": gsplat's 3DGS schedule (``train_gsplat``).
    iterations    Adam steps in all (cpu: split evenly over ``rounds``, the set grown between them).
    resolution    the photographs' longest side in training, pixels (None: their own size; never above it).
    sh_degree     SH degree of the scene (cuda: raised one band every 1000 steps, as 3DGS does).
    strategy      cuda: gsplat's densification, "default" (3DGS's) or "mcmc" (3DGS-MCMC).
    random_background  cuda: photographs with alpha and their renders laid on a random colour a step, else black.
    random_points start points where the capture has no structure-from-motion points.
    """

    device: Literal["cpu", "cuda"] = "cpu"
    iterations: int = ROUNDS * ITERATIONS
    rounds: int = ROUNDS
    resolution: int | None = RESOLUTION
    sh_degree: int = 1
    strategy: Strategy = "default"
    random_background: bool = False
    random_points: int = 20_000
    seed: int = 0

    @classmethod
    def for_device(cls, device: Literal["cpu", "cuda"], **overrides: object) -> TrainSettings:
        """The schedule of ``device`` with every override that is not None."""
        base = cls() if device == "cpu" else cls(device="cuda", iterations=GPU_ITERATIONS, rounds=1, resolution=None,
                                                   sh_degree=3, random_background=True, random_points=100_000)
        return replace(base, **{k: v for k, v in overrides.items() if v is not None})  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        if self.iterations < self.rounds or self.rounds < 1:
            raise ValueError(f"iterations must be at least {self.rounds} (one a round), got {self.iterations}")
        if self.resolution is not None and self.resolution < 16:
            raise ValueError(f"resolution must be at least 16 px, got {self.resolution}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if self.strategy not in ("default", "mcmc"):
            raise ValueError(f"strategy must be default or mcmc, got {self.strategy!r}")
        if self.device == "cpu" and (self.strategy != "default" or self.random_background):
            raise ValueError("the CPU schedule grows its own way on black: strategy and random_background are CUDA's")


def sfm_points(folder: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Positions [P, 3] and colours [P, 3] in [0, 1] of a COLMAP folder's structure-from-motion points (None: it
    has none)."""
    model = colmap_model_dir(Path(folder))
    if model is None or not (model / "points3D.ply").is_file():
        return None
    vertex = PlyData.read(str(model / "points3D.ply"))["vertex"]
    xyz = np.stack([vertex[a] for a in ("x", "y", "z")], axis=1).astype(np.float32)
    rgb = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1).astype(np.float32) / 255.0
    return xyz, rgb


def _rig(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera centres [C, 3], viewing directions [C, 3] and the point nearest every optical axis [3]."""
    centres = np.stack([c.center.detach().double().cpu().numpy() for c in cameras])
    axes = np.stack([c.R[2].detach().double().cpu().numpy() for c in cameras])  # viewing directions in the world
    # Least squares: sum_i (I - d_i d_i^T) x = sum_i (I - d_i d_i^T) c_i.
    across = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    target = np.linalg.lstsq(across.sum(0), np.einsum("nij,nj->i", across, centres), rcond=None)[0]
    return centres, axes, target


def start_points(cameras: list[Camera], count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random start positions [count, 3] and colours [count, 3] where ``cameras`` look: in a cube round
    their subject when they orbit it (``orbit_points``), in their frustums when they face it (``facing_points``)."""
    _, axes, _ = _rig(cameras)
    mean = axes.mean(axis=0)
    facing = np.linalg.norm(mean) > 0 and float((axes @ (mean / np.linalg.norm(mean))).min()) > math.cos(
        math.radians(FACING_DEG)
    )
    return (facing_points if facing else orbit_points)(cameras, count, seed)


def orbit_points(cameras: list[Camera], count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random positions [count, 3] and colours [count, 3] in the cube centred on the point nearest every
    camera's optical axis, its half side a third of the cameras' median distance to that point (NeRF-Synthetic's
    cameras orbit at 4.0, and 3DGS starts those scenes in a cube of half side 1.3)."""
    centres, _, target = _rig(cameras)
    half = np.median(np.linalg.norm(centres - target, axis=1)) / 3.0
    rng = np.random.default_rng(seed)
    xyz = target + rng.uniform(-half, half, (count, 3))
    return xyz.astype(np.float32), rng.uniform(0.0, 1.0, (count, 3)).astype(np.float32)


def facing_points(cameras: list[Camera], count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random positions [count, 3] and colours [count, 3] in the frustums of a rig facing its subject: each
    on the ray through a random pixel of a random camera, at a random depth within ``FACING_DEPTHS`` of that
    camera's distance to the point nearest every optical axis.

    A cube round that point, as for an orbit, would miss what such a rig sees most of: a phone held before a fox's
    head on a wall frames the wall a head's width either side and above, where the cube ends. Every point drawn here
    is seen by at least its own camera, and the surroundings get their share of the start."""
    centres, axes, target = _rig(cameras)
    rng = np.random.default_rng(seed)
    which = rng.integers(0, len(cameras), count)
    near, far = FACING_DEPTHS
    reach = np.einsum("ij,ij->i", target - centres, axes)  # each camera's depth to the target
    depth = reach[which] * rng.uniform(near, far, count)
    xyz = np.empty((count, 3))
    for i, camera in enumerate(cameras):
        mine = which == i
        u = rng.uniform(0.0, camera.width, int(mine.sum()))
        v = rng.uniform(0.0, camera.height, int(mine.sum()))
        rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=1)
        rotation = camera.R.detach().double().cpu().numpy()
        xyz[mine] = centres[i] + (rays * depth[mine, None]) @ rotation  # camera to world: R^T x, as rows
    return xyz.astype(np.float32), rng.uniform(0.0, 1.0, (count, 3)).astype(np.float32)


def initial_scene(xyz: np.ndarray, rgb: np.ndarray, sh_degree: int) -> GaussianScene:
    """One round Gaussian [P] per point, as wide as its mean distance to its three nearest neighbours."""
    distance, _ = cKDTree(xyz).query(xyz, k=4)
    width = np.maximum(distance[:, 1:].mean(axis=1), 1e-7)
    n = len(xyz)
    return GaussianScene(
        means=torch.from_numpy(xyz),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
        scales=torch.from_numpy(np.log(width)).float()[:, None].repeat(1, 3),
        opacities=torch.full((n,), math.log(START_OPACITY / (1.0 - START_OPACITY))),
        sh_dc=(torch.from_numpy(rgb) - 0.5) / C0,
        sh_rest=torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3),
    )


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


def capture_extent(cameras: list[Camera]) -> float:
    """The scene extent 3DGS scales position learning rates by: 1.1 times the cameras' largest distance from their
    mean centre."""
    centres = torch.stack([c.center.detach().cpu() for c in cameras])
    return 1.1 * float((centres - centres.mean(dim=0)).norm(dim=1).max())


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
