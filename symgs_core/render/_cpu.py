"""The CPU backend: compiled projection (autograd through ``projection.project`` for float64 scenes), compiled tile
compositing."""

from __future__ import annotations

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from .projection import Projection, project
from .rasterize import TILE_SIZE, bin_gaussians, composite
from .result import RenderResult


def render_cpu(
    scene: GaussianScene, camera: Camera, background: Tensor, sh_degree: int, tile_size: int = TILE_SIZE
) -> RenderResult:
    """Render on the CPU; ``background`` [3]. The image does not depend on ``tile_size`` (only the speed does)."""
    compiled = scene.means.dtype == torch.float32
    proj = _project_compiled(scene, camera, sh_degree) if compiled else project(scene, camera, sh_degree)
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
            "num_intersections": binning.num_intersections,
            "backend": "cpu",
        },
    )


class _ProjectCompiled(torch.autograd.Function):
    """``project`` in one compiled pass each way (``_project_kernel``, ``_project_grad``); float32."""

    @staticmethod
    def forward(ctx, camera: Camera, degree: int, *attributes: Tensor):  # noqa: ANN001, ANN205
        from ._project_kernel import project_fast

        means, quats, scales, opacities, dc, rest = _host(attributes)
        device = attributes[0].device
        outs = [torch.from_numpy(a).to(device)
                for a in project_fast(means, quats, scales, opacities, dc, rest, degree, camera)]  # fmt: skip
        ctx.save_for_backward(*attributes)  # autograd then refuses a backward after they changed in place
        ctx.camera, ctx.degree = camera, degree
        ctx.mark_non_differentiable(outs[3])  # radii
        return tuple(outs)

    @staticmethod
    def backward(ctx, *grads: Tensor):  # noqa: ANN001, ANN205
        from ._project_grad import project_backward_fast

        attributes = ctx.saved_tensors
        host = [g.detach().cpu().to(torch.float64).contiguous().numpy() for i, g in enumerate(grads) if i != 3]
        outs = project_backward_fast(_host(attributes), ctx.degree, ctx.camera, host)
        return (None, None, *(torch.from_numpy(o).to(attributes[0].device) for o in outs))


def _host(tensors: tuple[Tensor, ...]) -> list:
    """The compiled kernels' inputs: contiguous float32 arrays on the host."""
    return [t.detach().cpu().contiguous().numpy() for t in tensors]


def _project_compiled(scene: GaussianScene, camera: Camera, sh_degree: int) -> Projection:
    """``project`` for a float32 scene, forward and backward compiled; float64 scenes (the exactness tests') keep
    the reference."""
    return Projection(*_ProjectCompiled.apply(camera, sh_degree, scene.means, scene.quats, scene.scales,
                                               scene.opacities, scene.sh_dc, scene.sh_rest))  # fmt: skip
