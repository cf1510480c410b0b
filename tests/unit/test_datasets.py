"""Dataset loaders: NeRF-Synthetic and COLMAP (text and binary), cameras against exact oracles."""

from __future__ import annotations

import json
import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageFile
from scipy.spatial.transform import Rotation

from symgs_core.cameras import Camera
from symgs_core.datasets import (
    COLMAP_MODELS,
    DatasetError,
    colmap_frames,
    dataset_frames,
    dataset_layout,
    load_colmap,
    load_dataset,
    load_nerf_synthetic,
    load_photographs,
    pixel_limit,
    read_colmap_model,
    read_premultiplied,
    write_nerf_synthetic,
)
from symgs_core.synthetic import quat_to_matrix
from tests.conftest import shared_file

MODEL_IDS = {name: i for i, (name, _) in COLMAP_MODELS.items()}


def poses(count: int) -> list[Camera]:
    """Cameras around the origin at different heights and distances, 40x30 pixels."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = (3.0 * math.cos(a), 3.0 * math.sin(a), 0.5 + 0.3 * i)
        cams.append(Camera.look_at(eye, (0.1, -0.2, 0.3), fov_deg=50.0, width=40, height=30))
    return cams


def assert_same_pose(a: Camera, b: Camera, atol: float = 1e-5) -> None:
    torch.testing.assert_close(a.R, b.R, rtol=0, atol=atol)
    torch.testing.assert_close(a.t, b.t, rtol=0, atol=atol)
    for name in ("fx", "fy", "cx", "cy"):
        assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-6), name
    assert (a.width, a.height) == (b.width, b.height)


def rgba(width: int, height: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(height, width, 4), dtype=np.uint8)


# ---------------------------------------------------------------------------------------------------------------
# NeRF-Synthetic


def write_nerf(root: Path, cams: dict[str, list[Camera]], fov_deg: float = 50.0) -> dict[str, list[np.ndarray]]:
    """transforms_{split}.json with OpenGL camera-to-world matrices, and RGBA PNGs; returns the pixels."""
    pixels: dict[str, list[np.ndarray]] = {}
    for split, cameras in cams.items():
        (root / split).mkdir(parents=True)
        frames, pixels[split] = [], []
        for i, cam in enumerate(cameras):
            c2w = np.eye(4)
            c2w[:3, :3] = cam.R.double().numpy().T @ np.diag([1.0, -1.0, -1.0])
            c2w[:3, 3] = cam.center.double().numpy()
            array = rgba(cam.width, cam.height, seed=i)
            Image.fromarray(array, "RGBA").save(root / split / f"r_{i}.png")
            pixels[split].append(array)
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": c2w.tolist()})
        meta = {"camera_angle_x": math.radians(fov_deg), "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return pixels


def test_nerf_cameras_and_compositing(tmp_path: Path) -> None:
    cams = poses(4)
    pixels = write_nerf(tmp_path, {"train": cams[:3], "test": cams[3:]})
    views = load_nerf_synthetic(tmp_path, "train", background=(0.2, 0.4, 0.6))
    assert [v.name for v in views] == ["./train/r_0", "./train/r_1", "./train/r_2"]
    for view, cam, array in zip(views, cams[:3], pixels["train"], strict=True):
        assert_same_pose(view.camera, cam)
        rgb, alpha = array[..., :3] / 255.0, array[..., 3:] / 255.0
        expected = rgb * alpha + np.array([0.2, 0.4, 0.6]) * (1 - alpha)
        assert view.image.dtype == torch.float32 and view.image.shape == (30, 40, 3)
        np.testing.assert_allclose(view.image.numpy(), expected, rtol=0, atol=1e-6)
    assert dataset_layout(tmp_path) == "nerf_synthetic"
    assert [v.name for v in load_dataset(tmp_path, "all")] == [*(f"./train/r_{i}" for i in range(3)), "./test/r_0"]


def test_nerf_scale_and_max_views(tmp_path: Path) -> None:
    cams = poses(6)
    write_nerf(tmp_path, {"train": cams, "test": cams[:1]})
    views = load_nerf_synthetic(tmp_path, "train", max_views=3, scale=0.5)
    assert [v.name for v in views] == ["./train/r_0", "./train/r_2", "./train/r_4"]
    for view, cam in zip(views, cams[0::2], strict=True):
        assert view.image.shape == (15, 20, 3)
        assert_same_pose(view.camera, cam.resized(20, 15))
        assert 0.0 <= float(view.image.min()) and float(view.image.max()) <= 1.0


def test_a_nerf_dataset_without_a_test_split_is_held_out_as_llff(tmp_path: Path) -> None:
    """instant-ngp and nerfstudio write one transforms.json (intrinsics also per frame); some NeRF-style sets only
    transforms_train.json. Their test split is every 8th frame by name, as for COLMAP, never a training frame."""
    cams = poses(10)
    write_nerf(tmp_path / "single", {"train": cams})
    meta = json.loads((tmp_path / "single" / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][::-1]  # the file's order is not the split's
    meta["frames"][0].update(fl_x=30.0, w=40, h=30)  # this frame's own focal length
    (tmp_path / "single" / "transforms.json").write_text(json.dumps(meta))
    (tmp_path / "single" / "transforms_train.json").unlink()
    write_nerf(tmp_path / "train_only", {"train": cams})
    names = sorted(f"./train/r_{i}" for i in range(10))
    for root in (tmp_path / "single", tmp_path / "train_only"):
        assert dataset_layout(root) == "nerf_synthetic"
        test = [f.name for f in dataset_frames(root, "test")]
        train = [f.name for f in dataset_frames(root, "train")]
        assert test == names[::8] and sorted(train + test) == names
    own = {f.name: f.camera for f in dataset_frames(tmp_path / "single", "all")}["./train/r_9"]
    assert own.fx == pytest.approx(30.0) and own.fy == pytest.approx(30.0)


def test_nerfstudio_frame_brings_the_poses_where_its_splats_are(tmp_path: Path) -> None:
    """nerfstudio trains and exports in its own frame: X' = scale (R X + t). With its dataparser_transforms.json the
    loaded cameras see every X' at the pixel where the dataset's cameras see X."""
    cams = poses(3)
    write_nerf(tmp_path, {"train": cams, "test": cams[:1]})
    turn = quat_to_matrix(torch.nn.functional.normalize(torch.tensor([[0.9, 0.2, -0.3, 0.25]]), dim=1))[0].double()
    shift, scale = torch.tensor([0.4, -1.2, 2.0], dtype=torch.float64), 0.37
    transform = torch.cat([turn, shift[:, None]], dim=1)
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.tolist(), "scale": scale}))
    points = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.2], [-0.3, 0.2, 0.6]], dtype=torch.float64)
    moved = scale * (points @ turn.T + shift)

    def pixels(cam: Camera, x: torch.Tensor) -> torch.Tensor:
        c = x @ cam.R.double().T + cam.t.double()
        return torch.stack([cam.fx * c[:, 0] / c[:, 2] + cam.cx, cam.fy * c[:, 1] / c[:, 2] + cam.cy], dim=1)

    loaded = [f.camera for f in dataset_frames(tmp_path, "train")]
    for cam, new in zip(cams, loaded, strict=True):
        torch.testing.assert_close(pixels(new, moved), pixels(cam, points), rtol=0, atol=1e-3)
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": (2 * transform).tolist()}))
    with pytest.raises(DatasetError) as err:
        dataset_frames(tmp_path, "train")
    assert err.value.code == "bad_transforms"


def test_nerf_camera_models(tmp_path: Path) -> None:
    """Distortion is undone on load (``test_lens``); fisheye and panoramic models are refused by name."""
    write_nerf(tmp_path, {"train": poses(2)})
    path = tmp_path / "transforms_train.json"
    meta = json.loads(path.read_text())
    for changes, code, named in (
        ({"camera_model": "OPENCV_FISHEYE"}, "unsupported_camera_model", "OPENCV_FISHEYE"),
        ({"camera_model": "EQUIRECTANGULAR"}, "unsupported_camera_model", "EQUIRECTANGULAR"),
        ({"is_fisheye": True, "k1": 0.1}, "unsupported_camera_model", "is_fisheye"),
        ({"camera_model": "KANNALA"}, "unknown_camera_model", "KANNALA"),
        ({"p2": "x"}, "bad_transforms", "p2"),
    ):
        path.write_text(json.dumps({**meta, **changes}))
        with pytest.raises(DatasetError, match=named) as err:
            load_nerf_synthetic(tmp_path, "train")
        assert err.value.code == code
    path.write_text(json.dumps({**meta, "k1": 0.0, "p1": 0, "camera_model": "OPENCV"}))
    frames = dataset_frames(tmp_path, "all")
    assert len(frames) == 2 and all(f.lens is None for f in frames)  # no distortion: read as it is


def test_nerf_errors(tmp_path: Path) -> None:
    write_nerf(tmp_path, {"train": poses(2)})
    with pytest.raises(DatasetError, match="transforms_val.json") as err:
        load_nerf_synthetic(tmp_path, "val")
    assert err.value.code == "not_found"
    with pytest.raises(DatasetError) as err:
        load_nerf_synthetic(tmp_path, "validation")  # type: ignore[arg-type]
    assert err.value.code == "bad_split"

    meta_path = tmp_path / "transforms_train.json"
    meta = json.loads(meta_path.read_text())
    cases = []
    broken = json.loads(json.dumps(meta))
    broken["frames"][1]["transform_matrix"][0][0] = 5.0  # not a rotation
    cases.append((json.dumps(broken), "bad_transforms", "frame 1"))
    broken = json.loads(json.dumps(meta))
    broken["frames"][0]["file_path"] = "./train/nowhere"
    cases.append((json.dumps(broken), "image_missing", "nowhere"))
    broken = json.loads(json.dumps(meta))
    del broken["camera_angle_x"]
    cases.append((json.dumps(broken), "bad_transforms", "camera_angle_x"))
    broken = json.loads(json.dumps(meta))
    del broken["frames"][0]["transform_matrix"]
    cases.append((json.dumps(broken), "bad_transforms", "frame 0"))
    cases.append(('{"frames": [', "bad_json", "not valid JSON"))
    for text, code, message in cases:
        meta_path.write_text(text)
        with pytest.raises(DatasetError, match=message) as err:
            load_nerf_synthetic(tmp_path, "train")
        assert err.value.code == code
    meta_path.write_text(json.dumps(meta))
    (tmp_path / "train" / "r_1.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="r_1.png") as err:
        load_nerf_synthetic(tmp_path, "train")
    assert err.value.code == "bad_image"
    assert str(tmp_path) not in str(err.value)  # the worker's folders are not the client's business


def test_images_above_the_pixel_limit_are_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write_nerf(tmp_path, {"train": poses(2)})  # 40x30 pixels
    meta_path = tmp_path / "transforms_train.json"
    meta = json.loads(meta_path.read_text())
    meta["frames"][0]["file_path"] = "./train/r_0.dat"  # an image by its content, whatever its name
    meta_path.write_text(json.dumps(meta))
    (tmp_path / "train" / "r_0.png").rename(tmp_path / "train" / "r_0.dat")
    with pixel_limit(40 * 30):
        assert len(load_nerf_synthetic(tmp_path, "all")) == 2
    with pixel_limit(40 * 30 - 1), pytest.raises(DatasetError, match="r_0.dat is 40x30") as err:
        load_nerf_synthetic(tmp_path, "all")
    assert err.value.code == "image_too_large"

    def decode(self: ImageFile.ImageFile) -> None:
        raise AssertionError("decoded")

    monkeypatch.setattr(ImageFile.ImageFile, "load", decode)
    with pixel_limit(100), pytest.raises(DatasetError) as err:
        read_premultiplied(tmp_path / "train" / "r_0.dat")
    assert err.value.code == "image_too_large"


def test_pillow_bomb_limit_is_image_too_large(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Above twice its MAX_IMAGE_PIXELS Pillow refuses to open an image at all: without a limit of ours, that is
    still the input's fault, not the service's."""
    write_nerf(tmp_path, {"train": poses(2)})
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 40 * 30 // 2 - 1)
    with pytest.raises(DatasetError, match="r_0.png") as err:
        load_nerf_synthetic(tmp_path, "train")
    assert err.value.code == "image_too_large"
    with pytest.raises(DatasetError) as err:
        read_premultiplied(tmp_path / "train" / "r_1.png")
    assert err.value.code == "image_too_large"


