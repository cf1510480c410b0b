"""Image files of a posed set: read (alpha premultiplied), resized, laid on a background."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from .posed import DatasetError, Photograph, PosedFrame, View, composite


def image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, UnidentifiedImageError) as exc:
        raise DatasetError("bad_image", f"cannot read image {path.name}: {exc}") from None


def read_premultiplied(path: Path) -> tuple[Tensor, Tensor | None]:
    """Image [H, W, 3] float32 in [0, 1], premultiplied by its alpha channel [H, W, 1] (None: it has none)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
            array = np.asarray(im.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except (OSError, UnidentifiedImageError) as exc:
        raise DatasetError("bad_image", f"cannot read image {path.name}: {exc}") from None
    rgb = torch.from_numpy(array[..., :3].copy())
    if not has_alpha:
        return rgb, None
    alpha = torch.from_numpy(array[..., 3:].copy())
    return rgb * alpha, alpha


def read_image(path: Path, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> Tensor:
    """Image [H, W, 3] float32 in [0, 1]; an alpha channel is composited on ``background``."""
    return composite(*read_premultiplied(path), background)


def resize_image(image: Tensor, width: int, height: int) -> Tensor:
    """Anti-aliased resize of [H, W, 3]."""
    if image.shape[:2] == (height, width):
        return image
    out = torch.nn.functional.interpolate(
        image.permute(2, 0, 1)[None], size=(height, width), mode="bilinear", antialias=True, align_corners=False
    )
    return out[0].permute(1, 2, 0).clamp(0.0, 1.0).contiguous()


def load_frames(frames: list[PosedFrame], max_views: int | None = None, scale: float = 1.0) -> list[Photograph]:
    """The photographs of at most ``max_views`` of ``frames`` (evenly spaced, in order), each at its camera's size
    times ``scale``."""
    photographs = []
    for frame in _subsample(frames, max_views):
        camera = _scaled(frame.camera, scale)
        colour, alpha = read_premultiplied(frame.path)
        # Resized before compositing, so the same pixels can be laid on any background; premultiplied, that gives
        # what resizing the composite would.
        alpha = None if alpha is None else resize_image(alpha, camera.width, camera.height)
        photographs.append(Photograph(camera, resize_image(colour, camera.width, camera.height), alpha, frame.name))
    return photographs


def load_views(frames: list[PosedFrame], background: tuple[float, float, float], max_views: int | None = None,
               scale: float = 1.0) -> list[View]:  # fmt: skip
    """``load_frames``, laid on ``background``."""
    return [View(p.camera, p.on(background), p.name) for p in load_frames(frames, max_views, scale)]


def _scaled(camera: Camera, scale: float) -> Camera:
    if scale == 1.0:
        return camera
    return camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))


def _subsample(frames: list[PosedFrame], max_views: int | None) -> list[PosedFrame]:
    """At most ``max_views`` frames, evenly spaced over the list, in order."""
    if max_views is None or max_views >= len(frames):
        return frames
    if max_views <= 0:
        raise ValueError(f"max_views must be positive, got {max_views}")
    return [frames[i * len(frames) // max_views] for i in range(max_views)]
