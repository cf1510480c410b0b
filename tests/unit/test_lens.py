"""Distorted photographs are undistorted on load (``symgs_core.datasets.lens``), checked against an exact synthetic
distortion: a known pattern drawn through the lens model by the test's own formulas, loaded, and compared with the
pattern the returned pinhole camera sees."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from symgs_core.cameras import Camera
from symgs_core.datasets import DatasetError, Lens, PosedFrame, dataset_frames, load_photographs, read_frame
from tests.unit.test_datasets import poses, write_colmap_binary, write_colmap_text, write_nerf


@dataclass(frozen=True)
class Intrinsics:
    fx: float = 80.0
    fy: float = 78.0
    cx: float = 49.3
    cy: float = 35.1
    width: int = 96
    height: int = 72

    def scaled(self, s: int) -> Intrinsics:
        return Intrinsics(self.fx * s, self.fy * s, self.cx * s, self.cy * s, self.width * s, self.height * s)


LENS = Intrinsics()
# COLMAP model -> its parameters after the intrinsics, and the coefficients they are (d1..d3: FULL_OPENCV's k4..k6,
# the rational model's denominator).
MODELS = {
    "OPENCV": ([-0.18, 0.04, 0.003, -0.002], {"k1": -0.18, "k2": 0.04, "p1": 0.003, "p2": -0.002}),
    "FULL_OPENCV": ([-0.1, 0.02, 0.001, 0.002, 0.01, 0.05, -0.01, 0.003],
                    {"k1": -0.1, "k2": 0.02, "p1": 0.001, "p2": 0.002, "k3": 0.01, "d1": 0.05, "d2": -0.01,
                     "d3": 0.003}),
    "RADIAL": ([0.12, -0.03], {"k1": 0.12, "k2": -0.03}),  # pincushion: the frame grows
    "SIMPLE_RADIAL": ([-0.2], {"k1": -0.2}),
}  # fmt: skip


def distort(x: np.ndarray, y: np.ndarray, c: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's model as its documentation writes it, with nerfstudio's k4 (the r^8 term)."""
    g = lambda k: c.get(k, 0.0)  # noqa: E731
    r2 = x**2 + y**2
    radial = (1 + g("k1") * r2 + g("k2") * r2**2 + g("k3") * r2**3 + g("k4") * r2**4) / (
        1 + g("d1") * r2 + g("d2") * r2**2 + g("d3") * r2**3
    )
    return (x * radial + 2 * g("p1") * x * y + g("p2") * (r2 + 2 * x**2),
            y * radial + g("p1") * (r2 + 2 * y**2) + 2 * g("p2") * x * y)  # fmt: skip


def undistort(xd: np.ndarray, yd: np.ndarray, c: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """The inverse by fixed-point iteration (the scheme of OpenCV's undistortPoints), to machine precision."""
    x, y = xd.copy(), yd.copy()
    for _ in range(500):
        ex, ey = distort(x, y, c)
        if max(np.abs(ex - xd).max(), np.abs(ey - yd).max()) < 1e-13:
            return x, y
        x, y = x + (xd - ex), y + (yd - ey)
    raise AssertionError("the reference inverse did not converge")


def pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour pattern [..., 3] over normalised (undistorted) image coordinates."""
    return np.stack([0.5 + 0.4 * np.sin(5 * x + 1) * np.cos(4 * y), 0.5 + 0.4 * np.cos(6 * y - 0.5),
                     0.5 + 0.3 * np.sin(3 * x + 5 * y)], axis=-1)  # fmt: skip


def _centres(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    return np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)


def photograph(c: dict[str, float], k: Intrinsics = LENS) -> np.ndarray:
    """The pattern as the lens draws it (8 bits): each pixel centre's distorted coordinates undistorted exactly."""
    u, v = _centres(k.width, k.height)
    x, y = undistort((u - k.cx) / k.fx, (v - k.cy) / k.fy, c)
    return (pattern(x, y) * 255).round().astype(np.uint8)


def seen(camera: Camera) -> np.ndarray:
    """The pattern as ``camera``, a pinhole, sees it at its pixel centres."""
    u, v = _centres(camera.width, camera.height)
    return pattern((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)


def assert_pinhole_of(camera: Camera, c: dict[str, float], k: Intrinsics = LENS) -> None:
    """``camera`` keeps the lens's focal lengths; every pixel centre of its frame samples the photograph between
    its border pixel centres, and the frame is the largest that does along each axis (its outermost pixels come
    within a pixel of the photograph's)."""
    assert (camera.fx, camera.fy) == pytest.approx((k.fx, k.fy), rel=1e-9)
    u, v = _centres(camera.width, camera.height)
    xd, yd = distort((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, c)
    us, vs = xd * k.fx + k.cx, yd * k.fy + k.cy
    assert us.min() >= 0.5 - 1e-6 and us.max() <= k.width - 0.5 + 1e-6
    assert vs.min() >= 0.5 - 1e-6 and vs.max() <= k.height - 0.5 + 1e-6
    assert min(us.min() - 0.5, k.width - 0.5 - us.max()) < 1.0
    assert min(vs.min() - 0.5, k.height - 0.5 - vs.max()) < 1.0


def same(a: Camera, b: Camera) -> bool:
    intrinsics = lambda c: (c.fx, c.fy, c.cx, c.cy, c.width, c.height)  # noqa: E731
    return intrinsics(a) == intrinsics(b) and bool(torch.equal(a.R, b.R) and torch.equal(a.t, b.t))


def assert_shows_pattern(colour: torch.Tensor, camera: Camera, *, worst: float = 0.02, mean: float = 0.004) -> None:
    assert colour.shape == (camera.height, camera.width, 3)
    error = np.abs(colour.numpy() - seen(camera))
    assert error.max() < worst and error.mean() < mean, (error.max(), error.mean())


def test_the_reference_model_is_opencvs() -> None:
    """The test's own distortion formulas agree with OpenCV's projectPoints for every model it writes."""
    import cv2

    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-0.6, 0.6, (50, 2)), np.ones((50, 1))], axis=1)
    for _, c in MODELS.values():
        coeffs = np.array([c.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3", "d1", "d2", "d3")])
        projected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), np.eye(3), coeffs)
        np.testing.assert_allclose(np.stack(distort(points[:, 0], points[:, 1], c), 1), projected[:, 0], atol=1e-12)


