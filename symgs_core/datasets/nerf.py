"""NeRF-Synthetic and instant-ngp / nerfstudio image sets (``transforms_*.json``, ``transforms.json``).

``transform_matrix`` is camera-to-world with OpenGL/Blender camera axes (x right, y up, z back); the focal length
comes from ``camera_angle_x`` (or ``fl_x``/``fl_y``/``cx``/``cy`` when given, as in instant-ngp style files, also
per frame). A single ``transforms.json`` (instant-ngp, nerfstudio), or a ``transforms_train.json`` without
``transforms_test.json``, is split by the LLFF hold-out (``posed.in_split``). Distortion coefficients (``k1``,
``k2``, ``k3``, ``k4``, ``p1``, ``p2``, also per frame, as nerfstudio allows; ``k4`` is nerfstudio's r^8 term) are
undone on load (``lens``); ``camera_model``, when given, must be a pinhole or OPENCV one: fisheye and panoramic
models (``OPENCV_FISHEYE``, ``EQUIRECTANGULAR``, instant-ngp's ``is_fisheye``) fail with
``unsupported_camera_model``. nerfstudio trains (and by default exports its splats) in a frame of its own, turned,
moved and scaled from the poses' frame; with its ``dataparser_transforms.json`` (``transform`` [3, 4], ``scale``)
beside the transforms file, the poses are brought into that frame, as nerfstudio brings them. Intrinsics must be
finite, sizes and focal lengths positive; an image with a stated size (``w``, ``h``) must have its aspect ratio, as
stored or turned by its EXIF orientation (``images.oriented_size``). An image path that leads out of the dataset
folder is refused (``bad_transforms``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera, View
from .errors import DatasetError
from .images import image_size, load_views, oriented_size
from .lens import Lens
from .posed import (
    PosedFrame,
    Split,
    check_background,
    finite,
    held_out,
    inside,
    posed_frame,
    rotation_ok,
)

_NERF_SPLITS = ("train", "val", "test")
_NERF_SINGLE = "transforms.json"  # instant-ngp and nerfstudio: every frame in one file
_NERF_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
# nerfstudio's and instant-ngp's models that no pinhole holds whole (instant-ngp also says "is_fisheye": true).
_NERF_UNSUPPORTED = ("OPENCV_FISHEYE", "FISHEYE624", "EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L",
                     "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R")  # fmt: skip
_NERFSTUDIO_FRAME = "dataparser_transforms.json"
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
# NeRF-Synthetic's OpenGL camera axes (x right, y up, z back) to ours, OpenCV's (x right, y down, z forward); its own
# inverse.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def has_transforms(root: Path) -> bool:
    """Whether ``root`` holds a transforms file this module reads."""
    return any((root / f"transforms_{s}.json").is_file() for s in _NERF_SPLITS) or (root / _NERF_SINGLE).is_file()


def _find_image(root: Path, file_path: str) -> Path:
    base = root / file_path
    candidates = [base] + [base.with_name(base.name + s) for s in _IMAGE_SUFFIXES]
    for candidate in candidates:
        # Checked before existence, so that a path out of the folder cannot even learn what exists there.
        if not inside(root, candidate):
            raise DatasetError("bad_transforms", f"image {file_path!r} leads out of the dataset folder {root.name}/")
        if candidate.is_file():
            return candidate
    raise DatasetError(
        "image_missing", f"image {file_path!r} not found under {root.name}/ (tried {', '.join(_IMAGE_SUFFIXES)})"
    )


def _nerf_frames(root: Path, name: str) -> list[PosedFrame]:
    path = root / name
    if not path.is_file():
        raise DatasetError("not_found", f"{root.name}: no {path.name}")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError("bad_json", f"{path.name}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DatasetError("bad_transforms", f"{path.name}: expected an object with a 'frames' list")
    if "camera_angle_x" not in meta and "fl_x" not in meta:
        raise DatasetError("bad_transforms", f"{path.name}: neither 'camera_angle_x' nor 'fl_x' is given")
    to_frame, scale = _nerfstudio_frame(root)
    frames = []
    for i, frame in enumerate(meta["frames"]):
        try:
            file_path = str(frame["file_path"])
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError("bad_transforms", f"{path.name}: frame {i} is malformed ({exc})") from None
        if c2w.shape not in ((4, 4), (3, 4)) or not np.isfinite(c2w).all() or not rotation_ok(c2w[:3, :3]):
            raise DatasetError("bad_transforms", f"{path.name}: frame {i} transform_matrix is not a rigid 4x4 pose")
        image_path = _find_image(root, file_path)
        own = {**meta, **frame}
        orientation, width, height = 1, *image_size(image_path)
        if "w" in own and "h" in own:  # a stated size: the image is read the way that has its aspect ratio
            stated = _nerf_number(own, "w", path), _nerf_number(own, "h", path)
            orientation, width, height = oriented_size(image_path, *stated, f"{path.name}'s camera")
        lens = _nerf_intrinsics(own, width, height, path)
        rotation = (to_frame[:, :3] @ c2w[:3, :3] @ _GL_TO_CV).T
        t = -rotation @ (scale * (to_frame[:, :3] @ c2w[:3, 3] + to_frame[:, 3]))
        frames.append(posed_frame(torch.from_numpy(rotation).float(), torch.from_numpy(t).float(), lens, image_path,
                                  file_path, orientation))  # fmt: skip
    return frames


def _nerfstudio_frame(root: Path) -> tuple[np.ndarray, float]:
    """The rigid ``transform`` [3, 4] and ``scale`` that take the poses into nerfstudio's training frame (identity
    and 1 without ``dataparser_transforms.json``)."""
    path = root / _NERFSTUDIO_FRAME
    if not path.is_file():
        return np.eye(3, 4), 1.0
    try:
        meta = json.loads(path.read_text())
        transform = np.asarray(meta["transform"], dtype=np.float64)
        scale = float(meta.get("scale", 1.0))
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DatasetError("bad_transforms", f"{path.name}: expected 'transform' [3, 4] and 'scale' ({exc})") from None
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not rotation_ok(transform[:, :3]):
        raise DatasetError("bad_transforms", f"{path.name}: 'transform' is not a rigid 3x4 transform")
    if not (math.isfinite(scale) and scale > 0):
        raise DatasetError("bad_transforms", f"{path.name}: 'scale' must be positive, got {scale}")
    return transform, scale


def _nerf_intrinsics(meta: dict, width: int, height: int, path: Path) -> Lens:
    """The camera of one frame (its own keys over the file's), for its image of ``width`` x ``height``."""
    model = meta.get("camera_model", "OPENCV")
    if model in _NERF_UNSUPPORTED or meta.get("is_fisheye"):
        name = model if model in _NERF_UNSUPPORTED else "is_fisheye"
        raise DatasetError("unsupported_camera_model", f"{path.name}: camera model {name} is a fisheye or panoramic "
                           "one, which no pinhole camera holds whole; undistort the photographs to a pinhole model "
                           "first (COLMAP's image_undistorter)")  # fmt: skip
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise DatasetError("unknown_camera_model", f"{path.name}: camera model {model!r} is not a pinhole one")
    k1, k2, k3, k4, p1, p2 = (_nerf_number(meta, k, path, default=0.0, positive=False) for k in _NERF_DISTORTION)
    if "fl_x" in meta:
        # Given for a stated image size (pixels), rescaled to the size actually read.
        fl_x = _nerf_number(meta, "fl_x", path)
        fl_y = _nerf_number(meta, "fl_y", path, default=fl_x)
        w = _nerf_number(meta, "w", path, default=width)
        h = _nerf_number(meta, "h", path, default=height)
        cx = _nerf_number(meta, "cx", path, default=w / 2, positive=False)
        cy = _nerf_number(meta, "cy", path, default=h / 2, positive=False)
        sx, sy = width / w, height / h
        fx, fy, cx, cy = fl_x * sx, fl_y * sy, cx * sx, cy * sy
    else:
        angle = _nerf_number(meta, "camera_angle_x", path)
        if angle >= math.pi:
            raise DatasetError("bad_transforms", f"{path.name}: camera_angle_x must be in (0, pi) radians, got {angle}")
        fx = fy = 0.5 * width / math.tan(0.5 * angle)
        cx, cy = width / 2.0, height / 2.0
    return Lens(fx, fy, cx, cy, width, height, radial=(k1, k2, k3, k4), tangential=(p1, p2))


def _nerf_number(meta: dict, key: str, path: Path, default: float | None = None, positive: bool = True) -> float:
    """``meta[key]`` (``default`` when absent), finite and, when ``positive``, above 0; a NaN or an infinite value
    (which JSON readers accept) would otherwise surface far from its cause."""
    try:
        value = float(meta.get(key, default))  # type: ignore[arg-type]  # None (absent, no default): TypeError
    except (TypeError, ValueError) as exc:
        raise DatasetError("bad_transforms", f"{path.name}: {key} is not a number ({exc})") from None
    if not finite(value) or (positive and value <= 0.0):
        kind = "finite positive" if positive else "finite"
        raise DatasetError("bad_transforms", f"{path.name}: {key} must be a {kind} number, got {value}")
    return value


def nerf_synthetic_frames(root: str | Path, split: Split = "train") -> list[PosedFrame]:
    """Cameras and image paths of a NeRF-Synthetic split ("all": every transforms file present, in train, val,
    test order). Without a test split (a single ``transforms.json``, or no ``transforms_test.json``), the frames
    sorted by file path are split by the LLFF hold-out."""
    root = Path(root)
    if split != "all" and split not in _NERF_SPLITS:
        raise DatasetError("bad_split", f"unknown split {split!r}; expected train, val, test or all")
    present = [s for s in _NERF_SPLITS if (root / f"transforms_{s}.json").is_file()]
    if not present:
        if not (root / _NERF_SINGLE).is_file():
            raise DatasetError("not_found", f"{root.name}: no transforms_*.json or {_NERF_SINGLE}")
        return held_out(_nerf_frames(root, _NERF_SINGLE), split)
    if split == "all":
        return [f for s in present for f in _nerf_frames(root, f"transforms_{s}.json")]
    if split in ("train", "test") and "test" not in present and "train" in present:
        return held_out(_nerf_frames(root, "transforms_train.json"), split)
    return _nerf_frames(root, f"transforms_{split}.json")


def load_nerf_synthetic(
    root: str | Path,
    split: Split = "train",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_views: int | None = None,
    scale: float = 1.0,
) -> list[View]:
    """Views of a NeRF-Synthetic split, RGBA composited on ``background``, resized by ``scale``."""
    background = check_background(background)
    return load_views(nerf_synthetic_frames(root, split), background, max_views, scale)


def write_nerf_synthetic(root: str | Path, split: Split, cameras: list[Camera], images: list[Tensor]) -> None:
    """The inverse of ``load_nerf_synthetic`` for one split: ``transforms_{split}.json`` (OpenGL camera-to-world,
    the cameras' shared ``fl_x``, ``fl_y``, ``cx``, ``cy``) and ``{split}/r_{i}.png`` from images [H, W, 3] in
    [0, 1], 8 bits per channel, no alpha (read back as they are, whatever the background). Without a test split
    the set reads back held out (``nerf_synthetic_frames``): read a lone split back as "all"."""
    from PIL import Image

    if split not in _NERF_SPLITS:
        raise DatasetError("bad_split", f"unknown split {split!r}; expected train, val or test")
    if len(cameras) != len(images) or not cameras:
        raise ValueError(f"{len(cameras)} cameras for {len(images)} images: one image per camera, at least one")
    first = cameras[0]
    intrinsics = lambda c: (c.fx, c.fy, c.cx, c.cy, c.width, c.height)  # noqa: E731
    if any(intrinsics(c) != intrinsics(first) for c in cameras):
        raise ValueError("the cameras of a NeRF-Synthetic split share their intrinsics")
    root = Path(root)
    (root / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (camera, image) in enumerate(zip(cameras, images, strict=True)):
        if tuple(image.shape) != (camera.height, camera.width, 3):
            raise ValueError(f"image {i} is {tuple(image.shape)}, camera {i} is {camera.height}x{camera.width}")
        pixels = (image.detach().cpu().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()
        Image.fromarray(pixels, "RGB").save(root / split / f"r_{i}.png")
        c2w = np.eye(4)
        c2w[:3, :3] = camera.R.double().cpu().numpy().T @ _GL_TO_CV
        c2w[:3, 3] = camera.center.double().cpu().numpy()
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
    meta = {"fl_x": first.fx, "fl_y": first.fy, "cx": first.cx, "cy": first.cy, "w": first.width, "h": first.height,
            "frames": frames}  # fmt: skip
    (root / f"transforms_{split}.json").write_text(json.dumps(meta))
