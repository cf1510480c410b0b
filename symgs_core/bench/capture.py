"""A Gaussian scene trained from a posed photo capture, for benchmarks that need a real capture together with the
photographs it was trained from (none of the trained scenes the project is tested on comes with them).

The capture is a COLMAP folder with its structure-from-motion points (``sparse/0/points3D.ply``), or a folder of posed
photographs without them (NeRF-Synthetic), which starts, as 3DGS does there, from random points in a cube around
where the cameras look. Training follows 3DGS in outline, at a benchmark's scale: one Gaussian per point (its colour,
a size from the distance to its three nearest neighbours, opacity 0.1), then rounds of Adam with the 3DGS loss and
learning rates (``optimize_level``) on the training split only; the test split is never seen. Between rounds the set
grows as in 3DGS-MCMC: new Gaussians split off existing ones drawn in proportion to their opacity (both halves
narrower, moved apart along the parent's longest axis), and the nearly transparent ones are relocated there too.
Each Gaussian is fitted to the photographs on its own, so mirrored halves of a symmetric object are independent
reconstructions, as in any upload.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData
from scipy.spatial import cKDTree

from ..cameras import Camera
from ..datasets import colmap_model_dir, load_dataset
from ..pipeline.optimize import optimize_level
from ..pipeline.state import LevelState
from ..render.projection import quat_to_rotmat
from ..scene import GaussianScene
from ..sh import C0
from ..views import View, photo_scale

START_OPACITY = 0.1
DROP_OPACITY = 0.005  # below this a Gaussian is relocated between rounds
# The benchmarks' training (``bench_pipeline --captures``): 3,000 Adam steps in all, the set grown by half each round.
ROUNDS, ITERATIONS = 5, 600
RESOLUTION = 256  # px, the photographs' longest side in training
Say = Callable[[str], None]


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


def orbit_points(cameras: list[Camera], count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random positions [count, 3] and colours [count, 3] in the cube centred on the point nearest every
    camera's optical axis, its half side a third of the cameras' median distance to that point (NeRF-Synthetic's
    cameras orbit at 4.0, and 3DGS starts those scenes in a cube of half side 1.3)."""
    centres = np.stack([c.center.double().numpy() for c in cameras])
    axes = np.stack([c.R[2].double().numpy() for c in cameras])  # each camera's viewing direction in the world
    # Least squares: sum_i (I - d_i d_i^T) x = sum_i (I - d_i d_i^T) c_i.
    across = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    target = np.linalg.lstsq(across.sum(0), np.einsum("nij,nj->i", across, centres), rcond=None)[0]
    half = np.median(np.linalg.norm(centres - target, axis=1)) / 3.0
    rng = np.random.default_rng(seed)
    xyz = target + rng.uniform(-half, half, (count, 3))
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
) -> GaussianScene:
    """A scene fitted to the training photographs of the capture ``folder`` (their longest side brought to
    ``resolution``): ``rounds`` rounds of ``iterations`` Adam steps, the set grown by ``growth`` between rounds.
    ``points``: positions [P, 3] and colours [P, 3] to start from (default: the folder's ``sfm_points``, or
    ``random_points`` ``orbit_points`` where it has none)."""
    say = say or (lambda message: None)
    scale, _ = photo_scale(folder, resolution)
    photos = [View(p.camera, p.image, torch.ones(p.image.shape[:2], dtype=torch.bool))
              for p in load_dataset(folder, split="train", background=(0.0, 0.0, 0.0), scale=scale)]  # fmt: skip
    points = points or sfm_points(folder) or orbit_points([v.camera for v in photos], random_points, seed)
    scene = initial_scene(*points, sh_degree)
    centres = torch.stack([v.camera.center for v in photos])
    extent = 1.1 * float((centres - centres.mean(dim=0)).norm(dim=1).max())
    background = torch.zeros(3)
    generator = torch.Generator().manual_seed(seed)
    for r in range(rounds):
        if r:
            scene = grown(scene, growth, generator)
        state, _ = optimize_level(LevelState.plain(scene), photos, background, iterations=iterations, extent=extent,
                                  seed=seed + r)  # fmt: skip
        scene = state.stored
        say(f"round {r + 1}/{rounds}: {len(scene):,} Gaussians")
    return scene


def cached_capture(
    folder: str | Path, ply: str | Path, *, rounds: int = ROUNDS, iterations: int = ITERATIONS, say: Say | None = None
) -> Path:
    """``train_capture(folder)`` saved at ``ply``: trained on the first call, read from there on later ones (training
    takes minutes, and benchmarks of one capture should score one scene)."""
    from ..export import save_scene

    ply = Path(ply)
    if not ply.is_file():
        say = say or (lambda message: None)
        t0 = time.perf_counter()
        scene = train_capture(folder, rounds=rounds, iterations=iterations, say=say)
        ply.parent.mkdir(parents=True, exist_ok=True)
        save_scene(scene, ply)
        say(f"trained {len(scene):,} Gaussians in {time.perf_counter() - t0:.0f} s")
    return ply