def test_a_16_bit_grey_photograph_reads_as_its_greys(tmp_path: Path) -> None:
    """Pillow opens it as I;16 and clips it at 255 on the way to RGB: every pixel would read as white."""
    grey = np.arange(12 * 8, dtype=np.uint16).reshape(8, 12) * 600  # 0 .. 56,400 of 65,535
    Image.fromarray(grey).save(tmp_path / "g.png")
    image, alpha = read_premultiplied(tmp_path / "g.png")
    assert alpha is None and image.shape == (8, 12, 3)
    expected = torch.from_numpy(grey.astype(np.float32) / 65535.0)
    for channel in range(3):
        torch.testing.assert_close(image[..., channel], expected, rtol=0, atol=1e-7)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"fl_x": 30.0, "cx": math.nan}, "cx"),
        ({"fl_x": 30.0, "cy": math.inf}, "cy"),
        ({"fl_x": math.nan}, "fl_x"),
        ({"fl_x": 0.0}, "fl_x"),
        ({"fl_x": 30.0, "fl_y": -30.0}, "fl_y"),
        ({"fl_x": 30.0, "w": 0}, "w"),
        ({"fl_x": 30.0, "h": math.inf}, "h"),
        ({"camera_angle_x": math.nan}, "camera_angle_x"),
        ({"camera_angle_x": -0.5}, "camera_angle_x"),
    ],
)
def test_nerf_intrinsics_must_be_finite_and_positive(tmp_path: Path, changes: dict, field: str) -> None:
    """JSON readers accept NaN and Infinity: refused while the intrinsics are read, naming the field, not later as
    photographs that match no camera."""
    write_nerf(tmp_path, {"train": poses(2)})
    path = tmp_path / "transforms_train.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))
    with pytest.raises(DatasetError) as err:
        load_nerf_synthetic(tmp_path, "train")
    assert err.value.code == "bad_transforms" and f": {field} " in err.value.message


