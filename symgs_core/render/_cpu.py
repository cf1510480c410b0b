"""The CPU backend: PyTorch projection, compiled tile compositing."""

from __future__ import annotations

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from .projection import project
from .rasterize import TILE_SIZE, bin_gaussians, composite
from .result import RenderResult


def render_cpu(
    scene: GaussianScene, camera: Camera, background: Tensor, sh_degree: int, tile_size: int = TILE_SIZE
) -> RenderResult:
    """Render on the CPU; ``background`` [3]. The image does not depend on ``tile_size`` (only the speed does)."""
    proj = project(scene, camera, sh_degree)
    # Depth rides along as a fourth channel so the expected depth is composited (and differentiated) with colour.
    feats = torch.cat([proj.colors, proj.depths[:, None]], dim=-1)
    bg = torch.cat([background, background.new_zeros(1)])
    binning = bin_gaussians(proj.means2d, proj.radii, proj.depths, camera.width, camera.height, tile_size)
    out, alpha = composite(proj.means2d, proj.conics, feats, proj.opacity, bg, binning)
    visible = torch.from_numpy(binning.visible).to(scene.device)
    radii = torch.where(visible, proj.radii, torch.zeros_like(proj.radii)).clamp(max=2**31 - 1).to(torch.int32)
    return RenderResult(
        image=out[..., :3].clamp(0.0, 1.0),
        alpha=alpha,
        depth=out[..., 3] / alpha.clamp_min(1e-10),
        aux={
            "radii": radii,
            "num_visible": int(visible.sum()),
            "num_intersections": binning.num_intersections,
            "backend": "cpu",
        },
    )
