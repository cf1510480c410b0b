"""What a posed image set yields: frames (a camera and its image file), photographs and views; the error every
loader raises; the LLFF hold-out that splits a set without a test split of its own; the checks both layouts share
(rigid poses, finite intrinsics, paths that stay in the dataset folder).

Every camera comes out in our convention (``cameras.COORDINATE_CONVENTION``: OpenCV axes, world-to-camera).
Images are float32 [H, W, 3] in [0, 1]; RGBA images are composited on a chosen background, after resizing: a
``Photograph`` keeps its alpha, so what was read once can be laid on another background without reading it again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from .lens import Lens, pinhole_for

Split = Literal["train", "val", "test", "all"]
Layout = Literal["nerf_synthetic", "colmap"]

LLFF_HOLD = 8  # a set without a test split holds out every 8th image by name (the LLFF convention)


@dataclass
class Photograph:
    """One posed image before it is laid on a background, the size of ``camera``: ``colour`` [H, W, 3] float32
    premultiplied by ``alpha`` [H, W, 1] (None: an opaque image, which no background shows through)."""

    camera: Camera
    colour: Tensor
    alpha: Tensor | None
    name: str

    def on(self, background: Tensor | tuple[float, float, float]) -> Tensor:
        """The image laid on ``background`` [3]."""
        return composite(self.colour, self.alpha, background)


@dataclass(frozen=True)
class PosedFrame:
    """A camera and the image file it belongs to, before the image is decoded. ``lens``: the distorted camera the
    file was taken with, when it was (``camera`` is then the pinhole it is undistorted to on load). ``orientation``:
    the EXIF orientation the file's pixels are turned by as they are read (``images.oriented_size``; 1: as stored)."""

    camera: Camera
    path: Path
    name: str
    lens: Lens | None = None
    orientation: int = 1


def composite(colour: Tensor, alpha: Tensor | None, background: Tensor | tuple[float, float, float]) -> Tensor:
    """``colour`` [H, W, 3], premultiplied by ``alpha`` [H, W, 1] (None: opaque), laid on ``background`` [3]."""
    if alpha is None:
        return colour
    under = torch.as_tensor(background, dtype=colour.dtype, device=colour.device) * (1.0 - alpha)
    return (colour + under).clamp(0.0, 1.0)  # rounding may carry the sum a step past 1


def in_split(index: int, split: Split) -> bool:
    """Whether the ``index``-th view by name is in ``split`` ("train", "test" or "all") by the LLFF hold-out: every
    ``LLFF_HOLD``-th is "test"."""
    return split == "all" or (index % LLFF_HOLD == 0) == (split == "test")


def held_out(frames: list[PosedFrame], split: Split) -> list[PosedFrame]:
    """``split`` of ``frames`` by the LLFF hold-out (``in_split``; no "val")."""
    if split == "all":
        return frames
    if split == "val":
        return []
    return [f for i, f in enumerate(sorted(frames, key=lambda f: f.name)) if in_split(i, split)]


def check_background(background: tuple[float, float, float]) -> tuple[float, float, float]:
    values = tuple(float(v) for v in background)
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise ValueError(f"background must be three values in [0, 1], got {background}")
    return values


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def inside(root: Path, path: Path) -> bool:
    """Whether ``path``, its symbolic links followed, lies in the folder ``root``."""
    return path.resolve().is_relative_to(root.resolve())


def rotation_ok(r: np.ndarray) -> bool:
    return bool(np.allclose(r @ r.T, np.eye(3), atol=1e-3) and abs(np.linalg.det(r) - 1.0) < 1e-3)


def posed_frame(rotation: Tensor, translation: Tensor, lens: Lens, path: Path, name: str,
                orientation: int = 1) -> PosedFrame:  # fmt: skip
    """The frame of a photograph taken with ``lens`` from the pose ``rotation`` [3, 3], ``translation`` [3]
    (world-to-camera), its file read turned by the EXIF ``orientation``: a pinhole camera as it is, a distorted one
    as the pinhole it is undistorted to."""
    if not lens.distorted:
        camera = Camera(rotation, translation, lens.fx, lens.fy, lens.cx, lens.cy, lens.width, lens.height, name)
        return PosedFrame(camera, path, name, None, orientation)
    camera = Camera(rotation, translation, *pinhole_for(lens), name)
    return PosedFrame(camera, path, name, lens, orientation)