def test_unknown_layout(tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as err:
        load_dataset(tmp_path)
    assert err.value.code == "unknown_layout"
    with pytest.raises(DatasetError) as err:
        load_dataset(tmp_path / "absent")
    assert err.value.code == "not_found"
    (tmp_path / "a.ply").write_bytes(b"ply")
    with pytest.raises(DatasetError, match="a.ply is a file, not a folder") as err:
        load_dataset(tmp_path / "a.ply")
    assert err.value.code == "not_found"


# ---------------------------------------------------------------------------------------------------------------
# COLMAP


def quaternion(cam: Camera) -> list[float]:
    x, y, z, w = Rotation.from_matrix(cam.R.double().numpy()).as_quat()
    return [float(w), float(x), float(y), float(z)]


def write_colmap_text(
    sparse: Path, cameras: dict[int, tuple[str, int, int, list[float]]], images: list[tuple[str, Camera, int]]
) -> None:
    sparse.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list", *(f"{i} {m} {w} {h} {' '.join(map(repr, p))}" for i, (m, w, h, p) in cameras.items())]
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
    ]
    for image_id, (name, cam, camera_id) in enumerate(images, start=1):
        q, t = quaternion(cam), cam.t.double().tolist()
        lines.append(f"{image_id} {' '.join(map(repr, q + t))} {camera_id} {name}")
        lines.append("1.5 2.5 -1" if image_id % 2 else "")
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")


