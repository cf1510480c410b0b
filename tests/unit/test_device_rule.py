"""The device rule, checked without a GPU: every tensor the core makes takes its device from its inputs.

Under ``torch.device("meta")`` a factory call that names no device makes a meta tensor; the first time such a tensor
meets the scene's CPU tensors, or is read as a number, the job fails. A whole job on the CPU then proves that no
tensor of it was made off its inputs' device, which is what lets the same code run on a GPU."""

from __future__ import annotations

import pytest
import torch

from symgs_core.bench.photos import photographed
from symgs_core.config import PRESET_NAMES, CompressConfig
from symgs_core.detect import DetectConfig, detect
from symgs_core.pipeline import compress, decompress
from symgs_core.synthetic import synthetic_scene

SMALL = {"iterations": 8, "train_views": 3, "fit_views": 2, "eval_views": 2, "resolution": 40, "eval_resolution": 40,
         "max_levels": 2}  # fmt: skip


@pytest.fixture(scope="module")
def scene():
    """SH degree 3 with a planted mirror and a little positional noise, so levels are found and fine-tuned."""
    return synthetic_scene("global", n=1200, seed=3, sh_degree=3, noise=0.002).scene


def test_a_factory_without_a_device_fails_under_meta(scene) -> None:
    """The check itself: a tensor made without the scene's device cannot meet the scene's tensors."""
    with torch.device("meta"), pytest.raises((RuntimeError, NotImplementedError)):
        float((scene.means + torch.zeros(3)).sum())


def test_detection_makes_every_tensor_on_its_inputs_device(scene) -> None:
    with torch.device("meta"):
        mirrors = detect(scene, DetectConfig(max_mirrors=2))
    assert mirrors and all(m.left.device.type == "cpu" for m in mirrors)


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_every_preset_makes_every_tensor_on_its_inputs_device(scene, preset: str) -> None:
    config = CompressConfig.for_preset(preset, **SMALL)
    with torch.device("meta"):
        result = compress(scene, config=config)
        decoded = decompress(result.archive)
    assert len(decoded) == result.report.gaussians.decoded
    if preset in ("small", "balanced", "high"):  # the presets that judge mirrors by fitted archives try one
        assert result.report.levels
    if preset in ("balanced", "high"):  # and where the budget is tight, the fine-tune runs too
        assert any(level.iterations > 0 for level in result.report.levels)


def test_a_job_with_photographs_makes_every_tensor_on_its_inputs_device(tmp_path) -> None:
    upload = photographed("global", tmp_path, n=1500, photos=8, tests=2, resolution=48, sh_degree=3)
    config = CompressConfig.for_preset("balanced", **{**SMALL, "max_levels": 1, "eval_resolution": 48})
    with torch.device("meta"):
        result = compress(upload, images=tmp_path, config=config)
        decompress(result.archive)
    assert result.report.cameras.evaluation.source == "photographs"
    assert any(level.iterations > 0 for level in result.report.levels)
