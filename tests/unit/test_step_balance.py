"""Steps balanced on the scene's own renders, and the one-attribute-at-a-time spending of what the fit leaves."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from symgs_core.codec.steps import QuantSteps
from symgs_core.pipeline.budget import (
    _ATTRIBUTES,
    archive_bytes,
    balance_steps,
    coarsen_one_by_one,
    fit_quantization,
    fit_steps,
    palette_start,
    quantized,
)
from symgs_core.pipeline.encode import write_archive
from symgs_core.pipeline.state import LevelState
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import evaluate, self_supervised_views

FLOOR = 42.0
# Positions far finer than their share of the error: a start that balancing has to move.
SKEWED = replace(QuantSteps(), position=QuantSteps().position / 64.0)


@pytest.fixture(scope="module")
def setting():
    scene = synthetic_scene("global", n=700, seed=2, sh_degree=1).scene
    views = self_supervised_views(scene, train=2, fit=3, eval=1, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    return LevelState.plain(scene), views


def test_balancing_moves_each_step_against_its_error_per_component(setting) -> None:  # noqa: ANN001
    state, views = setting
    balanced = balance_steps(state, views.fit, views.background, start=SKEWED, psnr_before=math.inf)
    assert set(balanced.errors) == set(_ATTRIBUTES) | {"sh1"}
    assert balanced.order[0] == "sh1"  # nine coded components per Gaussian: the most bytes to save
    # A step moves against its attribute's error per coded component: the more error, the finer, relative to start.
    ratio = {
        "rotation": balanced.steps.rotation / SKEWED.rotation, "scale": balanced.steps.scale / SKEWED.scale,
        "opacity": balanced.steps.opacity / SKEWED.opacity, "dc": balanced.steps.dc / SKEWED.dc,
        "sh1": balanced.steps.sh[0] / SKEWED.sh[0],
    }  # fmt: skip
    per_component = {k: balanced.errors[k] / balanced.components[k] for k in ratio}
    by_error = sorted(ratio, key=per_component.get)
    assert [ratio[k] for k in by_error] == sorted(ratio.values(), reverse=True)
    assert min(ratio.values()) < 1.0 < max(ratio.values())
    # The over-fine positions show no error at the probe (well under a hundredth of a pixel): their step stays.
    assert balanced.errors["position"] < 1e-3 * min(balanced.errors[k] for k in ratio)
    assert balanced.steps.position == SKEWED.position


def test_coarsening_keeps_the_floor_and_never_grows_the_archive(setting) -> None:  # noqa: ANN001
    state, views = setting
    fit = fit_quantization(state, views.fit, views.background, floor=FLOOR, start=QuantSteps(), psnr_before=math.inf)
    order = ["position", "rotation", "scale", "opacity", "dc", "sh1"]
    spent = coarsen_one_by_one(state, views.fit, views.background, fit, floor=FLOOR, order=order, max_tries=6)
    assert FLOOR <= spent.psnr <= fit.psnr
    decoded = quantized(state.stored, spent.steps)
    assert evaluate(decoded, views.fit, views.background).worst == pytest.approx(spent.psnr)
    extent = float((state.stored.means.max(0).values - state.stored.means.min(0).values).max())
    size = lambda steps: len(write_archive(state, {}, steps.archive_codec(extent, "test-coarsen")))  # noqa: E731
    assert size(spent.steps) <= size(fit.steps)
    tried = [t for t in spent.tries if "coarsen" in t]
    assert 0 < len(tried) <= 6
    accepted = [t for t in tried if t["psnr"] >= FLOOR]  # a failed try leaves the steps as they were
    assert spent.psnr == (accepted[-1]["psnr"] if accepted else fit.psnr)


def test_fitting_from_a_skewed_start_beats_one_common_factor(setting) -> None:  # noqa: ANN001
    state, views = setting
    extent = float((state.stored.means.max(0).values - state.stored.means.min(0).values).max())
    size = lambda steps: len(write_archive(state, {}, steps.archive_codec(extent, "test-fit")))  # noqa: E731
    common = fit_quantization(state, views.fit, views.background, floor=FLOOR, start=SKEWED, psnr_before=math.inf)
    fitted = fit_steps(state, views.fit, views.background, floor=FLOOR, start=SKEWED, psnr_before=math.inf)
    assert common.psnr >= FLOOR and fitted.psnr >= FLOOR
    assert size(fitted.steps) < 0.95 * size(common.steps)
    assert fitted.probe_errors and fit_steps(state, views.fit, views.background, floor=math.inf, start=SKEWED,
                                             psnr_before=math.inf) is None  # fmt: skip


def test_palette_starts_exact_on_few_distinct_rows() -> None:
    rows = torch.tensor([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [0.1, 0.2, 0.3], [-0.4, 0.0, 0.5]]).repeat(50, 1)
    assert palette_start(rows.reshape(200, 1, 3)) == 3  # two distinct non-zero rows, plus the zero entry


def test_sh_scenes_keep_the_smaller_of_per_coefficient_and_palette_coding(setting) -> None:  # noqa: ANN001
    state, views = setting
    fitted = fit_steps(state, views.fit, views.background, floor=FLOOR, start=QuantSteps(), psnr_before=math.inf)
    balanced = balance_steps(state, views.fit, views.background, start=QuantSteps(), psnr_before=math.inf)
    scalar = fit_quantization(state, views.fit, views.background, floor=FLOOR, start=balanced.steps,
                              psnr_before=math.inf)  # fmt: skip
    scalar = coarsen_one_by_one(state, views.fit, views.background, scalar, floor=FLOOR, order=balanced.order)
    assert fitted.psnr >= FLOOR
    assert archive_bytes(state.stored, fitted.steps) <= archive_bytes(state.stored, scalar.steps)
    decoded = quantized(state.stored, fitted.steps)
    assert evaluate(decoded, views.fit, views.background).worst == pytest.approx(fitted.psnr)