def write_colmap_binary(sparse: Path, root: Path) -> None:
    """The binary form of ``root``'s model, written from the text files with COLMAP's record layout."""
    cameras, images = read_colmap_model(root)
    out = bytearray(struct.pack("<Q", len(cameras)))
    for camera_id, cam in cameras.items():
        out += struct.pack(
            f"<iiQQ{len(cam.params)}d", camera_id, MODEL_IDS[cam.model], cam.width, cam.height, *cam.params
        )
    (sparse / "cameras.bin").write_bytes(bytes(out))
    out = bytearray(struct.pack("<Q", len(images)))
    for image_id, im in images.items():
        out += struct.pack("<i4d3di", image_id, *im.qvec, *im.tvec, im.camera_id)
        out += im.name.encode() + b"\0"
        out += struct.pack("<Q", 2) + struct.pack("<ddqddq", 1.0, 2.0, -1, 3.0, 4.0, 7)
    (sparse / "images.bin").write_bytes(bytes(out))


def make_colmap(root: Path, count: int = 10, folder: str = "images", size: tuple[int, int] = (40, 30)) -> list[Camera]:
    cams = poses(count)
    (root / folder).mkdir(parents=True)
    for i in range(count):
        Image.fromarray(rgba(size[0], size[1], i)[..., :3]).save(root / folder / f"img_{i:02d}.jpg")
    intrinsics = {1: ("PINHOLE", 40, 30, [cams[0].fx, cams[0].fy, 20.0, 15.0])}
    # Shuffled registration order: the loader sorts by name.
    order = np.random.default_rng(0).permutation(count)
    write_colmap_text(root / "sparse" / "0", intrinsics, [(f"img_{i:02d}.jpg", cams[i], 1) for i in order])
    return cams


def test_colmap_text_cameras_and_llff_split(tmp_path: Path) -> None:
    cams = make_colmap(tmp_path, count=17)
    frames = colmap_frames(tmp_path)
    assert [f.name for f in frames] == [f"img_{i:02d}.jpg" for i in range(17)]
    for frame, cam in zip(frames, cams, strict=True):
        assert_same_pose(frame.camera, cam)
    assert [f.name for f in colmap_frames(tmp_path, "test")] == ["img_00.jpg", "img_08.jpg", "img_16.jpg"]
    assert len(colmap_frames(tmp_path, "train")) == 14
    views = load_dataset(tmp_path, "test", max_views=2)
    assert dataset_layout(tmp_path) == "colmap"
    assert [v.name for v in views] == ["img_00.jpg", "img_08.jpg"]
    assert views[0].image.shape == (30, 40, 3) and views[0].image.dtype == torch.float32
    jpeg = np.asarray(Image.open(tmp_path / "images" / "img_08.jpg"), dtype=np.float32) / 255
    np.testing.assert_array_equal(views[1].image.numpy(), jpeg)


