"""Exports of a decoded scene in the formats web viewers read; ``formats.EXPORTS`` is the one table of them.

Names are imported lazily, so reading the table (``symgs_core.export.formats``) costs no torch import.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..scene import GaussianScene
    from .formats import ExportFormat

_PUBLIC = {
    "EXPORTS": "formats",
    "ExportFormat": "formats",
    "by_name": "formats",
    "by_path": "formats",
    "SpzError": "spz",
    "read_spz": "spz",
    "write_spz": "spz",
    "compressed_ply_order": "playcanvas",
    "read_compressed_ply": "playcanvas",
    "write_compressed_ply": "playcanvas",
    "SogError": "sog",
    "read_sog": "sog",
    "sog_files": "sog",
    "sog_order": "sog",
    "write_sog": "sog",
    "GlbError": "glb",
    "read_glb": "glb",
    "write_glb": "glb",
}


def export_scene(scene: GaussianScene, path: str | os.PathLike[str], **options: Any) -> ExportFormat:
    """Write ``scene`` to ``path`` in the format its extension names (``meta.json``: the unbundled SOG); returns
    that format. ``options`` go to the writer (``version`` for `.spz`)."""
    from .formats import by_path

    fmt = by_path(path)
    fmt.save(scene, path, **options)
    return fmt


def save_scene(scene: GaussianScene, path: str | os.PathLike[str], *, comments: tuple[str, ...] = ()) -> None:
    """Write ``scene`` to ``path`` as a graphdeco PLY (``ply.ply_bytes``). A name another format owns (``.spz``,
    ``.compressed.ply``, ...) is refused: those bytes would not be that format; ``export_scene`` writes it."""
    from ..ply import ply_bytes
    from .formats import by_path

    try:
        owner = by_path(path)
    except ValueError:  # no format's extension (a temporary name, say): the caller's choice
        owner = None
    if owner is not None and owner.name != "ply":
        raise ValueError(f"{Path(path).name} names a {owner.title} file; save_scene writes a graphdeco PLY, "
                         "export_scene writes the format a name asks for")
    Path(path).write_bytes(ply_bytes(scene, comments=comments))


def import_scene(path: str | os.PathLike[str]) -> GaussianScene:
    """Read a scene written in any export format that has a reader (by extension)."""
    from .formats import by_path

    return by_path(path).read(path)


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'symgs_core.export' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


__all__ = sorted([*_PUBLIC, "export_scene", "import_scene", "save_scene"])