@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
@pytest.mark.parametrize("model", list(MODELS))
def test_colmap_distorted_photographs_come_out_as_their_pinhole_sees(tmp_path: Path, model: str, binary: bool) -> None:
    params, c = MODELS[model]
    single = model.startswith("SIMPLE") or model == "RADIAL"  # one focal length
    k = Intrinsics(fy=LENS.fx) if single else LENS
    intrinsics = [k.fx, k.cx, k.cy] if single else [k.fx, k.fy, k.cx, k.cy]
    (tmp_path / "images").mkdir()
    Image.fromarray(photograph(c, k)).save(tmp_path / "images" / "a.png")
    pose = poses(1)[0]
    write_colmap_text(tmp_path / "sparse" / "0", {1: (model, k.width, k.height, intrinsics + params)},
                      [("a.png", pose, 1)])  # fmt: skip
    if binary:
        write_colmap_binary(tmp_path / "sparse" / "0", tmp_path)
        for name in ("cameras.txt", "images.txt"):
            (tmp_path / "sparse" / "0" / name).unlink()
    (frame,) = dataset_frames(tmp_path)
    assert frame.lens is not None
    torch.testing.assert_close(frame.camera.R, pose.R, rtol=0, atol=1e-5)  # the pose is the lens's own
    assert_pinhole_of(frame.camera, c, k)
    (photo,) = load_photographs(tmp_path)
    assert photo.alpha is None and same(photo.camera, frame.camera)
    assert_shows_pattern(photo.colour, frame.camera)


def test_transforms_distortion_with_per_frame_coefficients_and_nerfstudios_k4(tmp_path: Path) -> None:
    """instant-ngp's and nerfstudio's ``k1 k2 k3 k4 p1 p2``, file-wide and overridden per frame; k4 is the r^8
    term, as nerfstudio's model has it."""
    shared = {"k1": -0.12, "k2": 0.02, "k3": 0.004, "k4": -0.002, "p1": 0.002, "p2": 0.001}
    own = {**shared, "k1": 0.08, "p2": -0.003}
    write_nerf(tmp_path, {"train": poses(2)})
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta.update(fl_x=LENS.fx, fl_y=LENS.fy, cx=LENS.cx, cy=LENS.cy, w=LENS.width, h=LENS.height, **shared)
    meta["frames"][1].update(k1=own["k1"], p2=own["p2"])
    for i, c in enumerate((shared, own)):
        Image.fromarray(photograph(c)).save(tmp_path / "train" / f"r_{i}.png")
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    frames = dataset_frames(tmp_path, "all")
    photos = load_photographs(tmp_path, "all")
    for frame, photo, c in zip(frames, photos, (shared, own), strict=True):
        assert frame.lens is not None
        assert_pinhole_of(frame.camera, c)
        assert_shows_pattern(photo.colour, frame.camera)
    assert frames[0].camera.width != frames[1].camera.width  # each frame's own lens gives its own frame


