"""Posed image sets: NeRF-Synthetic (``transforms_*.json``) and COLMAP (``sparse/0``, text or binary).

Every camera comes out in our convention (``cameras.COORDINATE_CONVENTION``: OpenCV axes, world-to-camera).
Images are float32 [H, W, 3] in [0, 1]; RGBA images are composited on a chosen background, after resizing: a
``Photograph`` keeps its alpha, so what was read once can be laid on another background without reading it again.

NeRF-Synthetic: ``transform_matrix`` is camera-to-world with OpenGL/Blender camera axes (x right, y up, z back);
the focal length comes from ``camera_angle_x`` (or ``fl_x``/``fl_y``/``cx``/``cy`` when given, as in
instant-ngp style files, also per frame). A single ``transforms.json`` (instant-ngp, nerfstudio), or a
``transforms_train.json`` without ``transforms_test.json``, is split by the LLFF hold-out below. Distortion
coefficients (``k1``, ``k2``, ``k3``, ``k4``, ``p1``, ``p2``) must be zero and ``camera_model``, when given, a
pinhole or OPENCV one, as for COLMAP. nerfstudio trains (and by default exports its splats) in a frame of its own,
turned, moved and scaled from the poses' frame; with its ``dataparser_transforms.json`` (``transform`` [3, 4],
``scale``) beside the transforms file, the poses are brought into that frame, as nerfstudio brings them.
Intrinsics must be finite, sizes and focal lengths positive.

COLMAP: ``sparse/0/{cameras,images}.{txt,bin}`` (binary preferred when both exist; ``points3D`` is not needed).
Images come from ``images/`` or, when absent, the ``images_N`` folder with the smallest N; intrinsics are rescaled
to the size of the image actually read. Pinhole models (PINHOLE, SIMPLE_PINHOLE) are exact. SIMPLE_RADIAL, RADIAL
and OPENCV are accepted when their distortion coefficients are zero; otherwise loading fails with
``distorted_camera`` (undistort with COLMAP's ``image_undistorter``) unless ``ignore_distortion=True`` treats them
as pinhole cameras. Fisheye and other models fail with ``unknown_camera_model``. Hold-out split (LLFF
convention): images sorted by name, every 8th one (index 0, 8, 16, ...) is "test", the rest "train". Every
camera needs a positive size and finite intrinsics (a positive focal length), every image a finite rigid pose.

In either layout an image path that leads out of the dataset folder (absolute, through ``..`` or a symbolic link) is
refused: uploaded datasets are read on a worker, whose other files they must not reach.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from .cameras import Camera

Split = Literal["train", "val", "test", "all"]
Layout = Literal["nerf_synthetic", "colmap"]

LLFF_HOLD = 8
_NERF_SPLITS = ("train", "val", "test")
_NERF_SINGLE = "transforms.json"  # instant-ngp and nerfstudio: every frame in one file
_NERF_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_NERFSTUDIO_FRAME = "dataparser_transforms.json"
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
# NeRF-Synthetic's OpenGL camera axes (x right, y up, z back) to ours, OpenCV's (x right, y down, z forward); its own
# inverse.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])

# COLMAP camera models: id -> (name, parameter count).
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
_MODEL_IDS = {name: i for i, (name, _) in COLMAP_MODELS.items()}
# Where fx, fy, cx, cy sit in each supported model's parameters, and where its distortion coefficients start.
_INTRINSICS = {
    "SIMPLE_PINHOLE": ((0, 0, 1, 2), 3),
    "PINHOLE": ((0, 1, 2, 3), 4),
    "SIMPLE_RADIAL": ((0, 0, 1, 2), 3),
    "RADIAL": ((0, 0, 1, 2), 3),
    "OPENCV": ((0, 1, 2, 3), 4),
}


class DatasetError(ValueError):
    """A dataset that cannot be loaded; ``code`` says why in a machine-readable word.

    Codes: not_found, unknown_layout, bad_split, bad_json, bad_transforms, image_missing, bad_image, malformed,
    unknown_camera_model, distorted_camera, camera_missing, empty; and, from the pipeline, images_mismatch
    (``views.check_photographs``) and too_few_images (``views.dataset_views``).
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)  # both, so a pickled copy (Celery's failure hook) keeps the code
        self.code, self.message = code, message

    def __str__(self) -> str:
        return self.message


