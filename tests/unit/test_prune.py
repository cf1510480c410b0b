"""Pruning and SH band reduction: contributions measured with the renderer, band energies, and reductions that stay
above their floor."""

from __future__ import annotations

import math

import pytest
import torch

from symgs_core.cameras import scene_cameras
from symgs_core.pipeline.prune import band_energy, contributions, prune, reduce_sh, truncate_sh
from symgs_core.pipeline.state import LevelState
from symgs_core.render import render
from symgs_core.scene import GaussianScene
from symgs_core.sh import eval_sh
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import evaluate, self_supervised_views


@pytest.fixture(scope="module")
def scene() -> GaussianScene:
    return synthetic_scene("global", n=600, seed=4, sh_degree=2).scene


def test_contributions_sum_to_the_rendered_alpha(scene: GaussianScene) -> None:
    cams = scene_cameras(scene.means, 3, 48, 48)
    weights = contributions(LevelState.plain(scene), cams)
    alpha = sum(float(render(scene, cam).alpha.sum()) for cam in cams)
    assert float(weights.sum()) == pytest.approx(alpha, rel=1e-3)
    assert (weights >= 0).all()


def test_gaussians_nobody_sees_contribute_nothing_and_are_pruned(scene: GaussianScene) -> None:
    far = scene.select(torch.arange(40)).map(lambda t: t.clone())
    far.means += 1000.0  # far outside every camera's frustum
    both = GaussianScene.cat([scene, far])
    views = self_supervised_views(scene, train=4, fit=2, eval=1, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    weights = contributions(LevelState.plain(both), [v.camera for v in views.train])
    assert (weights[len(scene) :] == 0).all()
    result = prune(LevelState.plain(both), views.train, views.fit, views.background, floor=60.0, extent=1.0,
                   thresholds=(1e-9,))  # fmt: skip
    assert result is not None and result.removed >= 40
    assert len(result.state.stored) == len(both) - result.removed
    assert result.psnr >= 60.0


def test_pruning_gives_up_rather_than_go_below_its_floor(scene: GaussianScene) -> None:
    views = self_supervised_views(scene, train=4, fit=2, eval=1, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    result = prune(LevelState.plain(scene), views.train, views.fit, views.background, floor=200.0, extent=1.0,
                   thresholds=(1e6,))  # fmt: skip
    assert result is None


def test_band_energy_is_the_mean_squared_colour_over_the_sphere() -> None:
    coeffs = torch.randn(5, 8, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    energy = band_energy(coeffs)  # [5, 2]
    n = 40000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    dirs = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], dim=1)
    for band, rows in ((1, slice(0, 3)), (2, slice(3, 8))):
        only = torch.zeros(5, 9, 3, dtype=torch.float64)
        only[:, 1:][:, rows] = coeffs[:, rows]
        colours = eval_sh(only[:, None].expand(5, n, 9, 3).reshape(-1, 9, 3), dirs.repeat(5, 1)).reshape(5, n, 3)
        mean_square = colours.pow(2).sum(-1).mean(1)
        assert torch.allclose(mean_square, energy[:, band - 1], rtol=2e-3)


def test_truncate_keeps_exactly_the_bands_up_to_each_degree() -> None:
    rest = torch.ones(3, 15, 3)
    out = truncate_sh(rest, torch.tensor([0, 1, 3]))
    assert out[0].abs().sum() == 0
    assert (out[1, :3] == 1).all() and out[1, 3:].abs().sum() == 0
    assert torch.equal(out[2], rest[2])


def test_sh_reduction_drops_bands_without_view_dependence(scene: GaussianScene) -> None:
    rest = scene.sh_rest.clone()
    rest[::2] *= 1e-4  # half the Gaussians barely change colour with direction
    tweaked = scene.with_(sh_rest=rest)
    views = self_supervised_views(tweaked, train=4, fit=2, eval=1, resolution=48, eval_resolution=48,
                                  background=torch.zeros(3))  # fmt: skip
    result = reduce_sh(LevelState.plain(tweaked), views.train, views.fit, views.background, floor=45.0,
                       thresholds=(1e-6,))  # fmt: skip
    assert result is not None and result.removed >= 0.4 * len(scene) * 2
    kept = result.state.stored.sh_rest
    dropped = (kept == 0).all(dim=(1, 2))
    assert dropped[::2].float().mean() > 0.9  # the flat ones lose every band
    assert dropped[1::2].float().mean() < dropped[::2].float().mean()
    assert evaluate(result.state.expanded(), views.fit, views.background).worst == pytest.approx(result.psnr)
    assert result.psnr >= 45.0
