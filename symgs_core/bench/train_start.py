"""Where a capture's training starts, whichever schedule runs it (``capture`` on the CPU, ``train_gsplat`` on CUDA):
its settings, the first points (the capture's structure-from-motion points, or random ones where its cameras look)
and the first scene made of them."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from plyfile import PlyData
from scipy.spatial import cKDTree

from ..cameras import Camera
from ..datasets import colmap_model_dir
from ..scene import GaussianScene
from ..sh import C0

START_OPACITY = 0.1
# The benchmarks' training (``bench_pipeline --captures``): 3,000 Adam steps in all, the set grown by half each round.
ROUNDS, ITERATIONS = 5, 600
RESOLUTION = 256  # px, the photographs' longest side in training
GPU_ITERATIONS = 30_000  # 3DGS's schedule
# A rig whose cameras all look within this angle of their mean direction faces its subject from one side (a wall, an
# LLFF scene); one that turns further round it (NeRF-Synthetic, a walk round an object) orbits it.
FACING_DEG = 75.0
# The depths, in multiples of each camera's distance to where the rig looks, a facing rig's random start spans.
FACING_DEPTHS = (0.5, 1.5)
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


def capture_extent(cameras: list[Camera]) -> float:
    """The scene extent 3DGS scales position learning rates by: 1.1 times the cameras' largest distance from their
    mean centre."""
    centres = torch.stack([c.center.detach().cpu() for c in cameras])
    return 1.1 * float((centres - centres.mean(dim=0)).norm(dim=1).max())
