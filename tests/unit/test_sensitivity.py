"""The sensitivity model: Hutchinson's estimate against the exact diagonal of J^T J, and its prediction of a render's
error against the measured one."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from symgs_core.cameras import Camera
from symgs_core.metrics import psnr_to_mse
from symgs_core.mirror import expand
from symgs_core.pipeline.sensitivity import Sensitivity, sensitivity
from symgs_core.pipeline.state import LevelState
from symgs_core.render import render
from symgs_core.scene import GaussianScene
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import View, evaluate, self_supervised_views


def _tiny() -> tuple[GaussianScene, list[View]]:
    g = torch.Generator().manual_seed(4)
    n = 6
    scene = GaussianScene(
        means=torch.rand(n, 3, generator=g) * 0.6 - 0.3, quats=torch.randn(n, 4, generator=g),
        scales=torch.full((n, 3), -1.6) + 0.2 * torch.rand(n, 3, generator=g), opacities=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g), sh_rest=0.1 * torch.randn(n, 3, 3, generator=g),
    )  # fmt: skip
    cam = Camera.look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0), fov_deg=40, width=10, height=10)
    with torch.no_grad():
        out = render(scene, cam)
    return scene, [View(cam, out.image, out.alpha >= 0.5)]


def test_hutchinson_estimate_converges_to_the_exact_diagonal() -> None:
    scene, views = _tiny()
    view = views[0]
    n_obj, n_all = int(view.mask.sum()), view.mask.numel()
    pixel_weight = ((view.mask.double() / n_obj + 1.0 / n_all) / 3.0)[..., None].expand(10, 10, 3).reshape(-1)
    estimates = sensitivity(LevelState.plain(scene), views, torch.zeros(3), probes=3000, seed=1).weights
    for name, value in scene.tensors().items():

        def image_of(x: torch.Tensor, name: str = name) -> torch.Tensor:
            return render(scene.with_(**{name: x}), view.camera).image.reshape(-1)

        jac = torch.autograd.functional.jacobian(image_of, value).reshape(300, -1).double()  # [pixels*3, params]
        exact = (pixel_weight[:, None] * jac**2).sum(dim=0).reshape(value.shape)
        if name == "opacities":  # the model keeps opacity per unit of alpha
            alpha = torch.sigmoid(scene.opacities.double())
            exact = exact / (alpha * (1 - alpha)) ** 2
        estimate = estimates[name]
        assert estimate.shape == value.shape
        scale = float(exact.abs().max())
        assert float((estimate - exact).abs().max()) <= 0.15 * scale, name


def test_predicted_error_matches_the_rendered_one_for_small_independent_errors() -> None:
    scene = synthetic_scene("global", n=1200, seed=2, sh_degree=1).scene
    views = self_supervised_views(scene, train=1, fit=4, eval=1, resolution=16, eval_resolution=64,
                                  background=torch.zeros(3))  # fmt: skip
    weights = sensitivity(LevelState.plain(scene), views.fit, views.background)
    g = torch.Generator().manual_seed(9)
    sizes = {"means": 2e-3, "quats": 3e-3, "scales": 1e-2, "opacities": 2e-2, "sh_dc": 1e-2, "sh_rest": 1e-2}
    noisy = {k: v + sizes[k] * torch.randn(v.shape, generator=g) for k, v in scene.tensors().items()}
    noisy["quats"] = torch.nn.functional.normalize(noisy["quats"], dim=1)
    original = scene.with_(quats=torch.nn.functional.normalize(scene.quats, dim=1))
    predicted = sum(weights.error(k, original.tensors()[k].numpy(), v.numpy()) for k, v in noisy.items())
    measured = evaluate(GaussianScene(**noisy), views.fit, views.background, with_ssim=False)
    rendered = psnr_to_mse(measured.psnr) + psnr_to_mse(measured.psnr_object)
    assert 0.6 < predicted / rendered < 1.5, (predicted, rendered)


def test_mirror_copies_add_to_their_source() -> None:
    """A stored Gaussian rendered twice (itself and its reflection) weighs what both copies weigh."""
    scene, views = _tiny()
    one = sensitivity(LevelState.plain(scene), views, torch.zeros(3), probes=400, seed=2).weights["sh_dc"]
    normal, offset = torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([0.0])
    bits = torch.ones(len(scene), 1, dtype=torch.bool)
    mirrored = LevelState(scene, normal, offset, bits)
    both = sensitivity(mirrored, views, torch.zeros(3), probes=400, seed=2).weights["sh_dc"]
    assert both.shape == one.shape and float(both.sum()) > float(one.sum())
    assert len(expand(scene, normal, offset, bits)[0]) == 2 * len(scene)
    assert math.isfinite(float(both.sum()))


def test_removal_prices_each_gaussian_by_its_alpha() -> None:
    scene, views = _tiny()
    weights = sensitivity(LevelState.plain(scene), views, torch.zeros(3), probes=50)
    alpha = torch.sigmoid(scene.opacities.double())
    assert torch.allclose(weights.removal(scene.opacities), weights.weights["opacities"] * alpha**2)
    with pytest.raises(ValueError, match="at least one view"):
        sensitivity(LevelState.plain(scene), [], torch.zeros(3))


def test_what_only_the_coverage_cameras_see_still_weighs() -> None:
    scene, views = _tiny()
    far = scene.with_(means=torch.cat([scene.means[:-1], torch.tensor([[0.0, -8.0, 0.0]])]))  # behind the camera
    behind = Camera.look_at((0.0, -6.0, 0.2), (0.0, -8.0, 0.0), fov_deg=40, width=10, height=10)  # facing it
    alone = sensitivity(LevelState.plain(far), views, torch.zeros(3)).per_gaussian("sh_dc")
    covered = sensitivity(LevelState.plain(far), views, torch.zeros(3), coverage=[behind]).per_gaussian("sh_dc")
    assert float(alone[-1]) == 0.0 and float(covered[-1]) > 0.0
    assert torch.allclose(covered[:-1], alone[:-1])  # the coverage camera sees nothing else


def test_step_classes_coarsen_by_a_step_per_quarter_of_the_weight() -> None:
    n = 100
    weight = torch.full((n,), 1.0, dtype=torch.float64)
    weight[:10] = 4.0 ** torch.arange(-4, 6, dtype=torch.float64)  # 1/256 .. 1024
    weights = {name: weight[:, None].repeat(1, width) for name, width in (("means", 3), ("sh_dc", 3))}
    classes = Sensitivity(weights).step_classes(4)
    assert classes[:10].tolist() == [3, 3, 2, 1, 0, 0, 0, 0, 0, 0] and (classes[10:] == 0).all()
    assert (Sensitivity({"means": torch.zeros(5, 3, dtype=torch.float64)}).step_classes() == 0).all()


def test_an_error_priced_by_group_is_the_error_of_every_value() -> None:
    # Groups decoded to their rows: what a palette's rung costs, priced per entry, against the sum over its rows.
    rng = np.random.default_rng(3)
    n, groups = 500, 40
    original = rng.normal(size=(n, 3, 3)).astype(np.float32)
    index = rng.integers(0, groups, n)
    index[index == 7] = 8  # a group no value uses
    weights = torch.from_numpy(10.0 ** rng.uniform(-6, 0, (n, 3, 3)))
    weights[index == 3] = 0.0  # a group the renders do not see
    sens = Sensitivity({"sh_rest": weights})
    grouped = sens.grouped("sh_rest", original, index)
    for scale in (1e-6, 1e-2, 1.0):
        rows = (rng.normal(size=(groups, 3, 3)) * scale).astype(np.float32)
        assert grouped.error(rows) == pytest.approx(sens.error("sh_rest", original, rows[index]), rel=1e-9)
    # Rows at the groups' own values (one value each) err by rounding alone.
    exact = sens.grouped("sh_rest", original, np.arange(n)).error(original)
    assert 0.0 <= exact <= 1e-15 * sens.error("sh_rest", original, np.zeros_like(original))
    with pytest.raises(ValueError, match="opacities"):
        Sensitivity({"opacities": weights[:, 0, 0]}).grouped("opacities", original[:, 0, 0], index)
