"""Levels: nested membership bits decode Gaussian by Gaussian, the fine-tune moves only what a mirror changed, and
the straight-through rounding of a quantisation-aware fine-tune."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from symgs_core.codec import decode_archive, expand_archive
from symgs_core.codec.steps import QuantSteps
from symgs_core.mirror import Plane, reflect
from symgs_core.pipeline import levels
from symgs_core.pipeline.encode import write_archive
from symgs_core.pipeline.levels import apply_mirror, consistent_bits
from symgs_core.pipeline.optimize import fake_quantized, halo, optimize_level
from symgs_core.pipeline.state import LevelState
from symgs_core.scene import GaussianScene
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import self_supervised_views

Y_PLANE = torch.tensor([0.0, 1.0, 0.0])
X_PLANE = torch.tensor([[1.0, 0.0, 0.0]])


def _rows(scene: GaussianScene) -> np.ndarray:
    return torch.cat([t.reshape(len(scene), -1) for t in scene.tensors().values()], dim=1).double().numpy()


def _same_gaussians(a: GaussianScene, b: GaussianScene) -> bool:
    """The two scenes hold the same Gaussians, each matched to the one nearest in position, attributes equal."""
    if len(a) != len(b):
        return False
    _, match = cKDTree(b.means.numpy()).query(a.means.numpy(), k=1)
    return len(set(match.tolist())) == len(b) and np.allclose(_rows(a), _rows(b)[match], atol=2e-5)


def _nested() -> tuple[LevelState, torch.Tensor, torch.Tensor]:
    """Level 0 (plane x = 0) already applied, with its left bits drawn at random; the stored set is exact twins
    across y = 0, so a level-1 mirror pairs Gaussians whose level-0 bits differ about half the time."""
    g = torch.Generator().manual_seed(5)
    n = 150
    half = GaussianScene(
        means=torch.rand(n, 3, generator=g) * torch.tensor([0.8, 0.8, 0.8]) + torch.tensor([0.1, 0.05, -0.4]),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        scales=torch.randn(n, 3, generator=g) * 0.2 - 3.0, opacities=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g), sh_rest=0.1 * torch.randn(n, 3, 3, generator=g),
    )  # fmt: skip
    stored = GaussianScene.cat([half, reflect(half, Y_PLANE, 0.0)])
    bits = (torch.rand(2 * n, 1, generator=g) < 0.5)
    state = LevelState(stored, X_PLANE.clone(), torch.zeros(1), bits)
    return state, torch.arange(n), torch.arange(n, 2 * n)


def test_nested_levels_decode_gaussian_by_gaussian() -> None:
    state, left, right = _nested()
    whole = state.expanded()
    fixed_left, fixed_right = consistent_bits(state, Plane((0.0, 1.0, 0.0), 0.0), left, right)
    assert 0 < fixed_right.numel() < right.numel()  # some pairs disagree on level 0, some agree
    mirrored = apply_mirror(state, Plane((0.0, 1.0, 0.0), 0.0), fixed_left, fixed_right)
    decoded = expand_archive(decode_archive(write_archive(mirrored, {})))
    assert len(mirrored.stored) < len(state.stored)
    assert _same_gaussians(decoded, whole)
    # Without the consistency a dropped Gaussian's level-0 copy is lost, or its stand-in's is made for nothing.
    careless = apply_mirror(state, Plane((0.0, 1.0, 0.0), 0.0), left, right)
    assert not _same_gaussians(expand_archive(decode_archive(write_archive(careless, {}))), whole)


def test_without_earlier_levels_the_membership_is_kept_whole() -> None:
    state, left, right = _nested()
    plain = LevelState.plain(state.stored)
    assert consistent_bits(plain, Plane((0.0, 1.0, 0.0), 0.0), left, right) == (left, right)


def test_the_fine_tune_leaves_what_it_may_not_train_bit_exact() -> None:
    scene = synthetic_scene("global", n=400, seed=1, sh_degree=1).scene
    views = self_supervised_views(scene.map(lambda t: t + 0.01), train=3, fit=1, eval=1, resolution=32,
                                  eval_resolution=32, background=torch.zeros(3))  # fmt: skip
    trainable = torch.arange(len(scene)) % 3 == 0
    tuned, run = optimize_level(LevelState.plain(scene), views.train, views.background, iterations=5, extent=1.0,
                                trainable=trainable)  # fmt: skip
    assert run == 5
    for name, value in scene.tensors().items():
        after = tuned.stored.tensors()[name]
        assert torch.equal(after[~trainable], value[~trainable]), name
    assert not torch.equal(tuned.stored.means[trainable], scene.means[trainable])


def test_the_fine_tune_stops_when_a_stretch_stops_gaining() -> None:
    scene = synthetic_scene("global", n=300, seed=1).scene
    views = self_supervised_views(scene, train=2, fit=1, eval=1, resolution=24, eval_resolution=24,
                                  background=torch.zeros(3))  # fmt: skip
    seen = []
    _, run = optimize_level(LevelState.plain(scene), views.train, views.background, iterations=40, extent=1.0,
                            check_every=10, keep_going=lambda state: seen.append(len(state.stored)) or False)
    assert run == 10 and seen == [len(scene)]


def test_the_halo_holds_the_neighbours_of_a_region_and_nothing_far() -> None:
    before = synthetic_scene("global", n=600, seed=4).scene
    region = torch.nonzero(before.means[:, 0] > 0.2).flatten()
    mask = halo(before, region, before, radius=0.05)
    assert mask[region].all()
    far = before.means[:, 0] < 0.2 - 0.15  # more than two voxels of 0.05 away along x
    assert not mask[far].any()
    assert not halo(before, torch.zeros(0, dtype=torch.long), before, radius=0.05).any()


def test_straight_through_rounding() -> None:
    params = {k: v.clone().requires_grad_(True) for k, v in synthetic_scene("global", n=50, seed=2, sh_degree=1)
              .scene.tensors().items()}  # fmt: skip
    steps = QuantSteps().scaled(4.0)
    shown = fake_quantized(params, steps, extent=2.0)
    step = steps.position * 2.0
    assert torch.allclose(shown["means"] / step, torch.round(params["means"] / step), atol=1e-4)
    assert torch.allclose(shown["scales"], torch.round(params["scales"] / steps.scale) * steps.scale)
    (shown["means"].sum() + shown["sh_dc"].sum()).backward()
    assert torch.equal(params["means"].grad, torch.ones_like(params["means"]))  # the rounding passes the gradient
    assert torch.equal(params["sh_dc"].grad, torch.ones_like(params["sh_dc"]))


def test_a_membership_that_cannot_pay_is_rendered_only_until_it_is_known(monkeypatch) -> None:  # noqa: ANN001
    """With a rate model, a membership whose archive is predicted no smaller than the best even from the highest
    start the views rendered so far allow is not rendered further: its start is reported as that bound."""
    from symgs_core.pipeline.encode import Rate
    from symgs_core.views import BOUND_BATCH, evaluate

    scene = synthetic_scene("global", n=400, seed=1, sh_degree=1).scene
    views = self_supervised_views(scene, train=2, fit=4 * BOUND_BATCH, eval=2, resolution=32, eval_resolution=32,
                                  background=torch.zeros(3))  # fmt: skip
    state = LevelState.plain(scene)
    # A plane the scene is not symmetric about: the reflected half renders with errors, view by view.
    centre = float(scene.means[:, 2].median())
    left = torch.nonzero(scene.means[:, 2] < centre).squeeze(1)
    right = torch.nonzero(scene.means[:, 2] >= centre).squeeze(1)
    member = levels.Membership(Plane((0.0, 0.0, 1.0), centre), left, right, 1.0, 1.0, None)
    candidate = apply_mirror(state, member.plane, left, right).expanded()
    true = evaluate(candidate, views.fit, views.background, with_ssim=False).worst
    rendered: list[int] = []
    real = levels.worst_psnr
    monkeypatch.setattr(levels, "worst_psnr", lambda *a, **k: (rendered.append(1), real(*a, **k))[1])
    steep = Rate(lambda before, after: 1.0 if after >= true + 50 else 10.0)  # pays only far above where it starts
    (attempt,) = levels.plan_attempts(state, math.inf, [member], views, floor=0.0, rate=steep, best_bytes=1000)
    assert attempt.bounded and true < attempt.psnr_before and attempt.predicted >= 1000
    assert not attempt.pays(0.0, 1000)
    # The bound came from the first batch alone: the bound over every view but the first batch's is lower.
    first = real(candidate, views.fit, views.background, below=-math.inf, settled=lambda bound: True)
    assert attempt.psnr_before == first
    flat = Rate(lambda before, after: 0.5)  # pays from any start: every view is rendered
    (paying,) = levels.plan_attempts(state, math.inf, [member], views, floor=0.0, rate=flat, best_bytes=1000)
    assert not paying.bounded and paying.psnr_before == pytest.approx(true)


def _half_mirror(scene: GaussianScene) -> tuple[LevelState, levels.Membership, levels.Membership]:
    """The plain state of ``scene`` and two memberships of a plane it is not symmetric about: one that drops its whole
    right half, one that drops a third of it."""
    centre = float(scene.means[:, 2].median())
    left = torch.nonzero(scene.means[:, 2] < centre).squeeze(1)
    right = torch.nonzero(scene.means[:, 2] >= centre).squeeze(1)
    plane = Plane((0.0, 0.0, 1.0), centre)
    whole = levels.Membership(plane, left, right, 1.0, 1.0, None)
    third = levels.Membership(plane, left, right[: right.numel() // 3], 1.0, 0.6, 0.3)
    return LevelState.plain(scene), whole, third


def test_against_photographs_every_membership_is_probed_the_largest_first() -> None:
    """No fine-tune gain is assumed against photographs: a membership that starts far under the floor, which a rate
    model would skip against the upload's renders, is tried, from its exact start, the one dropping most first."""
    from symgs_core.pipeline.encode import Rate
    from symgs_core.views import evaluate

    scene = synthetic_scene("global", n=400, seed=1, sh_degree=1).scene
    views = self_supervised_views(scene, train=2, fit=2, eval=1, resolution=32, eval_resolution=32,
                                  background=torch.zeros(3))  # fmt: skip
    state, whole, third = _half_mirror(scene)
    steep = Rate(lambda before, after: 10.0)  # no start pays by the model
    floor = 80.0
    uploads = levels.plan_attempts(state, 90.0, [third, whole], views, floor=floor, rate=steep, best_bytes=1000)
    assert not any(a.pays(floor, 1000) for a in uploads)
    probed = levels.plan_attempts(state, 90.0, [third, whole], views, floor=floor, rate=steep, best_bytes=1000,
                                  photographs=True)  # fmt: skip
    assert [a.membership for a in probed] == [whole, third]
    for attempt in probed:
        assert attempt.probed and attempt.pays(floor, 1000) and not attempt.bounded and attempt.predicted is None
        start = apply_mirror(state, attempt.membership.plane, attempt.membership.left, attempt.membership.right)
        true = evaluate(start.expanded(), views.fit, views.background, with_ssim=False).worst
        assert attempt.psnr_before == pytest.approx(true) and attempt.psnr_before < floor - levels.TUNE_GAIN


