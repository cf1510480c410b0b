"""Pruning leaves out the Gaussians the fitting views see least, so those views cannot tell what their absence costs
elsewhere: views that played no part in the order (``check``) judge it too."""

from __future__ import annotations

import math

import torch

from symgs_core.cameras import Camera
from symgs_core.codec.steps import QuantSteps
from symgs_core.metrics import psnr_to_mse
from symgs_core.pipeline.budget import RateDistortion
from symgs_core.pipeline.encode import check_views, prune
from symgs_core.pipeline.sensitivity import sensitivity
from symgs_core.pipeline.state import LevelState
from symgs_core.render import render
from symgs_core.scene import GaussianScene
from symgs_core.views import View

WALL, HIDDEN = 400, 20


def _wall_and_hidden() -> GaussianScene:
    """An opaque wall in the plane z = 0 and, behind it (z < 0), a cluster of bright Gaussians."""
    g = torch.Generator().manual_seed(7)
    side = int(math.sqrt(WALL))
    u = torch.linspace(-1.0, 1.0, side)
    grid = torch.stack(torch.meshgrid(u, u, indexing="ij"), dim=-1).reshape(-1, 2)
    wall = torch.cat([grid, torch.zeros(WALL, 1)], dim=1)
    hidden = torch.cat([0.2 * torch.randn(HIDDEN, 2, generator=g), torch.full((HIDDEN, 1), -0.3)], dim=1)
    n = WALL + HIDDEN
    scales = torch.cat([torch.tensor([[-2.3, -2.3, -4.0]]).expand(WALL, 3), torch.full((HIDDEN, 3), -3.0)])
    dc = torch.cat([torch.full((WALL, 3), -1.0), torch.tensor([[2.0, 1.5, -1.0]]).expand(HIDDEN, 3)])
    return GaussianScene(
        means=torch.cat([wall, hidden]), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(n, 4).clone(),
        scales=scales.clone(), opacities=torch.full((n,), 6.0), sh_dc=dc.clone(), sh_rest=torch.zeros(n, 0, 3),
    )  # fmt: skip


def _views(scene: GaussianScene, side: float) -> list[View]:
    views = []
    for x in (-0.6, 0.0, 0.6):
        cam = Camera.look_at((x, 0.3, 3.0 * side), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov_deg=50, width=48, height=48)
        with torch.no_grad():
            out = render(scene, cam, torch.zeros(3))
        views.append(View(cam, out.image, torch.ones(48, 48, dtype=torch.bool)))
    return views


def test_what_only_other_views_see_is_not_left_out() -> None:
    scene = _wall_and_hidden()
    state = LevelState.plain(scene)
    front, back = _views(scene, 1.0), _views(scene, -1.0)  # the wall hides the cluster from the front
    rd = RateDistortion(state.stored, sensitivity(state, front, torch.zeros(3)), QuantSteps())
    allowed = psnr_to_mse(40.0)
    hidden = torch.arange(WALL, WALL + HIDDEN)

    keep, removed = prune(state, rd, front, torch.zeros(3), allowed=allowed, psnr_before=math.inf)
    assert int((~keep).sum()) >= 6 and not keep[hidden].all()  # invisible from the front: free to leave out
    assert removed < 0.5 * allowed

    keep, removed = prune(state, rd, front, torch.zeros(3), allowed=allowed, psnr_before=math.inf, check=back)
    assert keep[hidden].all()  # seen from behind: their absence costs more than the budget
    assert removed < 0.5 * allowed


def test_check_views_are_spread_over_the_training_set() -> None:
    views = list(range(128))
    assert check_views(views, 16) == list(range(0, 128, 8))  # type: ignore[arg-type]
    assert check_views(views[:5], 16) == list(range(5))  # type: ignore[arg-type]
    assert check_views([], 16) == []


def test_a_state_judged_against_its_own_renders_is_not_rendered_on_the_check_views(monkeypatch) -> None:  # noqa: ANN001
    """Against renders of the input (``psnr_before`` infinite) the check views' targets are the state's own renders
    too, so its PSNR there is known without a render; what the check decides is unchanged."""
    from symgs_core.pipeline import encode

    scene = _wall_and_hidden()
    state = LevelState.plain(scene)
    front, back = _views(scene, 1.0), _views(scene, -1.0)
    rd = RateDistortion(state.stored, sensitivity(state, front, torch.zeros(3)), QuantSteps())
    rendered: list[int] = []
    real = encode.evaluate
    monkeypatch.setattr(encode, "evaluate", lambda s, views, *a, **k: (
        rendered.append(len(s)) if views is back else None, real(s, views, *a, **k))[1])  # fmt: skip
    keep, removed = prune(state, rd, front, torch.zeros(3), allowed=psnr_to_mse(40.0), psnr_before=math.inf,
                          check=back)  # fmt: skip
    assert keep[torch.arange(WALL, WALL + HIDDEN)].all() and removed < 0.5 * psnr_to_mse(40.0)
    assert rendered and len(scene) not in rendered  # the shares were checked, the whole state was not rendered