@dataclass
class View:
    """One posed image: ``image`` [H, W, 3] float32 in [0, 1], the size of ``camera``."""

    camera: Camera
    image: Tensor
    name: str


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
    """A camera and the image file it belongs to, before the image is decoded."""

    camera: Camera
    path: Path
    name: str


# ---------------------------------------------------------------------------------------------------------------
# Shared helpers


def _image_size(path: Path) -> tuple[int, int]:
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


def composite(colour: Tensor, alpha: Tensor | None, background: Tensor | tuple[float, float, float]) -> Tensor:
    """``colour`` [H, W, 3], premultiplied by ``alpha`` [H, W, 1] (None: opaque), laid on ``background`` [3]."""
    if alpha is None:
        return colour
    under = torch.as_tensor(background, dtype=colour.dtype, device=colour.device) * (1.0 - alpha)
    return (colour + under).clamp(0.0, 1.0)  # rounding may carry the sum a step past 1


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


def _check_background(background: tuple[float, float, float]) -> tuple[float, float, float]:
    values = tuple(float(v) for v in background)
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise ValueError(f"background must be three values in [0, 1], got {background}")
    return values  # type: ignore[return-value]


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _inside(root: Path, path: Path) -> bool:
    """Whether ``path``, its symbolic links followed, lies in the folder ``root``."""
    return path.resolve().is_relative_to(root.resolve())


def _rotation_ok(r: np.ndarray) -> bool:
    return bool(np.allclose(r @ r.T, np.eye(3), atol=1e-3) and abs(np.linalg.det(r) - 1.0) < 1e-3)


def _load_photographs(frames: list[PosedFrame]) -> list[Photograph]:
    photographs = []
    for frame in frames:
        colour, alpha = read_premultiplied(frame.path)
        w, h = frame.camera.width, frame.camera.height
        # Resized before compositing, so the same pixels can be laid on any background; premultiplied, that gives
        # what resizing the composite would.
        alpha = None if alpha is None else resize_image(alpha, w, h)
        photographs.append(Photograph(frame.camera, resize_image(colour, w, h), alpha, frame.name))
    return photographs


def _load_views(frames: list[PosedFrame], background: tuple[float, float, float]) -> list[View]:
    return [View(p.camera, p.on(background), p.name) for p in _load_photographs(frames)]


# ---------------------------------------------------------------------------------------------------------------
# NeRF-Synthetic


def _find_image(root: Path, file_path: str) -> Path:
    base = root / file_path
    candidates = [base] + [base.with_name(base.name + s) for s in _IMAGE_SUFFIXES]
    for candidate in candidates:
        # Checked before existence, so that a path out of the folder cannot even learn what exists there.
        if not _inside(root, candidate):
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
        if c2w.shape not in ((4, 4), (3, 4)) or not np.isfinite(c2w).all() or not _rotation_ok(c2w[:3, :3]):
            raise DatasetError("bad_transforms", f"{path.name}: frame {i} transform_matrix is not a rigid 4x4 pose")
        image_path = _find_image(root, file_path)
        width, height = _image_size(image_path)
        fx, fy, cx, cy = _nerf_intrinsics({**meta, **frame}, width, height, path)
        rotation = (to_frame[:, :3] @ c2w[:3, :3] @ _GL_TO_CV).T
        t = -rotation @ (scale * (to_frame[:, :3] @ c2w[:3, 3] + to_frame[:, 3]))
        camera = Camera(
            torch.from_numpy(rotation).float(), torch.from_numpy(t).float(), fx, fy, cx, cy, width, height, file_path
        )
        frames.append(PosedFrame(camera, image_path, file_path))
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
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not _rotation_ok(transform[:, :3]):
        raise DatasetError("bad_transforms", f"{path.name}: 'transform' is not a rigid 3x4 transform")
    if not (math.isfinite(scale) and scale > 0):
        raise DatasetError("bad_transforms", f"{path.name}: 'scale' must be positive, got {scale}")
    return transform, scale


