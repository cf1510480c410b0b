"""Posed image sets: NeRF-Synthetic (``transforms_*.json``, ``nerf.py``) and COLMAP (``sparse/0``, text or binary,
``colmap.py``), read into frames, photographs and views (``posed.py``) from their image files (``images.py``),
distorted photographs undistorted to pinhole cameras on load (``lens.py``).

Every camera comes out in our convention (``cameras.COORDINATE_CONVENTION``: OpenCV axes, world-to-camera). Sets
without a test split of their own are split by the LLFF hold-out: every 8th image by name is "test".

In either layout an image path that leads out of the dataset folder (absolute, through ``..`` or a symbolic link) is
refused: uploaded datasets are read on a worker, whose other files they must not reach.
"""

from __future__ import annotations

from pathlib import Path

from ..cameras import View
from .colmap import COLMAP_MODELS, colmap_frames, colmap_model_dir, load_colmap, read_colmap_model
from .errors import DatasetError
from .images import load_frames, load_views, pixel_limit, read_frame, read_image, read_premultiplied, resize_image
from .lens import Lens
from .nerf import has_transforms, load_nerf_synthetic, nerf_synthetic_frames, write_nerf_synthetic
from .posed import (
    LLFF_HOLD,
    Layout,
    Photograph,
    PosedFrame,
    Split,
    check_background,
    composite,
)

__all__ = [
    "COLMAP_MODELS", "LLFF_HOLD", "DatasetError", "Layout", "Lens", "Photograph", "PosedFrame", "Split", "View",
    "colmap_frames", "colmap_model_dir", "composite", "dataset_frames", "dataset_layout", "load_colmap",
    "load_dataset", "load_nerf_synthetic", "load_photographs", "nerf_synthetic_frames", "pixel_limit",
    "read_colmap_model", "read_frame", "read_image", "read_premultiplied", "resize_image", "write_nerf_synthetic",
]  # fmt: skip


def dataset_layout(root: str | Path) -> Layout:
    """Which loader reads ``root``; DatasetError when neither layout is there."""
    root = Path(root)
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else "does not exist"
        raise DatasetError("not_found", f"dataset folder {root} {what}")
    if has_transforms(root):
        return "nerf_synthetic"
    if colmap_model_dir(root) is not None:
        return "colmap"
    raise DatasetError(
        "unknown_layout",
        f"{root.name}: neither a NeRF-Synthetic dataset (transforms_train.json, ... or transforms.json) nor a COLMAP "
        f"one (sparse/0/cameras.bin or cameras.txt)",
    )


def dataset_frames(root: str | Path, split: Split = "all") -> list[PosedFrame]:
    """Cameras and image paths of either layout, without decoding any image."""
    if dataset_layout(root) == "nerf_synthetic":
        frames = nerf_synthetic_frames(root, split)
    else:
        frames = colmap_frames(root, split)
    if not frames:
        raise DatasetError("empty", f"{Path(root).name}: split {split!r} has no views")
    return frames


def load_dataset(
    root: str | Path,
    split: Split = "all",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_views: int | None = None,
    scale: float = 1.0,
) -> list[View]:
    """Views of a NeRF-Synthetic or COLMAP dataset, whichever ``root`` holds."""
    background = check_background(background)
    return load_views(dataset_frames(root, split), background, max_views, scale)


def load_photographs(
    root: str | Path, split: Split = "all", max_views: int | None = None, scale: float = 1.0
) -> list[Photograph]:
    """The views of ``load_dataset`` before they are laid on a background."""
    return load_frames(dataset_frames(root, split), max_views, scale)
