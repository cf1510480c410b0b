"""``render``: one entry point over the CPU and gsplat backends."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from ._cpu import render_cpu
from ._gsplat import gsplat_importable, render_gsplat_many
from .result import RenderResult

Backend = Literal["auto", "cpu", "gsplat"]


def render(
    scene: GaussianScene,
    camera: Camera,
    background: Tensor | None = None,
    *,
    backend: Backend = "auto",
    sh_degree: int | None = None,
) -> RenderResult:
    """Render ``scene`` from ``camera`` over ``background`` [3] RGB (default black).

    Differentiable with respect to every Gaussian attribute (and the background). ``backend="auto"`` uses gsplat
    when the scene is on CUDA and gsplat imports, the CPU tile rasterizer otherwise. ``sh_degree`` (default: the
    scene's) renders with the first bands only.
    """
    return render_many(scene, [camera], background, backend=backend, sh_degree=sh_degree)[0]


def render_many(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    background: Tensor | None = None,
    *,
    backend: Backend = "auto",
    sh_degree: int | None = None,
) -> list[RenderResult]:
    """``render`` from each of ``cameras``: on gsplat the cameras of one size are drawn in one call."""
    degree = scene.sh_degree if sh_degree is None else sh_degree
    if not 0 <= degree <= scene.sh_degree:
        raise ValueError(f"sh_degree must be in 0..{scene.sh_degree} for this scene, got {sh_degree}")
    dtype, device = scene.means.dtype, scene.device
    if background is None:
        bg = torch.zeros(3, dtype=dtype, device=device)
    else:
        bg = torch.as_tensor(background, device=device).to(dtype=dtype)
        if tuple(bg.shape) != (3,):
            raise ValueError(f"background must be an RGB tensor of shape (3,), got {tuple(bg.shape)}")
    if backend == "auto":
        backend = "gsplat" if scene.means.is_cuda and gsplat_importable() else "cpu"
    if backend == "cpu":
        return [render_cpu(scene, camera, bg, degree) for camera in cameras]
    if backend == "gsplat":
        return render_gsplat_many(scene, cameras, bg, degree)
    raise ValueError(f"backend must be 'auto', 'cpu' or 'gsplat', got {backend!r}")
