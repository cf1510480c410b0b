"""The CUDA backend: gsplat's rasterizer with the same conventions as the CPU backend.

gsplat is an optional extra (``pip install 'symgs[gpu]'``); it is imported inside the functions that need it so the
package imports without it. Its kernels compile on first use.
"""

from __future__ import annotations

from functools import lru_cache

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from ..sh import num_coeffs
from .projection import LOW_PASS
from .rasterize import TILE_SIZE
from .result import RenderResult


class BackendUnavailableError(RuntimeError):
    """The requested render backend cannot run here (no CUDA device, or gsplat not installed)."""


@lru_cache(maxsize=1)
def gsplat_importable() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def render_gsplat(scene: GaussianScene, camera: Camera, background: Tensor, sh_degree: int) -> RenderResult:
    """Render with ``gsplat.rasterization`` on the scene's CUDA device; ``background`` [3]."""
    if not scene.means.is_cuda:
        raise BackendUnavailableError(
            f"the gsplat backend renders CUDA tensors, but the scene is on {scene.device}; "
            "move it with scene.to('cuda') or use backend='cpu'"
        )
    try:
        import gsplat
    except ImportError as err:
        raise BackendUnavailableError(
            "the gsplat backend needs the optional 'gpu' extra: pip install 'symgs[gpu]'"
        ) from err

    device, dtype = scene.device, scene.means.dtype
    coeffs = torch.cat([scene.sh_dc[:, None, :], scene.sh_rest[:, : num_coeffs(sh_degree) - 1]], dim=1)
    out, alphas, meta = gsplat.rasterization(
        means=scene.means,
        quats=scene.quats,
        scales=scene.activated_scales(),
        opacities=scene.activated_opacities(),
        colors=coeffs,  # [N, K, 3]
        viewmats=camera.viewmat.to(device=device, dtype=dtype)[None],  # [1, 4, 4]
        Ks=camera.K.to(device=device, dtype=dtype)[None],  # [1, 3, 3]
        width=camera.width,
        height=camera.height,
        near_plane=camera.near,
        eps2d=LOW_PASS,
        sh_degree=sh_degree,
        packed=False,
        tile_size=TILE_SIZE,
        backgrounds=background.to(device=device, dtype=dtype)[None],  # [1, 3]
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    radii = meta["radii"][0]  # [N] in older gsplat, [N, 2] (x and y extent) in newer
    if radii.dim() == 2:
        radii = radii.max(dim=-1).values
    return RenderResult(
        image=out[0, ..., :3].clamp(0.0, 1.0),
        alpha=alphas[0, ..., 0],
        depth=out[0, ..., 3],
        aux={"radii": radii.to(torch.int32), "num_visible": int((radii > 0).sum()), "backend": "gsplat"},
    )
