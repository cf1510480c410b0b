"""SymGS core: the method, usable alone (no web, queue or Redis imports).

Public names are imported lazily so that ``import symgs_core`` stays cheap for tools that need one part.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

# OpenMP threads (torch's and numba's) that spin while waiting take the cores from the threads doing the work: on
# two busy cores that made the renderer ten times slower. Only effective before torch is first imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

_PUBLIC = {
    "GaussianScene": "scene",
    "load_scene": "ply",
    "save_scene": "export",
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
    "CompressConfig": "config",
    "export_scene": "export",
    "import_scene": "export",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'symgs_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value
