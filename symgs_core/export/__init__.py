"""Exports of a decoded scene in the formats web viewers read, chosen by file extension.

``.ply`` graphdeco PLY (float32), ``.spz`` Niantic SPZ (version 3 unless ``version`` says 2 or 4),
``.compressed.ply`` PlayCanvas compressed PLY. Each writer has its reader beside it, for round trips.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import torch

from ..scene import GaussianScene
from .playcanvas import CompressedPlyError, compressed_ply_order, read_compressed_ply, write_compressed_ply
from .spz import SpzError, read_spz, write_spz

ExportFormat = Literal["ply", "spz", "compressed.ply"]
FORMATS: tuple[ExportFormat, ...] = ("ply", "spz", "compressed.ply")


def ply_bytes(scene: GaussianScene) -> bytes:
    """The graphdeco PLY of ``scene`` (binary little-endian float32, zero normals), as ``ply.save_scene`` writes it.

    Built as one float32 matrix: a million Gaussians take a fraction of a second, where a structured array per
    property takes seconds.
    """
    from ..ply import graphdeco_properties

    n, k = len(scene), scene.sh_rest.shape[1]
    t = {name: v.detach().to("cpu", torch.float32) for name, v in scene.tensors().items()}
    flat = torch.cat(
        [t["means"], torch.zeros(n, 3), t["sh_dc"], t["sh_rest"].transpose(1, 2).reshape(n, 3 * k),
         t["opacities"][:, None], t["scales"], t["quats"]],
        dim=1,
    )  # fmt: skip
    names = graphdeco_properties(scene.sh_degree)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + flat.numpy().astype("<f4", copy=False).tobytes()


def format_of(path: str | os.PathLike[str]) -> ExportFormat:
    """The export format a file name asks for; ValueError naming the known extensions otherwise."""
    name = Path(path).name.lower()
    if name.endswith(".compressed.ply"):
        return "compressed.ply"
    if name.endswith(".ply"):
        return "ply"
    if name.endswith(".spz"):
        return "spz"
    raise ValueError(f"unsupported export format for {Path(path).name!r}: use .ply, .spz or .compressed.ply")


def export_scene(
    scene: GaussianScene, path: str | os.PathLike[str], format: ExportFormat | None = None, *, version: int = 3
) -> ExportFormat:
    """Write ``scene`` to ``path`` in ``format`` (default: from the extension); returns the format written.

    ``version`` selects the `.spz` version (2, 3 or 4) and is ignored by the other formats.
    """
    fmt = format_of(path) if format is None else format
    if fmt == "ply":
        Path(path).write_bytes(ply_bytes(scene))
    elif fmt == "spz":
        Path(path).write_bytes(write_spz(scene, version=version))
    elif fmt == "compressed.ply":
        Path(path).write_bytes(write_compressed_ply(scene))
    else:
        raise ValueError(f"unknown export format {fmt!r}; known: {FORMATS}")
    return fmt


def import_scene(path: str | os.PathLike[str]) -> GaussianScene:
    """Read a scene written in any export format (by extension)."""
    fmt = format_of(path)
    if fmt == "ply":
        from ..ply import load_scene

        return load_scene(path)
    data = Path(path).read_bytes()
    return read_spz(data) if fmt == "spz" else read_compressed_ply(data)


__all__ = [
    "FORMATS",
    "CompressedPlyError",
    "ExportFormat",
    "SpzError",
    "compressed_ply_order",
    "export_scene",
    "format_of",
    "import_scene",
    "ply_bytes",
    "read_compressed_ply",
    "read_spz",
    "write_compressed_ply",
    "write_spz",
]
