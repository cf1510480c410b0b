"""Phone photographs stored on their side with an EXIF orientation tag: read the way their camera saw them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageOps

from symgs_core.datasets import DatasetError, colmap_frames, dataset_frames
from symgs_core.datasets.images import load_frames
from tests.unit.test_datasets import poses, rgba, write_colmap_text

ORIENTATION = 0x0112
DISTORTED = [50.0, 52.0, 15.5, 19.0, 0.05, -0.02, 0.001, -0.0005]  # OPENCV: fx fy cx cy k1 k2 p1 p2


def _stored(orientation: int | None, seed: int = 0, size: tuple[int, int] = (40, 30)) -> Image.Image:
    """Landscape pixels, as a phone stores a portrait photograph, tagged with ``orientation`` (None: no tag)."""
    image = Image.fromarray(rgba(*size, seed)[..., :3])
    if orientation is not None:
        image.getexif()[ORIENTATION] = orientation
    return image


def _save(image: Image.Image, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, exif=image.getexif())  # PNG: lossless, so both readings can be compared pixel for pixel


def _colmap(root: Path, image: Image.Image, model: str, size: tuple[int, int]) -> None:
    _save(image, root / "images" / "img.png")
    params = DISTORTED if model == "OPENCV" else DISTORTED[:4]
    write_colmap_text(root / "sparse" / "0", {1: (model, *size, params)}, [("img.png", poses(1)[0], 1)])


@pytest.mark.parametrize("model", ["PINHOLE", "OPENCV"])
@pytest.mark.parametrize("orientation", [5, 6, 7, 8])
def test_a_photograph_its_tag_turns_to_its_cameras_shape_reads_as_the_turned_one(
    tmp_path: Path, orientation: int, model: str
) -> None:
    """The oracle: the same photograph turned upright beforehand and stored without a tag, under the same camera."""
    stored = _stored(orientation)
    _colmap(tmp_path / "tagged", stored, model, (30, 40))
    _colmap(tmp_path / "upright", ImageOps.exif_transpose(stored), model, (30, 40))
    (tagged,), (upright,) = colmap_frames(tmp_path / "tagged"), colmap_frames(tmp_path / "upright")
    assert (tagged.orientation, upright.orientation) == (orientation, 1)
    assert (tagged.camera.width, tagged.camera.height) == (upright.camera.width, upright.camera.height)
    assert tagged.camera.fx == upright.camera.fx and tagged.camera.cy == upright.camera.cy
    (a,), (b,) = load_frames([tagged]), load_frames([upright])
    assert a.colour.shape == b.colour.shape and torch.equal(a.colour, b.colour)


def test_a_camera_that_has_the_stored_shape_reads_the_stored_pixels_as_colmap_does(tmp_path: Path) -> None:
    """COLMAP reads the stored pixels whatever the tag: its cameras then have the stored size."""
    stored = _stored(6)
    _colmap(tmp_path, stored, "PINHOLE", (40, 30))
    (frame,) = colmap_frames(tmp_path)
    assert frame.orientation == 1
    (photo,) = load_frames([frame])
    assert torch.equal(photo.colour, torch.from_numpy(np.asarray(stored, dtype=np.float32) / 255.0))


def _nerf(root: Path, image: Image.Image, size: tuple[int, int]) -> None:
    _save(image, root / "images" / "a.png")
    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"fl_x": 50.0, "fl_y": 50.0, "w": size[0], "h": size[1], "frames": [frame]}
    (root / "transforms.json").write_text(json.dumps(meta))


def test_an_instant_ngp_camera_of_another_shape_than_its_photograph_is_refused_or_turned(tmp_path: Path) -> None:
    """A stated size of another aspect ratio was read before as a camera stretched to the photograph; now it is
    the EXIF turn that gives the photograph that shape, or a clear error."""
    _nerf(tmp_path / "untagged", _stored(None), (30, 40))
    with pytest.raises(DatasetError, match="aspect ratios differ") as err:
        dataset_frames(tmp_path / "untagged", "all")
    assert err.value.code == "bad_image" and "40x30" in err.value.message and "30x40" in err.value.message
    _nerf(tmp_path / "tagged", _stored(8), (30, 40))
    (frame,) = dataset_frames(tmp_path / "tagged", "all")
    assert frame.orientation == 8
    assert (frame.camera.width, frame.camera.height, frame.camera.fx, frame.camera.fy) == (30, 40, 50.0, 50.0)
    (photo,) = load_frames([frame])
    turned = np.asarray(ImageOps.exif_transpose(_stored(8)), dtype=np.float32) / 255.0
    assert torch.equal(photo.colour, torch.from_numpy(turned))


def test_a_half_turn_keeps_the_shape_and_is_not_applied(tmp_path: Path) -> None:
    """A half turn or a mirror leaves the size as it was: nothing tells which way the poses saw the photograph,
    and COLMAP's way (as stored) is kept."""
    _colmap(tmp_path, _stored(3), "PINHOLE", (40, 30))
    (frame,) = colmap_frames(tmp_path)
    assert frame.orientation == 1
