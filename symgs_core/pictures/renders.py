"""Pictures made of renders: the input beside the decoded scene with their difference, and the mirror planes
drawn over the scene."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from matplotlib.colors import to_rgba
from matplotlib.patches import Patch, Polygon
from torch import Tensor

from ..cameras import Camera
from ..mirror import Plane
from ..scene import GaussianScene
from ._png import new_figure, png_bytes
from .geometry import plane_box_polygon, project_polygon
from .palette import level_colour


def picture_camera(camera: Camera, size: int) -> Camera:
    """``camera`` resized so that its longest side is ``size`` pixels."""
    if size < 8:
        raise ValueError(f"picture size must be at least 8 pixels, got {size}")
    scale = size / max(camera.width, camera.height)
    return camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))


@torch.no_grad()
def render_view(scene: GaussianScene, camera: Camera, background: Tensor) -> np.ndarray:
    """The scene from ``camera`` as float32 RGB [H, W, 3] in [0, 1]."""
    from ..render import render

    image = render(scene, camera.to(scene.device), background.to(scene.device)).image
    return image.clamp(0.0, 1.0).detach().to("cpu", torch.float32).numpy()


def difference_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean absolute difference over the colour channels [H, W] of two images [H, W, 3]."""
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"images must both be [H, W, 3], got {a.shape} and {b.shape}")
    return np.abs(a.astype(np.float64) - b.astype(np.float64)).mean(axis=2)


def image_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of ``b`` against ``a``, both in [0, 1]; inf when identical."""
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def compare_png(reference: np.ndarray, decoded: np.ndarray, title: str) -> bytes:
    """Three panels: ``reference`` [H, W, 3] (the uncompressed scene), ``decoded`` [H, W, 3], and a heat map of
    their mean absolute difference on a scale from 0 to the largest difference (at least 1/255)."""
    diff = difference_map(reference, decoded)
    h, w = diff.shape
    fig = new_figure(3 * w + 150, h + 90)
    axes = fig.subplots(1, 3)
    psnr = image_psnr(reference, decoded)
    fidelity = "identical" if psnr == math.inf else f"{psnr:.2f} dB"
    panels = [(reference, "uncompressed"), (decoded, f"decoded ({fidelity})")]
    for ax, (image, label) in zip(axes, panels):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(label, fontsize=9)
    heat = axes[2].imshow(diff, cmap="inferno", vmin=0.0, vmax=max(float(diff.max()), 1 / 255), interpolation="nearest")
    axes[2].set_title("|difference|, mean over RGB", fontsize=9)
    fig.colorbar(heat, ax=axes[2], fraction=0.046, pad=0.02)
    for ax in axes:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    return png_bytes(fig)


def mirrors_png(
    image: np.ndarray,
    camera: Camera,
    planes: Sequence[tuple[int, Plane]],
    box: tuple[np.ndarray, np.ndarray],
    title: str = "Mirror planes found",
) -> bytes:
    """``image`` [H, W, 3] seen from ``camera`` (of the same size) with each ``(level, plane)`` drawn over it: the
    plane cut to ``box`` (lo [3], hi [3]), filled semi-transparent and outlined in the level's colour."""
    h, w = image.shape[:2]
    if (camera.width, camera.height) != (w, h):
        raise ValueError(f"camera is {camera.width}x{camera.height} but the image is {w}x{h}")
    fig = new_figure(w + 40, h + 70 + 20 * max(len(planes), 1))
    ax = fig.add_subplot()
    ax.imshow(image, extent=(0, w, h, 0), interpolation="nearest")  # pixel centres at +0.5, as the renderer's
    handles = []
    for level, plane in planes:
        colour = level_colour(level)
        outline = project_polygon(plane_box_polygon(plane.normal, plane.offset, *box), camera)
        if len(outline):
            ax.add_patch(Polygon(outline, closed=True, facecolor=to_rgba(colour, 0.3), edgecolor=colour, linewidth=2))
        n = [round(v, 3) + 0.0 for v in (*plane.normal, plane.offset)]  # + 0.0 turns -0.0 into 0.0
        where = "" if len(outline) else " (out of view)"
        label = f"level {level}: n = ({n[0]:+.3f}, {n[1]:+.3f}, {n[2]:+.3f}), offset {n[3]:+.3f}{where}"
        handles.append(Patch(facecolor=to_rgba(colour, 0.3), edgecolor=colour, label=label))
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_axis_off()
    ax.set_title(title if planes else "No mirror plane was accepted", fontsize=10)
    if handles:
        fig.legend(handles=handles, loc="outside lower center", fontsize=8, frameon=False)
    return png_bytes(fig)
