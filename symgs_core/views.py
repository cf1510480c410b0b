"""Training and held-out views: posed images when given, otherwise self-supervised renders of the input scene."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .cameras import Camera, scene_cameras
from .scene import GaussianScene


@dataclass
class ViewSet:
    """Cameras with target images [H, W, 3]; ``source`` says what the targets are."""

    train: list[tuple[Camera, Tensor]]
    test: list[tuple[Camera, Tensor]]
    source: str  # "renders of the input" | "test images"
    background: Tensor  # [3]


def _fit(camera: Camera, resolution: int) -> Camera:
    scale = resolution / max(camera.width, camera.height)
    if scale >= 1.0:
        return camera
    return camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))


def _resize_image(image: Tensor, width: int, height: int) -> Tensor:
    if image.shape[1] == width and image.shape[0] == height:
        return image
    chw = image.permute(2, 0, 1)[None]
    return torch.nn.functional.interpolate(chw, size=(height, width), mode="area")[0].permute(1, 2, 0).contiguous()


@torch.no_grad()
def render_targets(scene: GaussianScene, cameras: list[Camera], background: Tensor) -> list[tuple[Camera, Tensor]]:
    from .render import render

    return [(cam, render(scene, cam.to(scene.device), background).image.detach()) for cam in cameras]


def self_supervised_views(
    scene: GaussianScene, train_count: int, test_count: int, resolution: int, background: Tensor
) -> ViewSet:
    """Cameras over the scene's bounding sphere; every ``k``-th one is held out and never trained on."""
    total = train_count + test_count
    cams = scene_cameras(scene.means, total, resolution, resolution)
    step = total / test_count
    test_idx = {int(i * step + step / 2) for i in range(test_count)}
    test_cams = [c for i, c in enumerate(cams) if i in test_idx]
    train_cams = [c for i, c in enumerate(cams) if i not in test_idx]
    return ViewSet(
        train=render_targets(scene, train_cams, background),
        test=render_targets(scene, test_cams, background),
        source="renders of the input",
        background=background,
    )


def dataset_views(folder: str | Path, resolution: int, background: Tensor, device: torch.device) -> ViewSet:
    """Posed images of a NeRF-Synthetic or COLMAP folder, downscaled so the longest side is ``resolution``."""
    from .datasets import load_dataset

    bg = tuple(float(v) for v in background)

    def load(split: str) -> list[tuple[Camera, Tensor]]:
        out = []
        for view in load_dataset(folder, split=split, background=bg):
            cam = _fit(view.camera, resolution)
            out.append((cam.to(device), _resize_image(view.image, cam.width, cam.height).to(device)))
        return out

    return ViewSet(train=load("train"), test=load("test"), source="test images", background=background)