@pytest.mark.parametrize(
    ("reached", "gained", "left", "pays"),
    [
        (30.0, 1.0, 2, True),  # reaches 32, the model's ratio 0.5 there: 800 * 0.5 < 1000
        (30.0, 0.5, 2, False),  # reaches 31: under the floor
        (30.0, -2.0, 3, False),  # a stretch that lost counts as none
        (31.5, 0.0, 0, True),  # on the floor, nothing left to run
        (33.0, 1.0, 1, False),  # 34: the model's ratio 1.5 there
    ],
)
def test_the_pace_of_a_fine_tune(reached: float, gained: float, left: int, pays: bool) -> None:
    from symgs_core.pipeline.encode import Rate
    from symgs_core.pipeline.levels import Pace

    rate = Rate(lambda before, after: 1.5 if after >= 34.0 else 0.5)
    assert Pace(31.5, rate, 30.0, 800.0, 1000)(reached, gained, left) is pays
    assert Pace(31.5, None, 30.0, 800.0, 1000)(reached, gained, left) is (reached + max(gained, 0) * left >= 31.5)


@pytest.mark.parametrize("reachable", [True, False])
def test_a_probed_fine_tune_stops_once_its_pace_cannot_pay(reachable: bool) -> None:
    """A fine-tune with a ``Pace`` runs on only while the pace says it may pay, and says whether it was stopped."""
    from symgs_core.config import CompressConfig
    from symgs_core.pipeline.job import Reporter
    from symgs_core.views import evaluate

    scene = synthetic_scene("global", n=300, seed=3).scene
    views = self_supervised_views(scene, train=2, fit=1, eval=1, resolution=24, eval_resolution=24,
                                  background=torch.zeros(3))  # fmt: skip
    state, whole, _ = _half_mirror(scene)
    candidate = apply_mirror(state, whole.plane, whole.left, whole.right)
    calls: list[tuple[float, float, int]] = []

    class Judged(levels.Pace):
        def __call__(self, reached: float, gained: float, stretches_left: int) -> bool:
            calls.append((reached, gained, stretches_left))
            return reachable

    pace = Judged(-math.inf, None, 0.0, 0.0, 0)
    config = CompressConfig.for_preset(iterations=40)
    start = evaluate(candidate.expanded(), views.fit, views.background, with_ssim=False).worst
    _, _, run, cut = levels.tune(state, candidate, whole, views, start=start, level=0, config=config, extent=1.0,
                                 spacing=0.05, steps=None, report=Reporter(None, None), pace=pace)  # fmt: skip
    assert calls and calls[0][2] == 3  # four stretches of 10: three left after the first
    if reachable:
        assert not cut and run == 10 * len(calls) + (10 if run == 40 else 0)
    else:
        assert cut and run == 10 and len(calls) == 1