def test_a_jpeg_is_undistorted_at_the_scale_it_is_decoded_at(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Asked for a quarter of its size, a JPEG is decoded at a quarter (libjpeg's DCT scaling) and undistorted
    there through maps made once for both photographs of the lens; nothing is decoded whole."""
    from symgs_core.datasets import images

    c = MODELS["OPENCV"][1]
    k = LENS.scaled(4)
    write_nerf(tmp_path, {"train": poses(2)})
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta.update(fl_x=k.fx, fl_y=k.fy, cx=k.cx, cy=k.cy, w=k.width, h=k.height, **c)
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    drawn = Image.fromarray(photograph(c, k))
    for i in range(2):
        (tmp_path / "train" / f"r_{i}.png").unlink()
        drawn.save(tmp_path / "train" / f"r_{i}.jpg", quality=98)
    decoded: list[tuple[int, ...]] = []
    maps: list[int] = []
    decode, make = images._decode, images.undistortion_maps
    monkeypatch.setattr(images, "_decode", lambda *a: decoded.append(tuple((out := decode(*a))[0].shape)) or out)
    monkeypatch.setattr(images, "undistortion_maps", lambda *a: maps.append(1) or make(*a))
    frames = dataset_frames(tmp_path, "all")
    photos = load_photographs(tmp_path, "all", scale=0.25)
    assert decoded == [(k.height // 4, k.width // 4, 3)] * 2 and len(maps) == 1
    for frame, photo in zip(frames, photos, strict=True):
        assert_pinhole_of(frame.camera, c, k)
        assert same(photo.camera, frame.camera.resized(round(frame.camera.width / 4), round(frame.camera.height / 4)))
        assert_shows_pattern(photo.colour, photo.camera, worst=0.05, mean=0.008)  # JPEG's own error besides


def test_alpha_goes_through_the_lens_and_pixels_off_the_photograph_are_transparent(tmp_path: Path) -> None:
    """An RGBA photograph's alpha is undistorted with its colour (premultiplied); a frame wider than the photograph
    covers (a lens past COLMAP's limits) is transparent where it samples nothing."""
    c = {"k1": -0.1}
    rgba = np.concatenate([photograph(c), np.full((LENS.height, LENS.width, 1), 128, np.uint8)], axis=-1)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    lens = Lens(LENS.fx, LENS.fy, LENS.cx, LENS.cy, LENS.width, LENS.height, radial=(-0.1, 0.0, 0.0, 0.0))
    wide = Camera(torch.eye(3), torch.zeros(3), LENS.fx, LENS.fy, LENS.cx + 20, LENS.cy, LENS.width + 40, LENS.height)
    colour, alpha = read_frame(PosedFrame(wide, tmp_path / "a.png", "a", lens), wide.width, wide.height)
    assert alpha is not None
    u, v = _centres(wide.width, wide.height)
    xd, yd = distort((u - wide.cx) / wide.fx, (v - wide.cy) / wide.fy, c)
    us, vs = xd * LENS.fx + LENS.cx, yd * LENS.fy + LENS.cy
    off = (us < 0) | (us > LENS.width) | (vs < 0) | (vs > LENS.height)
    assert off[:, 0].all() and not off[:, wide.width // 2].any()
    np.testing.assert_array_equal(alpha[..., 0].numpy()[off], 0.0)
    np.testing.assert_allclose(alpha[..., 0].numpy()[~off], 128 / 255, atol=1e-6)
    assert float(colour[torch.from_numpy(off)].abs().max()) == 0.0  # premultiplied: nothing where nothing is
    inside = ~off
    inside[:, :3] = inside[:, -3:] = False  # the rows next to the cut mix the edge with nothing
    error = np.abs(colour.numpy() / (128 / 255) - seen(wide))[inside]
    assert error.max() < 0.05


def test_a_lens_that_folds_the_image_is_refused(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    Image.fromarray(photograph({})).save(tmp_path / "images" / "a.png")
    write_colmap_text(tmp_path / "sparse" / "0", {1: ("SIMPLE_RADIAL", LENS.width, LENS.height,
                                                      [20.0, LENS.cx, LENS.cy, -1.5])}, [("a.png", poses(1)[0], 1)])
    with pytest.raises(DatasetError) as err:
        dataset_frames(tmp_path)
    assert err.value.code == "distorted_camera"