@pytest.mark.parametrize("layout", ["no points lines", "blank lines between", "a blank line after the comments"])
def test_colmap_text_images_are_told_by_content_not_line_pairs(tmp_path: Path, layout: str) -> None:
    """Converters and hand edits leave out the empty points lines or add blank ones; every image is still read,
    none taken for another's points."""
    make_colmap(tmp_path, count=7)
    images = tmp_path / "sparse" / "0" / "images.txt"
    expected = colmap_frames(tmp_path)
    lines = images.read_text().splitlines()
    comments, data = lines[:2], lines[2:]
    poses = data[0::2]
    edited = {"no points lines": poses, "blank lines between": [x for pose in poses for x in (pose, "", "")],
              "a blank line after the comments": ["", *data]}[layout]  # fmt: skip
    images.write_text("\n".join([*comments, *edited]) + "\n")
    frames = colmap_frames(tmp_path)
    assert [f.name for f in frames] == [f.name for f in expected] and len(frames) == 7
    for a, b in zip(frames, expected, strict=True):
        assert_same_pose(a.camera, b.camera, atol=0)


def test_colmap_binary_equals_text(tmp_path: Path) -> None:
    make_colmap(tmp_path, count=9)
    text = colmap_frames(tmp_path)
    write_colmap_binary(tmp_path / "sparse" / "0", tmp_path)
    for name in ("cameras.txt", "images.txt"):
        (tmp_path / "sparse" / "0" / name).unlink()
    binary = colmap_frames(tmp_path)
    assert [f.name for f in binary] == [f.name for f in text]
    for a, b in zip(binary, text, strict=True):
        assert_same_pose(a.camera, b.camera, atol=0)


def test_colmap_downsampled_images_rescale_intrinsics(tmp_path: Path) -> None:
    cams = make_colmap(tmp_path, count=3, folder="images_2", size=(20, 15))
    frames = colmap_frames(tmp_path)
    for frame, cam in zip(frames, cams, strict=True):
        assert frame.path.parent.name == "images_2"
        assert_same_pose(frame.camera, cam.resized(20, 15))
    views = load_colmap(tmp_path, scale=0.5)
    assert views[0].image.shape == (8, 10, 3)
    assert views[0].camera.fx == pytest.approx(cams[0].fx / 4)


@pytest.mark.parametrize(
    ("model", "params", "code"),
    [
        ("SIMPLE_PINHOLE", [50.0, 20.0, 15.0], None),
        ("OPENCV", [50.0, 50.0, 20.0, 15.0, 0.0, 0.0, 0.0, 0.0], None),
        ("SIMPLE_RADIAL", [50.0, 20.0, 15.0, 0.0], None),
        ("OPENCV_FISHEYE", [50.0, 50.0, 20.0, 15.0, 0.0, 0.0, 0.0, 0.0], "unsupported_camera_model"),
        ("SIMPLE_RADIAL_FISHEYE", [50.0, 20.0, 15.0, 0.0], "unsupported_camera_model"),
        ("RADIAL_FISHEYE", [50.0, 20.0, 15.0, 0.0, 0.0], "unsupported_camera_model"),
        ("THIN_PRISM_FISHEYE", [50.0, 50.0, 20.0, 15.0] + [0.0] * 8, "unsupported_camera_model"),
        ("PINHOLE", [50.0, 50.0, 20.0], "malformed"),
        ("KANNALA", [50.0, 20.0, 15.0], "unknown_camera_model"),
    ],
)
def test_colmap_camera_models(tmp_path: Path, model: str, params: list[float], code: str | None) -> None:
    cams = make_colmap(tmp_path, count=2)
    write_colmap_text(tmp_path / "sparse" / "0", {1: (model, 40, 30, params)}, [("img_00.jpg", cams[0], 1)])
    if code is None:
        (frame,) = colmap_frames(tmp_path)
        assert (frame.camera.fx, frame.camera.fy, frame.camera.cx, frame.camera.cy) == (50.0, 50.0, 20.0, 15.0)
        assert frame.lens is None  # no distortion: the photograph is read as it is
        return
    with pytest.raises(DatasetError) as err:
        colmap_frames(tmp_path)
    assert err.value.code == code
    assert model in err.value.message or code == "malformed"


