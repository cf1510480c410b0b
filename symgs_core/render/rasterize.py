"""Tile rasterizer for the CPU: compiled compositing kernels wrapped in an autograd Function."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from . import _kernels

TILE_SIZE = 16


@dataclass(frozen=True)
class Binning:
    """Which Gaussians each tile composites: ids[offsets[t]:offsets[t + 1]] for tile t, front to back."""

    rects: np.ndarray  # [N, 4] int32 pixel rects (x0, x1, y0, y1); x0 > x1 for Gaussians that touch no pixel
    offsets: np.ndarray  # [T + 1] int64
    ids: np.ndarray  # [I] int32
    order: np.ndarray  # [T] int64 tiles, arranged so each thread's share holds about as many intersections
    width: int
    height: int
    tile_size: int

    @property
    def num_intersections(self) -> int:
        return int(self.ids.shape[0])

    @property
    def visible(self) -> np.ndarray:
        """[N] bool: the Gaussians that touch at least one pixel centre."""
        return self.rects[:, 0] <= self.rects[:, 1]


def _np64(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


def bin_gaussians(
    means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = TILE_SIZE
) -> Binning:
    """Bin Gaussians (means2d [N, 2], radii [N], 0 = culled; depths [N]) front to back into square tiles."""
    if tile_size <= 0:
        raise ValueError(f"tile_size must be positive, got {tile_size}")
    threads = numba.get_num_threads()
    rects, offsets, ids = _kernels.bin_gaussians(
        _np64(means2d), _np64(radii), _np64(depths), width, height, tile_size, threads
    )
    # numba hands each thread one contiguous share of a parallel loop; balance the shares, or the thread that drew
    # the object's busy tiles finishes long after the others.
    order = _kernels.balance_tiles(np.diff(offsets).astype(np.float64), threads)
    return Binning(rects, offsets, ids, order, width, height, tile_size)


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means2d: Tensor,
        conics: Tensor,
        feats: Tensor,
        opacity: Tensor,
        background: Tensor,
        binning: Binning,
    ):
        b = binning
        rec = _kernels.pack(_np64(means2d), _np64(conics), _np64(feats), _np64(opacity), b.rects)
        out, t_final = _kernels.composite_forward(
            rec, b.offsets, b.ids, b.order, _np64(background), b.width, b.height, b.tile_size
        )
        ctx.rec = rec
        ctx.binning = binning
        ctx.out = out
        ctx.t_final = t_final
        dtype, device = feats.dtype, feats.device
        image = torch.from_numpy(out).to(device=device, dtype=dtype)
        alpha = torch.from_numpy(1.0 - t_final).to(device=device, dtype=dtype)
        return image, alpha

    @staticmethod
    def backward(ctx, grad_image: Tensor, grad_alpha: Tensor):
        b: Binning = ctx.binning
        g_out = _np64(grad_image)
        rows = _kernels.composite_backward(
            ctx.rec, b.offsets, b.ids, b.order, b.width, b.height, b.tile_size, ctx.out, ctx.t_final, g_out,
            -_np64(grad_alpha),
        )
        total = _kernels.sum_by_gaussian(rows, b.ids, ctx.rec.shape[0], numba.get_num_threads())
        dtype, device = grad_image.dtype, grad_image.device
        total_t = torch.from_numpy(total).to(device=device, dtype=dtype)
        g_bg = torch.from_numpy(np.einsum("hwc,hw->c", g_out, ctx.t_final)).to(device=device, dtype=dtype)
        g = _kernels.GEOM_GRADS
        return total_t[:, 0:2], total_t[:, 2:5], total_t[:, g:], total_t[:, 5], g_bg, None


def composite(
    means2d: Tensor, conics: Tensor, feats: Tensor, opacity: Tensor, background: Tensor, binning: Binning
) -> tuple[Tensor, Tensor]:
    """Front-to-back composite of binned Gaussians: channels [H, W, D] over ``background`` [D], alpha [H, W].

    means2d [N, 2], conics [N, 3], feats [N, D], opacity [N] (activated); differentiable in all of them and in
    ``background``. Gaussians left out by ``binning`` get zero gradients.
    """
    n, d = feats.shape
    for name, t, shape in (
        ("means2d", means2d, (n, 2)),
        ("conics", conics, (n, 3)),
        ("opacity", opacity, (n,)),
        ("background", background, (d,)),
    ):
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {shape}")
    if binning.rects.shape[0] != n:
        raise ValueError(f"binning covers {binning.rects.shape[0]} Gaussians, got {n}")
    return _Composite.apply(means2d, conics, feats, opacity, background, binning)
