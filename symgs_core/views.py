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