def test_colmap_errors(tmp_path: Path) -> None:
    cams = make_colmap(tmp_path, count=2)
    sparse = tmp_path / "sparse" / "0"
    write_colmap_text(sparse, {1: ("PINHOLE", 40, 30, [50.0, 50.0, 20.0, 15.0])}, [("img_00.jpg", cams[0], 7)])
    with pytest.raises(DatasetError, match="camera 7") as err:
        colmap_frames(tmp_path)
    assert err.value.code == "camera_missing"
    write_colmap_text(sparse, {1: ("PINHOLE", 40, 30, [50.0, 50.0, 20.0, 15.0])}, [("gone.jpg", cams[0], 1)])
    with pytest.raises(DatasetError, match="gone.jpg") as err:
        colmap_frames(tmp_path)
    assert err.value.code == "image_missing"
    write_colmap_text(sparse, {1: ("PINHOLE", 40, 20, [50.0, 50.0, 20.0, 10.0])}, [("img_00.jpg", cams[0], 1)])
    with pytest.raises(DatasetError, match="aspect") as err:
        colmap_frames(tmp_path)
    assert err.value.code == "bad_image"
    (sparse / "images.txt").write_text("1 0.5 0.5 not-a-number 0 0 0 0 1 img_00.jpg\n\n")
    with pytest.raises(DatasetError, match="line 1") as err:
        colmap_frames(tmp_path)
    assert err.value.code == "malformed"
    with pytest.raises(DatasetError) as err:
        colmap_frames(tmp_path, "val")
    assert err.value.code == "bad_split"


@pytest.mark.parametrize(
    ("model", "size", "params"),
    [
        ("PINHOLE", (0, 0), [50.0, 50.0, 20.0, 15.0]),
        ("PINHOLE", (-40, -30), [50.0, 50.0, 20.0, 15.0]),
        ("PINHOLE", (40, 30), [0.0, 50.0, 20.0, 15.0]),
        ("PINHOLE", (40, 30), [50.0, -50.0, 20.0, 15.0]),
        ("PINHOLE", (40, 30), [math.inf, 50.0, 20.0, 15.0]),
        ("SIMPLE_PINHOLE", (40, 30), [math.nan, 20.0, 15.0]),
        ("PINHOLE", (40, 30), [50.0, 50.0, math.nan, 15.0]),
        ("OPENCV", (40, 30), [50.0, 50.0, 20.0, math.inf, 0.0, 0.0, 0.0, 0.0]),
    ],
)
def test_colmap_cameras_need_a_positive_size_and_finite_intrinsics(
    tmp_path: Path, model: str, size: tuple[int, int], params: list[float]
) -> None:
    cams = make_colmap(tmp_path, count=2)
    write_colmap_text(tmp_path / "sparse" / "0", {3: (model, *size, params)}, [("img_00.jpg", cams[0], 3)])
    with pytest.raises(DatasetError, match="camera 3") as err:
        colmap_frames(tmp_path)
    assert err.value.code == "malformed"


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize(
    ("qvec", "tvec"),
    [
        ((0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 4.0)),
        ((1.0, math.nan, 0.0, 0.0), (0.0, 0.0, 4.0)),
        ((1.0, 0.0, 0.0, 0.0), (0.0, math.nan, 4.0)),
        ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -math.inf)),
    ],
)
def test_colmap_poses_must_be_finite_and_rigid(
    tmp_path: Path, qvec: tuple[float, ...], tvec: tuple[float, ...], binary: bool
) -> None:
    """img_00.jpg, broken here, is in the test split; the model is refused whichever split is read."""
    make_colmap(tmp_path, count=9)
    sparse = tmp_path / "sparse" / "0"
    if binary:
        write_colmap_binary(sparse, tmp_path)
        data = bytearray((sparse / "images.bin").read_bytes())
        # The record before the name: qvec 4d, tvec 3d, camera id i.
        struct.pack_into("<4d3d", data, data.index(b"img_00.jpg\0") - 60, *qvec, *tvec)
        (sparse / "images.bin").write_bytes(bytes(data))
    else:
        text = (sparse / "images.txt").read_text()
        words = next(line for line in text.splitlines() if line.endswith(" img_00.jpg")).split()
        broken = " ".join([words[0], *map(repr, qvec + tvec), *words[8:]])
        (sparse / "images.txt").write_text(text.replace(" ".join(words), broken))
    for split in ("train", "test"):
        with pytest.raises(DatasetError, match="img_00.jpg") as err:
            colmap_frames(tmp_path, split)  # type: ignore[arg-type]
        assert err.value.code == "malformed"


