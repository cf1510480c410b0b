"""The client zips a dataset folder so that the API's extraction finds the same dataset."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image

from service.api.archives import ArchiveLimits, extract_dataset
from service.client import zip_folder


def test_zipped_folder_extracts_to_the_same_dataset(tmp_path: Path) -> None:
    folder = tmp_path / "lego"
    (folder / "train").mkdir(parents=True)
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    for i in range(3):
        Image.new("RGB", (8, 8), (i, 0, 0)).save(folder / "train" / f"r_{i}.png")
    archive = zip_folder(folder, tmp_path / "lego.zip")
    limits = ArchiveLimits(max_entries=10, max_bytes=1 << 20, max_images=10, max_image_pixels=64)
    dataset = extract_dataset(archive, tmp_path / "out", limits)
    assert (dataset.layout, dataset.root, dataset.images) == ("nerf_synthetic", "lego", 3)
    for path in folder.rglob("*"):
        if path.is_file():
            assert (tmp_path / "out" / "lego" / path.relative_to(folder)).read_bytes() == path.read_bytes()
    with pytest.raises(ValueError, match="not a folder"):
        zip_folder(tmp_path / "missing", tmp_path / "x.zip")
