"""The same jobs on CUDA as on the CPU (skipped without a CUDA device and gsplat; ``make gpu-check`` runs them)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from symgs_core.bench.photos import photographed
from symgs_core.config import CompressConfig
from symgs_core.detect import DetectConfig, detect
from symgs_core.pipeline import compress, decompress
from symgs_core.render import render, render_many
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import viewer_cameras

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"),
]
SMALL = {"iterations": 20, "train_views": 4, "fit_views": 2, "eval_views": 2, "resolution": 48, "eval_resolution": 48,
         "max_levels": 2, "pictures": True}  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def _gsplat() -> None:
    pytest.importorskip("gsplat", reason="gsplat (the 'gpu' extra) is not installed")


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_a_mirrored_scene_of_every_sh_degree_compresses_on_cuda_as_on_the_cpu(sh_degree: int) -> None:
    """Twins with a little noise: the mirror is found, fine-tuned and kept on both devices, and the archives agree."""
    scene = synthetic_scene("global", n=2000, seed=1, sh_degree=sh_degree, noise=0.002).scene
    config = CompressConfig.for_preset("balanced", **SMALL)
    on_cpu = compress(scene, config=replace(config, device="cpu")).report
    result = compress(scene, config=replace(config, device="cuda"))
    on_gpu = result.report
    assert on_gpu.device == "cuda" and on_gpu.levels
    assert len(on_gpu.accepted_levels) == len(on_cpu.accepted_levels) >= 1
    assert on_gpu.fitting.worst >= on_gpu.psnr_floor
    assert abs(on_gpu.output_bytes / on_cpu.output_bytes - 1.0) < 0.03
    assert len(decompress(result.archive)) == on_gpu.gaussians.decoded
    assert "mirrors" in result.images


def test_a_job_with_photographs_fine_tunes_on_cuda(tmp_path) -> None:
    upload = photographed("global", tmp_path, n=2000, photos=8, tests=2, resolution=48, sh_degree=3)
    config = CompressConfig.for_preset("balanced", **{**SMALL, "max_levels": 1, "device": "cuda"})
    report = compress(upload, images=tmp_path, config=config).report
    assert report.cameras.evaluation.source == "photographs"
    assert report.accepted_levels and report.accepted_levels[0].iterations > 0


def test_cameras_rendered_together_are_the_cameras_rendered_one_by_one() -> None:
    scene = synthetic_scene("global", n=3000, seed=2, sh_degree=3).scene.to("cuda")
    cameras = viewer_cameras(scene.means.mean(dim=0), 2.0, 5, 48, seed=0)
    cameras[-1] = cameras[-1].resized(40, 32)  # another size: drawn in a call of its own
    background = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    together = render_many(scene, [c.to("cuda") for c in cameras], background)
    for camera, out in zip(cameras, together, strict=True):
        alone = render(scene, camera.to("cuda"), background)
        assert out.image.shape == alone.image.shape
        torch.testing.assert_close(out.image, alone.image, rtol=0, atol=1e-5)


def test_detection_on_cuda_finds_the_cpus_planes_and_answers_on_cuda() -> None:
    scene = synthetic_scene("local", n=6000, seed=0, sh_degree=3, objects=2).scene
    on_cpu = detect(scene, DetectConfig(max_mirrors=2))
    on_gpu = detect(scene.to("cuda"), DetectConfig(max_mirrors=2))
    assert [m.plane for m in on_gpu] == [m.plane for m in on_cpu]
    assert all(m.left.device.type == "cuda" for m in on_gpu)