def test_colmap_binary_hostile_counts(tmp_path: Path) -> None:
    make_colmap(tmp_path, count=2)
    sparse = tmp_path / "sparse" / "0"
    write_colmap_binary(sparse, tmp_path)
    good = (sparse / "images.bin").read_bytes()
    cases = [
        struct.pack("<Q", 10**15) + good[8:],  # a count the file cannot hold
        good[:-5],  # cut inside the last record
        good[: good.index(b"img_01.jpg")] + b"img_01.jpg",  # name without its terminator
    ]
    for data in cases:
        (sparse / "images.bin").write_bytes(data)
        with pytest.raises(DatasetError) as err:
            colmap_frames(tmp_path)
        assert err.value.code == "malformed"
    (sparse / "images.bin").write_bytes(good)
    cameras = bytearray((sparse / "cameras.bin").read_bytes())
    cameras[12:16] = struct.pack("<i", 99)  # model id of the first camera
    (sparse / "cameras.bin").write_bytes(bytes(cameras))
    with pytest.raises(DatasetError, match="model id 99") as err:
        colmap_frames(tmp_path)
    assert err.value.code == "unknown_camera_model"


# ---------------------------------------------------------------------------------------------------------------
# Image paths out of the dataset


def _aim_out(layout: str, how: str, root: Path, outside: Path) -> str:
    """A dataset at ``root`` whose first image is read from ``outside`` by ``how``; the path as the model writes it."""
    if layout == "nerf":
        write_nerf(root, {"train": poses(2)})
        written = {"absolute": str(outside), "parent": "../other/r_0", "link": "./train/r_0"}[how]
        image = root / "train" / "r_0.png"
        meta = json.loads((root / "transforms_train.json").read_text())
        meta["frames"][0]["file_path"] = written
        (root / "transforms_train.json").write_text(json.dumps(meta))
    else:
        cams = make_colmap(root, count=2)
        written = {"absolute": str(outside), "parent": "../../other/r_0.png", "link": "img_00.jpg"}[how]
        image = root / "images" / "img_00.jpg"
        intrinsics = {1: ("PINHOLE", 40, 30, [50.0, 50.0, 20.0, 15.0])}
        write_colmap_text(root / "sparse" / "0", intrinsics, [(written, cams[0], 1), ("img_01.jpg", cams[1], 1)])
    if how == "link":
        image.unlink()
        image.symlink_to(outside)
    return written


@pytest.mark.parametrize("how", ["absolute", "parent", "link"])
@pytest.mark.parametrize(("layout", "code"), [("nerf", "bad_transforms"), ("colmap", "malformed")])
def test_image_paths_out_of_the_dataset_are_refused(tmp_path: Path, layout: str, code: str, how: str) -> None:
    """An uploaded dataset must not read the worker's other files: an image path that leads out of the dataset
    folder, also through a link, is refused, named as written, even where a file is there to read."""
    outside = tmp_path / "other" / "r_0.png"
    outside.parent.mkdir()
    Image.fromarray(rgba(40, 30, seed=0)[..., :3]).save(outside)
    written = _aim_out(layout, how, tmp_path / "set", outside)
    with pytest.raises(DatasetError) as err:
        dataset_frames(tmp_path / "set", "all")
    assert err.value.code == code and repr(written) in err.value.message


def test_image_paths_may_wander_inside_the_dataset(tmp_path: Path) -> None:
    write_nerf(tmp_path, {"train": poses(2)})
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta["frames"][0]["file_path"] = "./train/../train/r_0"
    meta["frames"][1]["file_path"] = "train/link"
    (tmp_path / "train" / "link.png").symlink_to(tmp_path / "train" / "r_1.png")
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    assert len(dataset_frames(tmp_path, "all")) == 2


# ---------------------------------------------------------------------------------------------------------------
# Real datasets


