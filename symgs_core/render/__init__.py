"""Differentiable rendering of Gaussian scenes: a compiled CPU tile rasterizer and gsplat on CUDA."""

from __future__ import annotations

from ._gsplat import BackendUnavailableError
from .dispatch import Backend, render, render_many
from .result import RenderResult

__all__ = ["Backend", "BackendUnavailableError", "RenderResult", "render", "render_many"]
