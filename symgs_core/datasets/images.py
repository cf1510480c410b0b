"""Image files of a posed set: read (alpha premultiplied), undistorted (``lens``), resized, laid on a background.

A service sets the most pixels an image may have (``pixel_limit``); an image above it is refused from its header,
before it is decoded, and so is one above Pillow's own bomb limit, whatever the setting.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera, View
from .errors import DatasetError
from .lens import UndistortionMaps, undistort_image, undistortion_maps
from .posed import Photograph, PosedFrame, composite

_PIXEL_LIMIT: ContextVar[int | None] = ContextVar("pixel_limit", default=None)
_EXIF_ORIENTATION = 0x0112
# EXIF orientation -> Pillow's transpose that shows the stored pixels upright (1: as stored)
_TURNS = {2: "FLIP_LEFT_RIGHT", 3: "ROTATE_180", 4: "FLIP_TOP_BOTTOM", 5: "TRANSPOSE", 6: "ROTATE_270",
          7: "TRANSVERSE", 8: "ROTATE_90"}  # fmt: skip
_SWAPS_AXES = (5, 6, 7, 8)


@contextmanager
def pixel_limit(pixels: int) -> Iterator[None]:
    """Refuse images above ``pixels`` (``image_too_large``) while inside. A context, not an argument: the limit is the
    service's, and images are read several calls below the job that knows it."""
    token = _PIXEL_LIMIT.set(pixels)
    try:
        yield
    finally:
        _PIXEL_LIMIT.reset(token)


def _check_pixels(path: Path, width: int, height: int) -> None:
    limit = _PIXEL_LIMIT.get()
    if limit is not None and width * height > limit:
        raise DatasetError("image_too_large", f"image {path.name} is {width}x{height}, above {limit} pixels")


def _unreadable(path: Path, exc: Exception) -> DatasetError:
    from PIL import Image, UnidentifiedImageError

    if isinstance(exc, Image.DecompressionBombError):
        return DatasetError("image_too_large", f"image {path.name} has too many pixels ({exc})")
    # Pillow's "cannot identify" and the system's errors name the file by its path on the machine that reads it (a
    # worker's, for a job): their reason only.
    if isinstance(exc, UnidentifiedImageError):
        reason = "not in an image format Pillow reads"
    else:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    return DatasetError("bad_image", f"cannot read image {path.name}: {reason}")


def image_size(path: Path) -> tuple[int, int]:
    """Width and height of the image at ``path`` as its pixels are stored, from its header."""
    return _header(path)[:2]


