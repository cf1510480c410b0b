"""COLMAP reconstructions: ``sparse/0/{cameras,images}.{txt,bin}`` (binary preferred when both exist; ``points3D``
is not needed).

Images come from ``images/`` or, when absent, the ``images_N`` folder with the smallest N; intrinsics are rescaled
to the size of the image actually read, which must have its camera's aspect ratio, as stored or turned by its EXIF
orientation (``images.oriented_size``). Pinhole models (PINHOLE, SIMPLE_PINHOLE) are read as they are; the
distorted ones (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) are undistorted on load to the pinhole camera COLMAP's
``image_undistorter`` gives them (``lens``). Fisheye models (OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE,
RADIAL_FISHEYE, THIN_PRISM_FISHEYE) and FOV fail with ``unsupported_camera_model``, unknown ones with
``unknown_camera_model``. Hold-out split (LLFF
convention): images sorted by name, every 8th one (index 0, 8, 16, ...) is "test", the rest "train". Every
camera needs a positive size and finite intrinsics (a positive focal length), every image a finite rigid pose. An
image name that leads out of the dataset folder is refused (``malformed``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..cameras import View
from .errors import DatasetError
from .images import load_views, oriented_size
from .lens import Lens
from .posed import (
    PosedFrame,
    Split,
    check_background,
    finite,
    in_split,
    inside,
    posed_frame,
    rotation_ok,
)

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
# Where fx, fy, cx, cy sit in each supported model's parameters, and the names of its distortion coefficients after
# them (OpenCV's order; FULL_OPENCV's k4 k5 k6 are the denominator of OpenCV's rational model).
_INTRINSICS = {
    "SIMPLE_PINHOLE": ((0, 0, 1, 2), ()),
    "PINHOLE": ((0, 1, 2, 3), ()),
    "SIMPLE_RADIAL": ((0, 0, 1, 2), ("k1",)),
    "RADIAL": ((0, 0, 1, 2), ("k1", "k2")),
    "OPENCV": ((0, 1, 2, 3), ("k1", "k2", "p1", "p2")),
    "FULL_OPENCV": ((0, 1, 2, 3), ("k1", "k2", "p1", "p2", "k3", "d1", "d2", "d3")),
}
# Models no pinhole holds whole: fisheye lenses see past 180 degrees, and COLMAP's FOV model is a fisheye's too.
_UNSUPPORTED = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "FOV")


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
        images[image_id] = ColmapImage(q, t, camera_id, name)
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


def _is_numbers(line: str) -> bool:
    try:
        [float(word) for word in line.split()]
    except ValueError:
        return False
    return True


def read_colmap_images_text(path: Path) -> dict[int, ColmapImage]:
    # COLMAP writes two lines per image, the pose and then its 2D points (possibly empty), but converters and hand
    # edits drop the empty ones or add blank lines: a line is told by what it holds, not by where it falls. A points
    # line is numbers only; a pose line ends with the image's name.
    images = {}
    for number, line in _text_lines(path):
        if not line.strip() or _is_numbers(line):
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
    if not finite(*camera.params):
        raise DatasetError("malformed", f"camera {camera_id}: parameters {list(camera.params)} are not all finite")
    if camera.model in _INTRINSICS:
        focal = [camera.params[i] for i in _INTRINSICS[camera.model][0][:2]]
        if min(focal) <= 0.0:
            raise DatasetError("malformed", f"camera {camera_id}: focal length {focal} is not positive")


def _check_pose(image: ColmapImage) -> None:
    """Refuses an image whose quaternion is no rotation (zero, NaN, infinite) or whose translation is not finite."""
    with np.errstate(invalid="ignore", divide="ignore"):  # such a quaternion normalises to NaN: no rotation
        rotation = _quat_to_rotmat(image.qvec)
    if not (rotation_ok(rotation) and finite(*image.tvec)):
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


def _lens(camera: ColmapCamera, camera_id: int) -> Lens:
    """The lens of ``camera``, for an image of the camera's own size."""
    if camera.model in _UNSUPPORTED:
        raise DatasetError(
            "unsupported_camera_model",
            f"camera {camera_id}: model {camera.model} is a fisheye one, which no pinhole camera holds whole; "
            f"undistort the photographs first (COLMAP's image_undistorter writes them with a PINHOLE model)",
        )
    if camera.model not in _INTRINSICS:
        raise DatasetError("unknown_camera_model", f"camera {camera_id}: model {camera.model} is not supported")
    index, names = _INTRINSICS[camera.model]
    fx, fy, cx, cy = (camera.params[i] for i in index)
    k = dict(zip(names, camera.params[max(index) + 1 :], strict=True))
    return Lens(fx, fy, cx, cy, camera.width, camera.height,
                radial=(k.get("k1", 0.0), k.get("k2", 0.0), k.get("k3", 0.0), 0.0),
                tangential=(k.get("p1", 0.0), k.get("p2", 0.0)),
                rational=(k.get("d1", 0.0), k.get("d2", 0.0), k.get("d3", 0.0)))  # fmt: skip


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


def colmap_frames(root: str | Path, split: Split = "all", *, images: str | None = None) -> list[PosedFrame]:
    """Cameras and image paths of a COLMAP dataset, sorted by image name; split by the LLFF hold-out."""
    root = Path(root)
    if split not in ("train", "test", "all"):
        raise DatasetError("bad_split", f"unknown split {split!r} for a COLMAP dataset; expected train, test or all")
    cameras, registered = read_colmap_model(root)
    folder = _colmap_image_dir(root, images)
    frames = []
    for index, image in enumerate(sorted(registered.values(), key=lambda im: im.name)):
        if not in_split(index, split):
            continue
        cam = cameras.get(image.camera_id)
        if cam is None:
            raise DatasetError("camera_missing", f"image {image.name} refers to missing camera {image.camera_id}")
        lens = _lens(cam, image.camera_id)
        path = folder / image.name
        # Checked before existence, so that a name out of the folder cannot even learn what exists there.
        if not inside(root, path):
            raise DatasetError("malformed", f"image {image.name!r} leads out of the dataset folder {root.name}/")
        if not path.is_file():
            raise DatasetError("image_missing", f"image {image.name} not found in {folder.name}/")
        orientation, width, height = oriented_size(path, cam.width, cam.height, f"camera {image.camera_id}")
        rotation = torch.from_numpy(_quat_to_rotmat(image.qvec)).float()
        lens = lens.scaled(width / cam.width, height / cam.height, width, height)
        frames.append(posed_frame(rotation, torch.tensor(image.tvec, dtype=torch.float32), lens, path, image.name,
                                  orientation))  # fmt: skip
    return frames


def load_colmap(
    root: str | Path,
    split: Split = "all",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_views: int | None = None,
    scale: float = 1.0,
    *,
    images: str | None = None,
) -> list[View]:
    """Views of a COLMAP dataset (see the module docstring for models, image folders and the hold-out split)."""
    background = check_background(background)
    return load_views(colmap_frames(root, split, images=images), background, max_views, scale)
