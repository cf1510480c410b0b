"""Our `.spz` and `.compressed.ply` read by the real third-party reader, PlayCanvas ``splat-transform`` (npm), and
its files read by ours. Skips, with the reason, without Node.js or when the package cannot be installed
(``tests.npm_tools``: a cache outside the repository; ``SPLAT_TRANSFORM`` names another executable).
"""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from symgs_core.export import (
    compressed_ply_order,
    read_compressed_ply,
    read_spz,
    save_scene,
    write_compressed_ply,
    write_spz,
)
from symgs_core.ply import load_scene
from tests.npm_tools import SPLAT_TRANSFORM_SPZ, convert
from tests.npm_tools import splat_transform as installed_splat_transform
from tests.unit.test_export import EDGE_SCENES, assert_within_spz_precision, edge_scene, same_rotation, scene_for_export


@pytest.fixture(scope="module")
def splat_transform() -> str:
    return installed_splat_transform(SPLAT_TRANSFORM_SPZ)


def assert_same_scene(theirs, ours, atol: float = 1e-5) -> None:  # noqa: ANN001
    for name, value in ours.tensors().items():
        other = theirs.tensors()[name]
        if name == "quats":  # either sign of a quaternion is the same rotation
            other = other * torch.where((other * value).sum(1, keepdim=True) < 0, -1.0, 1.0)
        assert torch.allclose(other, value, atol=atol, rtol=1e-5), name


@pytest.mark.parametrize("version, spread", [(3, 3.0), (4, 3.0), (3, 0.1)])  # 0.1: 21 fractional bits
def test_splat_transform_decodes_our_spz_as_our_reader_does(
    splat_transform: str, tmp_path: Path, version: int, spread: float
) -> None:
    scene = scene_for_export(n=700, degree=3, seed=version, spread=spread)
    (tmp_path / "ours.spz").write_bytes(write_spz(scene, version=version))
    convert(splat_transform, tmp_path / "ours.spz", tmp_path / "theirs.ply")
    theirs = load_scene(tmp_path / "theirs.ply")
    ours = read_spz((tmp_path / "ours.spz").read_bytes())
    assert_same_scene(theirs, ours)
    assert_within_spz_precision(theirs, scene, version)


def test_splat_transform_decodes_our_compressed_ply_as_our_reader_does(splat_transform: str, tmp_path: Path) -> None:
    scene = scene_for_export(n=900, degree=2, seed=7)
    (tmp_path / "ours.compressed.ply").write_bytes(write_compressed_ply(scene))
    convert(splat_transform, tmp_path / "ours.compressed.ply", tmp_path / "theirs.ply")
    theirs = load_scene(tmp_path / "theirs.ply")
    ours = read_compressed_ply((tmp_path / "ours.compressed.ply").read_bytes())
    assert_same_scene(theirs, ours)
    ref = scene.select(compressed_ply_order(scene))
    assert (theirs.means - ref.means).abs().max() < 6.0 / 1023  # 10-11 bits in each chunk's box of side <= 6


@pytest.mark.parametrize("kind", EDGE_SCENES)
def test_splat_transform_decodes_edge_scenes_as_our_readers_do(splat_transform: str, tmp_path: Path, kind: str) -> None:
    """One Gaussian, identical ones, a flat scene far from the origin with odd quaternions and saturated opacities:
    their reader and ours agree on every value (opacities: the same byte, each reader's own clamp at 0 and 255), and
    the `.spz` holds the scene within its step, a zero quaternion as the identity."""
    scene = edge_scene(kind)
    for name, write, read in (
        ("ours.spz", write_spz, read_spz), ("ours.compressed.ply", write_compressed_ply, read_compressed_ply)
    ):  # fmt: skip
        (tmp_path / name).write_bytes(write(scene))
        convert(splat_transform, tmp_path / name, tmp_path / "theirs.ply")
        theirs, ours = load_scene(tmp_path / "theirs.ply"), read((tmp_path / name).read_bytes())
        for attribute in ("means", "scales", "sh_dc", "sh_rest"):
            assert torch.allclose(theirs.tensors()[attribute], ours.tensors()[attribute], atol=1e-5), attribute
        assert same_rotation(theirs.quats, ours.quats).min() > 1 - 1e-6
        assert (torch.sigmoid(theirs.opacities) - torch.sigmoid(ours.opacities)).abs().max() <= 1 / 510
    ours = read_spz((tmp_path / "ours.spz").read_bytes())
    step = 2.0 ** -gzip.decompress((tmp_path / "ours.spz").read_bytes())[13]
    assert (ours.means - scene.means).abs().max() <= step / 2 + float(scene.means.abs().max()) * 2**-23  # and float32's
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0])
    unit = torch.where(scene.quats.norm(dim=1, keepdim=True) > 0, scene.quats, identity)
    assert same_rotation(ours.quats, unit).min() >= math.cos(0.003)


def test_our_readers_decode_splat_transform_files(splat_transform: str, tmp_path: Path) -> None:
    from scipy.spatial import cKDTree

    scene = scene_for_export(n=600, degree=3, seed=9)
    save_scene(scene, tmp_path / "source.ply")
    convert(splat_transform, tmp_path / "source.ply", tmp_path / "theirs.spz")
    assert_within_spz_precision(read_spz((tmp_path / "theirs.spz").read_bytes()), scene, version=4)
    convert(splat_transform, tmp_path / "source.ply", tmp_path / "theirs.compressed.ply")
    decoded = read_compressed_ply((tmp_path / "theirs.compressed.ply").read_bytes())
    assert len(decoded) == len(scene)
    distance, index = cKDTree(scene.means.numpy()).query(decoded.means.numpy())
    assert distance.max() < 6.0 / 1023 and len(np.unique(index)) > 0.98 * len(scene)
    matched = scene.select(torch.from_numpy(index))
    assert (torch.sigmoid(decoded.opacities) - torch.sigmoid(matched.opacities)).abs().median() < 1 / 255
