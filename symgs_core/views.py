"""Training and held-out views: posed images when given, otherwise self-supervised renders of the input scene."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .cameras import Camera, orbit_cameras, scene_bounds
from .metrics import mse_to_psnr, ssim
from .scene import GaussianScene


@dataclass
class ViewSet:
    """Cameras with target images [H, W, 3]; ``source`` says what the targets are."""

    train: Sequence[tuple[Camera, Tensor]]
    test: Sequence[tuple[Camera, Tensor]]
    source: str  # "renders of the input" | "test images"
    background: Tensor  # [3]


class RenderedTargets(Sequence):
    """(camera, target) pairs whose targets are renders of a scene, made on first access and kept.

    Training draws many self-supervised views; rendering each only when the optimiser first asks for it keeps the
    set-up cost proportional to the views actually used.
    """

    def __init__(self, scene: GaussianScene, cameras: list[Camera], background: Tensor) -> None:
        self.scene, self.cameras, self.background = scene.detach(), cameras, background
        self._targets: dict[int, Tensor] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    @torch.no_grad()
    def __getitem__(self, index: int) -> tuple[Camera, Tensor]:  # type: ignore[override]
        from .render import render

        if index not in self._targets:
            cam = self.cameras[index].to(self.scene.device)
            self._targets[index] = render(self.scene, cam, self.background).image.detach()
        return self.cameras[index].to(self.scene.device), self._targets[index]


def _rotated(cams: list[Camera], center: Tensor, seed: int) -> list[Camera]:
    """The same rig turned by a random rotation about ``center``: a set of views disjoint from the original."""
    gen = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.linalg.det(q))
    c = center.to(torch.float64)
    out = []
    for cam in cams:
        R = cam.R.to(torch.float64) @ q.T
        eye = q @ (cam.center.to(torch.float64) - c) + c
        out.append(
            Camera(R.float(), (-R @ eye).float(), cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.name)
        )
    return out


def self_supervised_views(
    scene: GaussianScene, train_count: int, test_count: int, resolution: int, background: Tensor, seed: int = 0
) -> ViewSet:
    """Held-out cameras spread evenly over the scene's bounding sphere, and training cameras from a turned copy of
    another such spread, so no training view coincides with a held-out one."""
    center, radius = scene_bounds(scene.means.detach().cpu())
    test_cams = orbit_cameras(center, radius, test_count, resolution, resolution)
    train_cams = _rotated(orbit_cameras(center, radius, train_count, resolution, resolution), center, seed + 1)
    return ViewSet(
        train=RenderedTargets(scene, train_cams, background),
        test=RenderedTargets(scene, test_cams, background),
        source="renders of the input",
        background=background,
    )


def dataset_views(
    folder: str | Path, resolution: int, background: Tensor, device: torch.device, max_test: int | None = None
) -> ViewSet:
    """Posed images of a NeRF-Synthetic or COLMAP folder, decoded at a scale whose longest side is ``resolution``.

    All training images are used; ``max_test`` evenly spaced held-out images at most.
    """
    from .datasets import dataset_frames, load_dataset

    bg = tuple(float(v) for v in background)
    first = dataset_frames(folder, "train")[0].camera
    scale = min(1.0, resolution / max(first.width, first.height))

    def load(split: str, max_views: int | None) -> list[tuple[Camera, Tensor]]:
        views = load_dataset(folder, split=split, background=bg, max_views=max_views, scale=scale)
        return [(v.camera.to(device), v.image.to(device)) for v in views]

    return ViewSet(train=load("train", None), test=load("test", max_test), source="test images", background=background)


@torch.no_grad()
def evaluate(scene: GaussianScene, views: list[tuple[Camera, Tensor]], background: Tensor) -> tuple[float, float]:
    """Mean PSNR (dB, from the mean MSE over views) and mean SSIM of ``scene`` against the views' targets."""
    if not views:
        raise ValueError("evaluate needs at least one view")
    mse, ssims = 0.0, []
    from .render import render

    for cam, target in views:
        image = render(scene, cam, background).image
        mse += float(((image - target) ** 2).mean())
        ssims.append(float(ssim(image, target)))
    mse /= len(views)
    return mse_to_psnr(mse), sum(ssims) / len(ssims)
