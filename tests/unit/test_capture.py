"""Training a scene from a posed capture (``symgs_core.bench.capture``), the start of the real-capture benchmark."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from symgs_core.bench import capture
from symgs_core.bench.capture import DROP_OPACITY, cached_capture, capture_key, grown, train, train_capture
from symgs_core.bench.photos import photographed
from symgs_core.bench.train_start import TrainSettings, initial_scene, orbit_points, start_points
from symgs_core.cameras import Camera
from symgs_core.datasets import DatasetError, dataset_frames
from symgs_core.progress import ProgressEvent
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
    assert np.array_equal(start_points(cameras, 5000, seed=0)[0], xyz)  # cameras all round: an orbit
    assert xyz.shape == (5000, 3) and rgb.shape == (5000, 3) and 0 <= rgb.min() and rgb.max() <= 1
    # NeRF-Synthetic's proportion: a cube of half side 4/3 around the point every optical axis passes through.
    assert np.allclose(xyz.min(0), target.numpy() - 4 / 3, atol=0.01)
    assert np.allclose(xyz.max(0), target.numpy() + 4 / 3, atol=0.01)


def test_a_folder_without_photographs_is_refused(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="neither a NeRF-Synthetic dataset"):
        train_capture(tmp_path)


def test_a_rig_facing_a_wall_starts_in_what_its_cameras_see() -> None:
    """Phone photographs of a head on a wall: the cameras stand on one side, 5 units out, each turned up to 40
    degrees off the wall's normal. The start covers every camera's whole frame, wall included, not only a cube round
    where the optical axes meet (an orbit's start would leave the frame's edges empty)."""
    g = torch.Generator().manual_seed(0)
    cameras = []
    for _ in range(16):
        a, b = (torch.rand(2, generator=g) * 2 - 1) * math.radians(40)
        eye = 5.0 * torch.tensor([math.sin(a) * math.cos(b), math.sin(b), math.cos(a) * math.cos(b)])
        target = 0.3 * torch.randn(3, generator=g) * torch.tensor([1.0, 1.0, 0.0])
        cameras.append(Camera.look_at(eye, target, up=(0.0, 1.0, 0.0), fov_deg=45.0, width=48, height=64))
    xyz, rgb = start_points(cameras, 20_000, seed=0)
    assert xyz.shape == (20_000, 3) and rgb.shape == (20_000, 3)
    points = torch.from_numpy(xyz).double()
    for camera in cameras:
        p = points @ camera.R.double().T + camera.t.double()
        ahead = p[:, 2] > 0
        u = camera.fx * p[ahead, 0] / p[ahead, 2] + camera.cx
        v = camera.fy * p[ahead, 1] / p[ahead, 2] + camera.cy
        inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        cell = (v[inside] * 4 / camera.height).long() * 4 + (u[inside] * 4 / camera.width).long()
        cells = torch.bincount(cell, minlength=16)
        assert cells.min() > 20  # every part of every frame holds start points
    depth = points[:, 2].numpy()
    assert (depth < -0.5).mean() > 0.1  # some behind the wall's plane: the subject need not be flat
    # Each point is seen by the camera it was drawn for; none stands behind every camera.
    seen = torch.zeros(len(points), dtype=torch.bool)
    for camera in cameras:
        p = points @ camera.R.double().T + camera.t.double()
        u, v = camera.fx * p[:, 0] / p[:, 2] + camera.cx, camera.fy * p[:, 1] / p[:, 2] + camera.cy
        seen |= (p[:, 2] > 0) & (u >= 0) & (u <= camera.width) & (v >= 0) & (v <= camera.height)
    assert bool(seen.all())


def test_a_trained_capture_is_cached_by_what_it_was_trained_from(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cache key is the photographs' bytes, the transforms file and the settings: a copy of the capture elsewhere
    reads the cached scene; a changed photograph or pose, or another schedule, trains again."""
    photographed("global", tmp_path / "a", n=100, photos=3, tests=1, resolution=16)
    trained: list[tuple[Path, TrainSettings]] = []
    scene = initial_scene(np.random.default_rng(0).random((8, 3), np.float32), np.full((8, 3), 0.5, np.float32), 1)
    monkeypatch.setattr(capture, "train", lambda folder, settings, **_: trained.append((folder, settings)) or scene)
    settings = TrainSettings(iterations=10, rounds=2, resolution=16)
    first = cached_capture(tmp_path / "a", tmp_path / "cache", settings)
    assert first.is_file() and first.name.startswith("trained-2x5-") and len(trained) == 1
    import shutil

    shutil.copytree(tmp_path / "a", tmp_path / "b")
    assert cached_capture(tmp_path / "b", tmp_path / "cache", settings) == first and len(trained) == 1
    assert capture_key(tmp_path / "a", settings) != capture_key(tmp_path / "a", TrainSettings(iterations=12, rounds=2))
    image = tmp_path / "b" / "train" / "r_0.png"
    image.write_bytes(image.read_bytes()[:-12] + bytes(12))  # a photograph's last bytes
    original = capture_key(tmp_path / "a", settings)
    assert capture_key(tmp_path / "b", settings) != original
    meta = json.loads((tmp_path / "a" / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"][0][3] += 0.01  # a pose
    (tmp_path / "a" / "transforms_train.json").write_text(json.dumps(meta))
    assert capture_key(tmp_path / "a", settings) != original
    assert cached_capture(tmp_path / "a", tmp_path / "cache", settings) != first and len(trained) == 2


def test_training_reports_its_progress_over_every_round(tmp_path: Path) -> None:
    photographed("global", tmp_path, n=100, photos=3, tests=1, resolution=24)
    events: list[ProgressEvent] = []
    scene = train(tmp_path, TrainSettings(iterations=40, rounds=2, resolution=24, random_points=300),
                  progress=events.append)  # fmt: skip
    assert len(scene) > 0 and events[-1].fraction == 1.0 and events[-1].stage == "train"
    fractions = [e.fraction for e in events]
    assert fractions == sorted(fractions) and len(events) == 4  # every 10 of the 40 steps, over both rounds


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the CUDA schedule needs a CUDA device (and gsplat)")
@pytest.mark.parametrize("strategy", ["default", "mcmc"])
def test_the_cuda_schedule_trains_toward_the_photographs(tmp_path: Path, strategy: str) -> None:
    """gsplat's rasterizer and its densification strategies, 3DGS's schedule compressed to 600 steps: the held-out
    photographs come out far better than from where training started."""
    pytest.importorskip("gsplat")
    truth = photographed("global", tmp_path, n=400, photos=16, tests=4, resolution=64)
    background = torch.zeros(3, device="cuda")
    tests = dataset_eval_views(tmp_path, truth.to("cuda"), eval=4, resolution=64, background=background)
    settings = TrainSettings.for_device("cuda", iterations=600, random_points=2000, strategy=strategy)
    cameras = [frame.camera for frame in dataset_frames(tmp_path, "train")]
    start = initial_scene(*start_points(cameras, 2000, seed=0), sh_degree=3).to("cuda")
    before = evaluate(start, tests, background, with_ssim=False).psnr
    events: list[ProgressEvent] = []
    scene = train(tmp_path, settings, progress=events.append)
    after = evaluate(scene, tests, background, with_ssim=False).psnr
    assert scene.sh_degree == 3 and scene.means.is_cuda and events[-1].fraction == 1.0
    assert math.isfinite(after) and after > before + 3.0, (before, after)
