"""Training a scene from a posed capture (``symgs_core.bench.capture``), the start of the real-capture benchmark."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from symgs_core.bench import capture
from symgs_core.bench.capture import DROP_OPACITY, grown, initial_scene, orbit_points, train_capture
from symgs_core.bench.photos import photographed
from symgs_core.cameras import Camera
from symgs_core.datasets import DatasetError
from symgs_core.sh import C0
from symgs_core.views import dataset_eval_views, evaluate


def test_growth_drops_the_transparent_and_splits_without_changing_coverage() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=np.float32)
    scene = initial_scene(xyz, np.full((3, 3), 0.5, dtype=np.float32), sh_degree=1)
    alpha = torch.tensor([DROP_OPACITY / 2, 0.9, 0.5])
    scene = scene.with_(opacities=torch.log(alpha / (1 - alpha)), scales=torch.log(torch.tensor([[0.1, 0.3, 0.2]] * 3)))
    out = grown(scene, share=4.0, generator=torch.Generator().manual_seed(0))  # draws every parent that may be drawn
    assert len(out) == 4  # the transparent one is gone; the other two are each split in two
    for parent in (1, 2):
        pair = torch.nonzero((out.means - torch.from_numpy(xyz[parent])).norm(dim=1) < 0.2).flatten()
        assert len(pair) == 2
        a = torch.sigmoid(out.opacities[pair])
        assert torch.allclose(1 - (1 - a[0]) * (1 - a[1]), alpha[parent], atol=1e-5)
        assert torch.allclose(out.means[pair].mean(0), torch.from_numpy(xyz[parent]), atol=1e-6)
        # Apart along the longest axis (y, 0.3 wide): half a standard deviation either side.
        assert torch.allclose((out.means[pair[0]] - out.means[pair[1]]).abs(), torch.tensor([0.0, 0.3, 0.0]), atol=1e-6)
        assert torch.allclose(out.scales[pair].exp(), 0.6 * torch.tensor([0.1, 0.3, 0.2]).expand(2, 3), atol=1e-6)


def test_a_capture_trains_toward_its_photographs_and_never_sees_the_test_split(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    truth = photographed("global", tmp_path, n=400, photos=12, tests=4, resolution=48)
    g = torch.Generator().manual_seed(1)
    start = truth.select(torch.randperm(len(truth), generator=g)[:150])
    points = ((start.means + 0.01 * torch.randn(start.means.shape, generator=g)).numpy(),
              (C0 * start.sh_dc + 0.5).clamp(0, 1).numpy())  # fmt: skip
    background = torch.zeros(3)
    tests = dataset_eval_views(tmp_path, truth, eval=4, resolution=48, background=background)
    before = evaluate(initial_scene(*points, sh_degree=1), tests, background, with_ssim=False).psnr
    said: list[str] = []
    splits: list[str] = []
    load = capture.load_dataset
    monkeypatch.setattr(capture, "load_dataset", lambda *a, **k: splits.append(k["split"]) or load(*a, **k))
    scene = train_capture(tmp_path, resolution=48, rounds=3, iterations=100, points=points, say=said.append)
    after = evaluate(scene, tests, background, with_ssim=False).psnr
    assert splits == ["train"]
    assert len(said) == 3 and len(scene) > 150
    assert math.isfinite(after) and after > before + 2.5  # measured: 14.7 -> 18.0 dB


def test_the_transparent_are_relocated_not_lost() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=np.float32)
    scene = initial_scene(xyz, np.full((3, 3), 0.5, dtype=np.float32), sh_degree=1)
    alpha = torch.tensor([DROP_OPACITY / 2, 0.9, 0.5])
    out = grown(scene.with_(opacities=torch.log(alpha / (1 - alpha))), share=0.0, generator=torch.Generator())
    assert len(out) == 3  # no growth asked: the transparent one is gone, and one opaque one split in its stead
    assert not (out.means == torch.from_numpy(xyz[0])).all(dim=1).any()


def test_a_capture_without_points_starts_in_the_cube_its_cameras_look_at() -> None:
    target = torch.tensor([1.0, -2.0, 0.5])
    g = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(12, 3, generator=g), dim=1)
    cameras = [Camera.look_at(target + 4.0 * d, target, up=(0.3, 0.2, 1.0)) for d in directions]
    xyz, rgb = orbit_points(cameras, 5000, seed=0)
    assert xyz.shape == (5000, 3) and rgb.shape == (5000, 3) and 0 <= rgb.min() and rgb.max() <= 1
    # NeRF-Synthetic's proportion: a cube of half side 4/3 around the point every optical axis passes through.
    assert np.allclose(xyz.min(0), target.numpy() - 4 / 3, atol=0.01)
    assert np.allclose(xyz.max(0), target.numpy() + 4 / 3, atol=0.01)


def test_a_folder_without_photographs_is_refused(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="neither a NeRF-Synthetic dataset"):
        train_capture(tmp_path)
