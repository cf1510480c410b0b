"""The client zips a dataset folder so that the API's extraction finds the same dataset."""

from __future__ import annotations

import json
import zipfile
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


def test_zipped_folder_follows_links_to_photographs_and_folders_but_not_loops(tmp_path: Path) -> None:
    shared = tmp_path / "shared"  # photographs kept elsewhere, linked into the dataset
    (shared / "test").mkdir(parents=True)
    for i in range(3):
        Image.new("RGB", (8, 8), (i, 0, 0)).save(shared / f"r_{i}.png")
    Image.new("RGB", (8, 8), (9, 0, 0)).save(shared / "test" / "r_0.png")
    folder = tmp_path / "lego"
    (folder / "train").mkdir(parents=True)
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    for i in range(3):
        (folder / "train" / f"r_{i}.png").symlink_to(shared / f"r_{i}.png")
    (folder / "test").symlink_to(shared / "test")
    (folder / "train" / "again").symlink_to(folder)  # a loop: its files are in the archive already
    archive = zip_folder(folder, tmp_path / "lego.zip")
    with zipfile.ZipFile(archive) as zf:
        assert sorted(zf.namelist()) == [
            "lego/test/r_0.png", "lego/train/r_0.png", "lego/train/r_1.png", "lego/train/r_2.png",
            "lego/transforms_train.json",
        ]  # fmt: skip
        assert zf.read("lego/train/r_1.png") == (shared / "r_1.png").read_bytes()
    limits = ArchiveLimits(max_entries=10, max_bytes=1 << 20, max_images=10, max_image_pixels=64)
    assert extract_dataset(archive, tmp_path / "out", limits).images == 4
