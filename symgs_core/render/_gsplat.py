"""The CUDA backend: gsplat's rasterizer with the same conventions as the CPU backend.

gsplat is an optional extra (``pip install 'symgs[gpu]'``); it is imported inside the functions that need it so the
package imports without it. Its kernels compile on first use (``symgs worker --mode gpu`` builds them at start).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from ..sh import num_coeffs
from .projection import LOW_PASS
from .rasterize import TILE_SIZE
from .result import RenderResult

# Cameras rendered in one call hold at most this many (camera, Gaussian) pairs: gsplat keeps per-pair projections,
# about 100 bytes each, so a batch stays near 3 GiB whatever the scene's size.
BATCH_PAIRS = 1 << 25


class BackendUnavailableError(RuntimeError):
    """The requested render backend cannot run here (no CUDA device, or gsplat not installed)."""


@lru_cache(maxsize=1)
def gsplat_importable() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def render_gsplat_many(
    scene: GaussianScene, cameras: Sequence[Camera], background: Tensor, sh_degree: int
) -> list[RenderResult]:
    """One render per camera with ``gsplat.rasterization`` on the scene's CUDA device, the cameras of one size drawn
    together in as few gsplat calls as ``BATCH_PAIRS``
    allows; ``background`` [3]. The scene's activations are computed once for all of them."""
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
    scales, opacities = scene.activated_scales(), scene.activated_opacities()
    bg = background.to(device=device, dtype=dtype)
    per_call = max(1, BATCH_PAIRS // max(len(scene), 1))
    out: list[RenderResult | None] = [None] * len(cameras)
    groups: dict[tuple[int, int, float], list[int]] = {}
    for i, camera in enumerate(cameras):
        groups.setdefault((camera.width, camera.height, camera.near), []).append(i)
    for (width, height, near), members in groups.items():
        for start in range(0, len(members), per_call):
            batch = members[start : start + per_call]
            views = torch.stack([cameras[i].viewmat.to(device=device, dtype=dtype) for i in batch])  # [C, 4, 4]
            ks = torch.stack([cameras[i].K.to(device=device, dtype=dtype) for i in batch])  # [C, 3, 3]
            colours, alphas, meta = gsplat.rasterization(
                means=scene.means,
                quats=scene.quats,
                scales=scales,
                opacities=opacities,
                colors=coeffs,  # [N, K, 3]
                viewmats=views,
                Ks=ks,
                width=width,
                height=height,
                near_plane=near,
                eps2d=LOW_PASS,
                sh_degree=sh_degree,
                packed=False,
                tile_size=TILE_SIZE,
                backgrounds=bg[None].repeat(len(batch), 1),  # [C, 3]
                render_mode="RGB+ED",
                rasterize_mode="classic",
            )
            radii = meta["radii"]  # [C, N] in older gsplat, [C, N, 2] (x and y extent) in newer
            if radii.dim() == 3:
                radii = radii.max(dim=-1).values
            for c, i in enumerate(batch):
                out[i] = RenderResult(
                    image=colours[c, ..., :3].clamp(0.0, 1.0),
                    alpha=alphas[c, ..., 0],
                    depth=colours[c, ..., 3],
                    aux={"radii": radii[c].to(torch.int32), "backend": "gsplat"},
                )
    return [r for r in out if r is not None]