def _nerf_intrinsics(meta: dict, width: int, height: int, path: Path) -> tuple[float, float, float, float]:
    model = meta.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise DatasetError("unknown_camera_model", f"{path.name}: camera model {model!r} is not a pinhole one")
    try:
        distortion = [float(meta.get(k, 0.0)) for k in _NERF_DISTORTION]
    except (TypeError, ValueError) as exc:
        raise DatasetError("bad_transforms", f"{path.name}: bad distortion coefficients ({exc})") from None
    if any(distortion):
        raise DatasetError("distorted_camera", f"{path.name}: distortion coefficients are not zero; undistort the "
                           "images first (nerfstudio's ns-process-data, COLMAP's image_undistorter)")  # fmt: skip
    if "fl_x" in meta:
        # Given for a stated image size (pixels), rescaled to the size actually read.
        fl_x = _nerf_number(meta, "fl_x", path)
        fl_y = _nerf_number(meta, "fl_y", path, default=fl_x)
        w = _nerf_number(meta, "w", path, default=width)
        h = _nerf_number(meta, "h", path, default=height)
        cx = _nerf_number(meta, "cx", path, default=w / 2, positive=False)
        cy = _nerf_number(meta, "cy", path, default=h / 2, positive=False)
        sx, sy = width / w, height / h
        return fl_x * sx, fl_y * sy, cx * sx, cy * sy
    angle = _nerf_number(meta, "camera_angle_x", path)
    if angle >= math.pi:
        raise DatasetError("bad_transforms", f"{path.name}: camera_angle_x must be in (0, pi) radians, got {angle}")
    fx = 0.5 * width / math.tan(0.5 * angle)
    return fx, fx, width / 2.0, height / 2.0


def _nerf_number(meta: dict, key: str, path: Path, default: float | None = None, positive: bool = True) -> float:
    """``meta[key]`` (``default`` when absent), finite and, when ``positive``, above 0; a NaN or an infinite value
    (which JSON readers accept) would otherwise surface far from its cause."""
    try:
        value = float(meta.get(key, default))
    except (TypeError, ValueError) as exc:
        raise DatasetError("bad_transforms", f"{path.name}: {key} is not a number ({exc})") from None
    if not _finite(value) or (positive and value <= 0.0):
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
        return _held_out(_nerf_frames(root, _NERF_SINGLE), split)
    if split == "all":
        return [f for s in present for f in _nerf_frames(root, f"transforms_{s}.json")]
    if split in ("train", "test") and "test" not in present and "train" in present:
        return _held_out(_nerf_frames(root, "transforms_train.json"), split)
    return _nerf_frames(root, f"transforms_{split}.json")


def _in_split(index: int, split: Split) -> bool:
    """Whether the ``index``-th view by name is in ``split`` ("train", "test" or "all") by the LLFF hold-out: every
    ``LLFF_HOLD``-th is "test"."""
    return split == "all" or (index % LLFF_HOLD == 0) == (split == "test")


def _held_out(frames: list[PosedFrame], split: Split) -> list[PosedFrame]:
    """``split`` of ``frames`` by the LLFF hold-out (``_in_split``; no "val")."""
    if split == "all":
        return frames
    if split == "val":
        return []
    return [f for i, f in enumerate(sorted(frames, key=lambda f: f.name)) if _in_split(i, split)]


def load_nerf_synthetic(
    root: str | Path,
    split: Split = "train",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_views: int | None = None,
    scale: float = 1.0,
) -> list[View]:
    """Views of a NeRF-Synthetic split, RGBA composited on ``background``, resized by ``scale``."""
    background = _check_background(background)
    frames = _subsample(nerf_synthetic_frames(root, split), max_views)
    frames = [PosedFrame(_scaled(f.camera, scale), f.path, f.name) for f in frames]
    return _load_views(frames, background)


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


