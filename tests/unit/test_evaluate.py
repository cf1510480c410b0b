"""``worst_psnr``: the decisions that only ask whether a scene renders below a PSNR stop rendering once the views
seen so far answer it, and otherwise measure what ``evaluate`` measures."""

from __future__ import annotations

import math

import pytest
import torch

from symgs_core.cameras import View
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import BOUND_BATCH, evaluate, self_supervised_views, worst_psnr


@pytest.fixture(scope="module")
def scene_and_views():
    scene = synthetic_scene("global", n=600, seed=3).scene
    views = self_supervised_views(scene, train=2, fit=3 * BOUND_BATCH, eval=2, resolution=40, eval_resolution=40,
                                  background=torch.zeros(3))  # fmt: skip
    damaged = scene.with_(sh_dc=scene.sh_dc + 0.3)
    return scene, [views.fit[i] for i in range(len(views.fit))], damaged


def test_without_a_bound_it_is_evaluate_s_worst(scene_and_views) -> None:  # noqa: ANN001
    _, fit, damaged = scene_and_views
    measured = evaluate(damaged, fit, torch.zeros(3), with_ssim=False).worst
    assert worst_psnr(damaged, fit, torch.zeros(3), below=-math.inf) == pytest.approx(measured, rel=1e-12)
    assert worst_psnr(damaged, fit, torch.zeros(3), below=measured - 1.0) == pytest.approx(measured, rel=1e-12)


def test_it_stops_once_the_first_views_settle_the_question(scene_and_views) -> None:  # noqa: ANN001
    """The first batch's targets are black: their error alone puts the (damaged) scene far below ``below``. The
    bound it returns is below ``below`` and above the true PSNR (the views it did not render add error)."""
    _, fit, scene = scene_and_views
    black = [View(v.camera, torch.zeros_like(v.image), v.mask) for v in fit[:BOUND_BATCH]]
    views = black + list(fit[BOUND_BATCH:])
    true = evaluate(scene, views, torch.zeros(3), with_ssim=False).worst
    below = true + 3.0
    bound = worst_psnr(scene, views, torch.zeros(3), below=below)
    assert true < bound < below
    # Only the black batch was rendered: the bound is the PSNR of its error spread over every view's pixels.
    first = evaluate(scene, black, torch.zeros(3), with_ssim=False)
    share = lambda masks: float(sum(m.sum() for m in masks)) / float(sum(v.mask.sum() for v in views))  # noqa: E731
    frames = BOUND_BATCH / len(views)
    expected = min(first.psnr - 10 * math.log10(frames),
                   first.psnr_object - 10 * math.log10(share([v.mask for v in black])))  # fmt: skip
    assert bound == pytest.approx(expected, abs=1e-6)


def test_a_settling_question_stops_it_as_soon_as_a_bound_answers(scene_and_views) -> None:  # noqa: ANN001
    """``settled`` is asked about each bound while views remain: the first bound it accepts is returned; one it never
    accepts leaves the exact PSNR, and it is never asked once every view is rendered."""
    _, fit, damaged = scene_and_views
    measured = evaluate(damaged, fit, torch.zeros(3), with_ssim=False).worst
    asked: list[float] = []
    never = lambda bound: asked.append(bound) or False  # noqa: E731
    assert worst_psnr(damaged, fit, torch.zeros(3), below=-math.inf, settled=never) == pytest.approx(measured)
    assert len(asked) == len(fit) // BOUND_BATCH - 1 and all(b > measured for b in asked)
    first = asked[0]
    asked.clear()
    at_once = lambda bound: asked.append(bound) or True  # noqa: E731
    assert worst_psnr(damaged, fit, torch.zeros(3), below=-math.inf, settled=at_once) == first
    assert asked == [first]