def _header(path: Path) -> tuple[int, int, int]:
    """Width and height as stored, and the EXIF orientation (1 where there is none, or none Pillow knows)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            width, height = im.size
            orientation = im.getexif().get(_EXIF_ORIENTATION, 1)
    except (OSError, Image.DecompressionBombError) as exc:
        raise _unreadable(path, exc) from None
    _check_pixels(path, width, height)
    return width, height, orientation if orientation in _TURNS else 1


def oriented_size(path: Path, width: float, height: float, camera: str) -> tuple[int, int, int]:
    """(orientation, width, height): the EXIF orientation to read the image at ``path`` in, and its size so turned,
    for a camera of ``width`` x ``height`` pixels; ``bad_image`` when neither the stored image nor the turned one has
    the camera's aspect ratio (within 2%).

    Phones store a portrait photograph as landscape pixels and an EXIF tag that turns them. Pose tools differ: COLMAP
    reads the stored pixels (its cameras then have their size), others turn the photograph first (their cameras have
    the turned size). The image is read the way whose aspect is the camera's: as stored wherever that fits, as
    COLMAP does; a turn that keeps the aspect (a half turn, a mirror) cannot be told that way and is not applied."""
    stored_w, stored_h, orientation = _header(path)
    fits = lambda w, h: abs(w / width - h / height) <= 0.02 * max(w / width, h / height)  # noqa: E731
    if fits(stored_w, stored_h):
        return 1, stored_w, stored_h
    if orientation in _SWAPS_AXES and fits(stored_h, stored_w):
        return orientation, stored_h, stored_w
    turned = f" (its EXIF orientation {orientation} turns it to {stored_h}x{stored_w})"
    turned = turned if orientation in _SWAPS_AXES else ""
    raise DatasetError(
        "bad_image",
        f"image {path.name} is {stored_w}x{stored_h}{turned} but {camera} is {width:g}x{height:g}: the aspect ratios "
        "differ",
    )


# Grey modes wider than 8 bits and their white: 16-bit PNGs open as I;16 (or I, by Pillow's version), float TIFFs as F.
_WIDE_GREY = {"I;16": 65535.0, "I;16L": 65535.0, "I;16B": 65535.0, "I;16N": 65535.0, "I": 65535.0, "F": 1.0}


def read_premultiplied(path: Path) -> tuple[Tensor, Tensor | None]:
    """Image [H, W, 3] float32 in [0, 1], premultiplied by its alpha channel [H, W, 1] (None: it has none)."""
    colour, alpha, _ = _decode(path, 1)
    return colour, alpha


def _decode(path: Path, reduce: int, orientation: int = 1) -> tuple[Tensor, Tensor | None, int]:
    """``read_premultiplied``, a JPEG decoded at 1/``reduce`` of its size where libjpeg's DCT scaling allows (1/2,
    1/4, 1/8: a fraction of the work and memory of the whole decode), other images whole, then turned as the EXIF
    ``orientation`` says (``oriented_size``); and the reduction made (pixel corners scale by its inverse; a reduced
    decode's last pixel may cover only part of a block)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            _check_pixels(path, *im.size)
            width = im.size[0]
            if reduce > 1 and im.format == "JPEG":
                im.draft("RGB", (im.size[0] // reduce, im.size[1] // reduce))
            made = round(width / im.size[0])
            upright = im.transpose(Image.Transpose[_TURNS[orientation]]) if orientation in _TURNS else im
            if upright.mode in _WIDE_GREY:
                # Pillow's conversion to RGB clips these at 255, which would read a 16-bit grey photograph as white
                grey = np.clip(np.asarray(upright, dtype=np.float32) / _WIDE_GREY[upright.mode], 0.0, 1.0)
                return torch.from_numpy(np.repeat(grey[..., None], 3, axis=-1)), None, made
            has_alpha = upright.mode in ("RGBA", "LA", "PA") or "transparency" in upright.info
            array = np.asarray(upright.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except (OSError, Image.DecompressionBombError) as exc:
        raise _unreadable(path, exc) from None
    rgb = torch.from_numpy(array[..., :3].copy())
    if not has_alpha:
        return rgb, None, made
    alpha = torch.from_numpy(array[..., 3:].copy())
    return rgb * alpha, alpha, made


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
    times ``scale``; a distorted one undistorted to its pinhole camera (``read_frame``)."""
    maps: dict[tuple, UndistortionMaps] = {}  # per lens and size: every photograph of one lens shares its maps
    photographs = []
    for frame in _subsample(frames, max_views):
        camera = _scaled(frame.camera, scale)
        colour, alpha = read_frame(frame, camera.width, camera.height, maps)
        photographs.append(Photograph(camera, colour, alpha, frame.name))
    return photographs


def read_frame(
    frame: PosedFrame, width: int, height: int, maps: dict[tuple, UndistortionMaps] | None = None
) -> tuple[Tensor, Tensor | None]:
    """The photograph of ``frame`` at ``width`` x ``height``: colour [height, width, 3] premultiplied by alpha
    [height, width, 1] (None: opaque). ``maps`` keeps the undistortion maps of the lenses met, for the next call.

    A pinhole photograph is resized, nothing more. A distorted one is decoded at the largest reduction (1/2, 1/4,
    1/8 for a JPEG) that leaves its undistorted frame at least that size, undistorted there through maps computed
    once per lens and size, then resized: at the 256 px a job judges at, a phone photograph is never held whole.
    Where the undistorted frame samples outside the photograph (a lens past COLMAP's limits) its pixels are
    transparent."""
    if frame.lens is None:
        colour, alpha, _ = _decode(frame.path, 1, frame.orientation)
        # Resized before compositing, so the same pixels can be laid on any background; premultiplied, that gives
        # what resizing the composite would.
        alpha = None if alpha is None else resize_image(alpha, width, height)
        return resize_image(colour, width, height), alpha
    pinhole = frame.camera
    fits = lambda r: round(pinhole.width / r) >= width and round(pinhole.height / r) >= height  # noqa: E731
    colour, alpha, reduce = _decode(frame.path, next((r for r in (8, 4, 2) if fits(r)), 1), frame.orientation)
    lens = frame.lens.scaled(1.0 / reduce, 1.0 / reduce, colour.shape[1], colour.shape[0])
    middle = pinhole.resized(round(pinhole.width / reduce), round(pinhole.height / reduce))
    key = (lens, middle.fx, middle.fy, middle.cx, middle.cy, middle.width, middle.height)
    maps = {} if maps is None else maps
    if key not in maps:
        maps[key] = undistortion_maps(lens, middle.fx, middle.fy, middle.cx, middle.cy, middle.width, middle.height)
    found = maps[key]
    stacked = colour if alpha is None else torch.cat([colour, alpha], dim=-1)
    out = undistort_image(stacked, found)
    colour, alpha = out[..., :3], None if alpha is None else out[..., 3:]
    if not found.all_valid:
        inside = torch.from_numpy(found.valid)[..., None].to(colour.dtype)
        colour, alpha = colour * inside, inside if alpha is None else alpha * inside
    alpha = None if alpha is None else resize_image(alpha, width, height)
    return resize_image(colour, width, height), alpha


def load_views(frames: list[PosedFrame], background: tuple[float, float, float], max_views: int | None = None,
               scale: float = 1.0) -> list[View]:  # fmt: skip
    """``load_frames``, laid on ``background``; every pixel is the object's (no scene tells them apart here)."""
    views = []
    for p in load_frames(frames, max_views, scale):
        image = p.on(background)
        views.append(View(p.camera, image, image.new_ones(image.shape[:2], dtype=torch.bool), p.name))
    return views


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