# ---------------------------------------------------------------------------------------------------------------
# COLMAP


@dataclass(frozen=True)
class ColmapCamera:
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ColmapImage:
    """A registered image: world-to-camera rotation ``qvec`` (w, x, y, z) and translation ``tvec``."""

    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str


class _Bytes:
    """Bounds-checked reading of a little-endian COLMAP binary file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def remaining(self) -> int:
        return len(self.data) - self.pos

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if size > self.remaining():
            raise DatasetError("malformed", f"{self.path.name}: ends early at byte {self.pos}")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def count(self, min_record: int) -> int:
        (n,) = self.read("Q")
        if n * min_record > self.remaining():
            raise DatasetError(
                "malformed", f"{self.path.name}: claims {n} records but holds only {self.remaining()} more bytes"
            )
        return n

    def skip(self, size: int) -> None:
        if size > self.remaining():
            raise DatasetError("malformed", f"{self.path.name}: ends early at byte {self.pos}")
        self.pos += size

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError("malformed", f"{self.path.name}: unterminated image name at byte {self.pos}")
        raw, self.pos = self.data[self.pos : end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DatasetError("malformed", f"{self.path.name}: image name is not UTF-8") from None


def _model_name(model_id: int, path: Path) -> tuple[str, int]:
    if model_id not in COLMAP_MODELS:
        raise DatasetError("unknown_camera_model", f"{path.name}: unknown camera model id {model_id}")
    return COLMAP_MODELS[model_id]


def read_colmap_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    f = _Bytes(path)
    cameras = {}
    for _ in range(f.count(24)):
        camera_id, model_id, width, height = f.read("iiQQ")
        name, count = _model_name(model_id, path)
        cameras[camera_id] = ColmapCamera(name, width, height, f.read(f"{count}d"))
    return cameras


def read_colmap_images_binary(path: Path) -> dict[int, ColmapImage]:
    f = _Bytes(path)
    images = {}
    for _ in range(f.count(4 + 7 * 8 + 4 + 1 + 8)):
        (image_id,) = f.read("i")
        q = f.read("4d")
        t = f.read("3d")
        (camera_id,) = f.read("i")
        name = f.cstring()
        (points,) = f.read("Q")
        f.skip(points * 24)  # (x, y, point3D_id) per 2D point; not needed
        images[image_id] = ColmapImage(q, t, camera_id, name)  # type: ignore[arg-type]
    return images


def _text_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DatasetError("malformed", f"{path.name}: not a text file") from None
    return [(i + 1, line) for i, line in enumerate(text.splitlines()) if not line.lstrip().startswith("#")]


def read_colmap_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for number, line in _text_lines(path):
        words = line.split()
        if not words:
            continue
        try:
            camera_id, model, width, height = int(words[0]), words[1], int(words[2]), int(words[3])
            params = tuple(float(w) for w in words[4:])
        except (IndexError, ValueError):
            raise DatasetError("malformed", f"{path.name}: line {number} is malformed: {line.strip()!r}") from None
        if model not in _MODEL_IDS:
            raise DatasetError("unknown_camera_model", f"{path.name}: unknown camera model {model!r}")
        expected = COLMAP_MODELS[_MODEL_IDS[model]][1]
        if len(params) != expected:
            raise DatasetError(
                "malformed", f"{path.name}: {model} needs {expected} parameters, line {number} has {len(params)}"
            )
        cameras[camera_id] = ColmapCamera(model, width, height, params)
    return cameras


def read_colmap_images_text(path: Path) -> dict[int, ColmapImage]:
    # Two lines per image: the pose line, then its 2D points (possibly empty).
    lines = _text_lines(path)
    images = {}
    for number, line in lines[0::2]:
        if not line.strip():
            continue
        words = line.split(maxsplit=9)
        try:
            image_id = int(words[0])
            q = tuple(float(w) for w in words[1:5])
            t = tuple(float(w) for w in words[5:8])
            camera_id, name = int(words[8]), words[9].strip()
        except (IndexError, ValueError):
            raise DatasetError("malformed", f"{path.name}: line {number} is malformed: {line.strip()!r}") from None
        images[image_id] = ColmapImage(q, t, camera_id, name)  # type: ignore[arg-type]
    return images


def colmap_model_dir(root: Path) -> Path | None:
    """The folder holding cameras.{txt,bin} and images.{txt,bin}: sparse/0, or sparse."""
    for folder in (root / "sparse" / "0", root / "sparse"):
        if any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    return None


def read_colmap_model(root: str | Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage]]:
    """Cameras and registered images of a COLMAP reconstruction (binary files preferred over text), each camera and
    pose checked (``_check_camera``, ``_check_pose``)."""
    root = Path(root)
    folder = colmap_model_dir(root)
    if folder is None:
        raise DatasetError("not_found", f"{root.name}: no sparse/0/cameras.bin or cameras.txt")
    if (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file():
        cameras = read_colmap_cameras_binary(folder / "cameras.bin")
        images = read_colmap_images_binary(folder / "images.bin")
    elif (folder / "cameras.txt").is_file() and (folder / "images.txt").is_file():
        cameras = read_colmap_cameras_text(folder / "cameras.txt")
        images = read_colmap_images_text(folder / "images.txt")
    else:
        raise DatasetError("not_found", f"{root.name}: {folder.name}/ lacks a matching images.bin or images.txt")
    for camera_id, camera in cameras.items():
        _check_camera(camera_id, camera)
    for image in images.values():
        _check_pose(image)
    return cameras, images


def _check_camera(camera_id: int, camera: ColmapCamera) -> None:
    """Refuses a camera no image can be scaled to: a size (pixels) that is not positive, a parameter that is not
    finite, a focal length that is not positive."""
    if camera.width <= 0 or camera.height <= 0:
        raise DatasetError("malformed", f"camera {camera_id}: size {camera.width}x{camera.height} is not positive")
    if not _finite(*camera.params):
        raise DatasetError("malformed", f"camera {camera_id}: parameters {list(camera.params)} are not all finite")
    if camera.model in _INTRINSICS:
        focal = [camera.params[i] for i in _INTRINSICS[camera.model][0][:2]]
        if min(focal) <= 0.0:
            raise DatasetError("malformed", f"camera {camera_id}: focal length {focal} is not positive")


def _check_pose(image: ColmapImage) -> None:
    """Refuses an image whose quaternion is no rotation (zero, NaN, infinite) or whose translation is not finite."""
    with np.errstate(invalid="ignore", divide="ignore"):  # such a quaternion normalises to NaN: no rotation
        rotation = _quat_to_rotmat(image.qvec)
    if not (_rotation_ok(rotation) and _finite(*image.tvec)):
        raise DatasetError(
            "malformed", f"image {image.name}: pose {list(image.qvec)}, {list(image.tvec)} is not a finite rigid one"
        )


def _quat_to_rotmat(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pinhole(camera: ColmapCamera, ignore_distortion: bool, camera_id: int) -> tuple[float, float, float, float]:
    if camera.model not in _INTRINSICS:
        raise DatasetError(
            "unknown_camera_model",
            f"camera {camera_id}: model {camera.model} is not supported (PINHOLE, SIMPLE_PINHOLE; SIMPLE_RADIAL, "
            f"RADIAL and OPENCV without distortion)",
        )
    index, distortion_start = _INTRINSICS[camera.model]
    distortion = camera.params[distortion_start:]
    if any(d != 0.0 for d in distortion) and not ignore_distortion:
        raise DatasetError(
            "distorted_camera",
            f"camera {camera_id}: {camera.model} has distortion {list(distortion)}; undistort the images first "
            f"(colmap image_undistorter) or load with ignore_distortion=True to treat it as a pinhole camera",
        )
    fx, fy, cx, cy = (camera.params[i] for i in index)
    return fx, fy, cx, cy


def _colmap_image_dir(root: Path, images: str | None) -> Path:
    if images is not None:
        folder = root / images
        if not folder.is_dir():
            raise DatasetError("image_missing", f"{root.name}: no image folder {images!r}")
        return folder
    if (root / "images").is_dir():
        return root / "images"
    downsampled = sorted(
        (int(p.name.split("_", 1)[1]), p) for p in root.glob("images_*") if p.is_dir() and p.name[7:].isdigit()
    )
    if not downsampled:
        raise DatasetError("image_missing", f"{root.name}: no images/ or images_N/ folder")
    return downsampled[0][1]


def colmap_frames(
    root: str | Path, split: Split = "all", *, images: str | None = None, ignore_distortion: bool = False
) -> list[PosedFrame]:
    """Cameras and image paths of a COLMAP dataset, sorted by image name; split by the LLFF hold-out."""
    root = Path(root)
    if split not in ("train", "test", "all"):
        raise DatasetError("bad_split", f"unknown split {split!r} for a COLMAP dataset; expected train, test or all")
    cameras, registered = read_colmap_model(root)
    folder = _colmap_image_dir(root, images)
    frames = []
    for index, image in enumerate(sorted(registered.values(), key=lambda im: im.name)):
        if not _in_split(index, split):
            continue
        cam = cameras.get(image.camera_id)
        if cam is None:
            raise DatasetError("camera_missing", f"image {image.name} refers to missing camera {image.camera_id}")
        fx, fy, cx, cy = _pinhole(cam, ignore_distortion, image.camera_id)
        path = folder / image.name
        # Checked before existence, so that a name out of the folder cannot even learn what exists there.
        if not _inside(root, path):
            raise DatasetError("malformed", f"image {image.name!r} leads out of the dataset folder {root.name}/")
        if not path.is_file():
            raise DatasetError("image_missing", f"image {image.name} not found in {folder.name}/")
        width, height = _image_size(path)
        sx, sy = width / cam.width, height / cam.height
        if abs(sx - sy) > 0.02 * max(sx, sy):
            raise DatasetError(
                "bad_image",
                f"image {image.name} is {width}x{height} but camera {image.camera_id} is {cam.width}x{cam.height}: "
                f"the aspect ratios differ",
            )
        rotation = _quat_to_rotmat(image.qvec)
        camera = Camera(
            torch.from_numpy(rotation).float(),
            torch.tensor(image.tvec, dtype=torch.float32),
            fx * sx,
            fy * sy,
            cx * sx,
            cy * sy,
            width,
            height,
            image.name,
        )
        frames.append(PosedFrame(camera, path, image.name))
    return frames


def load_colmap(
    root: str | Path,
    split: Split = "all",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_views: int | None = None,
    scale: float = 1.0,
    *,
    images: str | None = None,
    ignore_distortion: bool = False,
) -> list[View]:
    """Views of a COLMAP dataset (see the module docstring for models, image folders and the hold-out split)."""
    background = _check_background(background)
    frames = _subsample(colmap_frames(root, split, images=images, ignore_distortion=ignore_distortion), max_views)
    frames = [PosedFrame(_scaled(f.camera, scale), f.path, f.name) for f in frames]
    return _load_views(frames, background)


# ---------------------------------------------------------------------------------------------------------------
# Either layout


def dataset_layout(root: str | Path) -> Layout:
    """Which loader reads ``root``; DatasetError when neither layout is there."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError("not_found", f"dataset folder {root} does not exist")
    if any((root / f"transforms_{s}.json").is_file() for s in _NERF_SPLITS) or (root / _NERF_SINGLE).is_file():
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
    background = _check_background(background)
    return [View(p.camera, p.on(background), p.name) for p in load_photographs(root, split, max_views, scale)]


def load_photographs(
    root: str | Path, split: Split = "all", max_views: int | None = None, scale: float = 1.0
) -> list[Photograph]:
    """The views of ``load_dataset`` before they are laid on a background."""
    frames = _subsample(dataset_frames(root, split), max_views)
    return _load_photographs([PosedFrame(_scaled(f.camera, scale), f.path, f.name) for f in frames])
