"""The shared PSNR budget: stage floors as cumulative shares of the excess MSE, and the quantisation step search."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from symgs_core.codec.steps import QuantSteps
from symgs_core.metrics import psnr_to_mse
from symgs_core.pipeline.budget import SHARES, fit_quantization, quantized, split_budget
from symgs_core.pipeline.state import LevelState
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import evaluate, self_supervised_views


def test_stage_floors_are_cumulative_shares_of_the_excess_mse() -> None:
    floors = split_budget(40.0, math.inf)
    assert list(floors) == list(SHARES)
    for stage, share in SHARES.items():
        assert psnr_to_mse(floors[stage]) == pytest.approx(share * psnr_to_mse(40.0), rel=1e-12)
    assert floors["quantization"] == pytest.approx(40.0)
    # Against test images the reference error is not zero: shares apply to the excess over it.
    real = split_budget(30.0, 31.0)
    excess = psnr_to_mse(30.0) - psnr_to_mse(31.0)
    assert psnr_to_mse(real["mirrors"]) == pytest.approx(psnr_to_mse(31.0) + SHARES["mirrors"] * excess)
    assert split_budget(math.inf, math.inf) == {stage: math.inf for stage in SHARES}


@pytest.fixture(scope="module")
def setting():
    scene = synthetic_scene("global", n=700, seed=2, sh_degree=1).scene
    views = self_supervised_views(scene, train=2, fit=3, eval=1, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    return LevelState.plain(scene), views


def test_step_search_spends_the_budget_without_going_under_the_floor(setting) -> None:  # noqa: ANN001
    state, views = setting
    fit = fit_quantization(state, views.fit, views.background, floor=42.0, start=QuantSteps(), psnr_before=math.inf)
    assert fit is not None and fit.psnr >= 42.0
    decoded = LevelState(quantized(state.stored, fit.steps), state.normals, state.offsets, state.bits)
    assert evaluate(decoded.expanded(), views.fit, views.background).worst == pytest.approx(fit.psnr)
    assert fit.psnr < 52.0  # it coarsened the steps towards the floor instead of stopping at the first pass
    assert all(t["psnr"] >= 42.0 for t in fit.tries if t["factor"] == fit.factor)


def test_no_quantisation_fits_an_infinite_floor(setting) -> None:  # noqa: ANN001
    state, views = setting
    assert fit_quantization(state, views.fit, views.background, floor=math.inf, start=QuantSteps(),
                            psnr_before=math.inf) is None  # fmt: skip


def test_a_lossy_preset_reports_every_stage_and_keeps_the_floor() -> None:
    from symgs_core.config import CompressConfig
    from symgs_core.pipeline import compress, decompress

    scene = synthetic_scene("global", n=900, seed=6, sh_degree=1).scene
    config = CompressConfig.for_preset("balanced", iterations=2, train_views=3, fit_views=2, eval_views=2,
                                       resolution=48, eval_resolution=48, max_levels=1, pictures=False)  # fmt: skip
    result = compress(scene, config=config)
    report = result.report
    stages = report.stages
    assert [s.stage for s in stages] == ["mirrors", "pruning", "sh_reduction", "quantization", "entropy_coding"]
    for before, after in zip(stages, stages[1:]):
        assert after.bytes_before == before.bytes_after
    assert stages[-1].bytes_after == len(result.archive) == report.output_bytes
    assert report.fitting.worst >= report.psnr_floor == pytest.approx(config.self_supervised_floor())
    assert stages[-1].psnr_after == pytest.approx(report.fitting.worst)
    lossless = compress(scene, config=replace(config, preset="lossless", psnr_budget=0.0)).report
    assert report.output_bytes * 4 < lossless.output_bytes
    assert len(decompress(result.archive)) == report.gaussians.decoded
