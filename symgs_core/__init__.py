"""SymGS core: the method, usable alone (no web, queue or Redis imports).

Public names are imported lazily so that ``import symgs_core`` stays cheap for tools that need one part.
"""

from __future__ import annotations

import importlib
from typing import Any

_PUBLIC = {
    "GaussianScene": "scene",
    "load_scene": "ply",
    "save_scene": "ply",
    "PlyError": "ply",
    "Camera": "cameras",
    "orbit_cameras": "cameras",
    "scene_cameras": "cameras",
    "load_dataset": "datasets",
    "render": "render",
    "reflect": "mirror",
    "Plane": "mirror",
    "psnr": "metrics",
    "ssim": "metrics",
    "detect": "detect",
    "DetectConfig": "detect",
    "Mirror": "detect",
    "compress": "pipeline",
    "decompress": "pipeline",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'symgs_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value