def test_lego_cameras_look_at_the_origin() -> None:
    root = shared_file("nerf_synthetic_lego_400px")
    frames = dataset_frames(root, "all")
    assert len(frames) == 300 and len(dataset_frames(root, "test")) == 200
    for frame in frames:
        cam = frame.camera
        p = cam.R.double() @ torch.zeros(3, dtype=torch.float64) + cam.t.double()
        assert p[2] > 3.0  # in front of the camera, about 4 units away
        u, v = cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy
        assert abs(u - 200.0) < 0.01 and abs(v - 200.0) < 0.01
        assert cam.fx == pytest.approx(0.5 * 400 / math.tan(0.5 * 0.6911112070083618))
        # Blender's world z is up, and no lego camera is upside down: image "down" points down in the world
        assert float(cam.R[1, 2]) < 0
    views = load_nerf_synthetic(root, "train", max_views=2, background=(0.0, 0.0, 0.0))
    white = load_nerf_synthetic(root, "train", max_views=2)
    assert views[0].image.shape == (400, 400, 3)
    assert float(views[0].image[0, 0].abs().max()) == 0.0 and float(white[0].image[0, 0].min()) == 1.0


def test_snowmiku_colmap_matches_the_graphdeco_cameras(tmp_path: Path) -> None:
    root = shared_file("snowmiku_plush_capture_mit")
    frames = colmap_frames(root)
    assert len(frames) == 97 and len(colmap_frames(root, "test")) == 13
    reference = {c["img_name"] + ".jpg": c for c in json.loads((root / "cameras_fullres_graphdeco.json").read_text())}
    for frame in frames:
        ref, cam = reference[frame.name], frame.camera
        assert (cam.width, cam.height) == (495, 371)
        np.testing.assert_allclose(cam.center.double().numpy(), ref["position"], atol=1e-5)
        np.testing.assert_allclose(cam.R.double().numpy().T, ref["rotation"], atol=1e-6)
        assert cam.fx == pytest.approx(ref["fx"] * 371 / ref["height"], rel=1e-9)
    # The binary form of the same model reads the same cameras.
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    shutil.copytree(root / "images_8", tmp_path / "images_8")  # a link out of the dataset would be refused
    write_colmap_binary(tmp_path / "sparse" / "0", root)
    for a, b in zip(colmap_frames(tmp_path), frames, strict=True):
        assert a.name == b.name
        assert_same_pose(a.camera, b.camera, atol=0)
    (view,) = load_dataset(root, "test", max_views=1)
    assert view.image.shape == (371, 495, 3) and float(view.image.std()) > 0.05


def test_written_nerf_split_reads_back_as_it_was_written(tmp_path: Path) -> None:
    """``write_nerf_synthetic`` is ``load_nerf_synthetic``'s inverse: the same poses, intrinsics and 8-bit pixels."""
    cams = poses(3)
    gen = torch.Generator().manual_seed(0)
    images = [torch.rand(cam.height, cam.width, 3, generator=gen) for cam in cams]
    write_nerf_synthetic(tmp_path, "train", cams, images)
    views = load_nerf_synthetic(tmp_path, "all", background=(0.3, 0.6, 0.9))  # no alpha: the background is unused
    for view, cam, image in zip(views, cams, images, strict=True):
        assert_same_pose(view.camera, cam)
        torch.testing.assert_close(view.image, (image * 255).round() / 255, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="intrinsics"):
        write_nerf_synthetic(tmp_path / "mixed", "test", [cams[0], cams[0].resized(20, 15)], images[:1] * 2)
    with pytest.raises(ValueError, match="one image per camera"):
        write_nerf_synthetic(tmp_path / "short", "test", cams, images[:2])


@pytest.mark.realdata
def test_the_fox_capture_loads_undistorted() -> None:
    """instant-ngp's fox: 50 phone photographs with one shared OPENCV lens (k1 k2 p1 p2). Each comes out as the
    pinhole COLMAP's undistorter gives it: the lens's focal lengths, the frame cropped to the photograph (1067x1898
    of 1080x1920), read at a job's 256 px through a quarter-size decode."""
    root = shared_file("instant_ngp_fox_capture")
    frames = dataset_frames(root, "all")
    assert len(frames) == 50 and len(dataset_frames(root, "test")) == 7
    for frame in frames:
        cam, lens = frame.camera, frame.lens
        assert lens is not None and (lens.width, lens.height) == (1080, 1920)
        assert lens.radial[:2] == (0.0578421, -0.0805099) and lens.tangential == (-0.000980296, 0.00015575)
        assert (cam.fx, cam.fy) == (1375.52, 1374.49)
        assert (cam.width, cam.height) == (1067, 1898)
        assert cam.cx == pytest.approx(554.558 * 1067 / 1080) and cam.cy == pytest.approx(965.268 * 1898 / 1920)
    photos = load_photographs(root, "test", scale=256 / 1898)
    assert len(photos) == 7
    for photo in photos:
        assert photo.alpha is None and photo.colour.shape == (256, 144, 3)
        assert (photo.camera.width, photo.camera.height) == (144, 256) and float(photo.colour.std()) > 0.1
