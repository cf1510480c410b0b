"""The one table of export formats: name, extension, media type, writer and reader.

Everything that offers a decoded scene reads this table: ``symgs decompress`` (by extension), the worker's result
files (``result<extension>``), the HTTP download routes and their OpenAPI entries, the job's links and the dashboard.
Adding a format is one row here and its writer. The table is standard library only, so the API process, which
never imports torch, can read it: writers and readers are named as ``module:function`` and imported when called.
A format that also has an unbundled layout (SOG's ``meta.json`` beside its images) names the file that stands for
the folder (``folder_entry``) and the function that writes it; the worker and the HTTP API offer the bundle.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..scene import GaussianScene


@dataclass(frozen=True)
class ExportFormat:
    name: str  # key in links and reports, e.g. "spz"
    extension: str  # with its leading dot, e.g. ".compressed.ply"
    media_type: str
    title: str  # what people call it
    description: str  # one sentence for the OpenAPI document and the dashboard
    writer: str  # "module:function" under symgs_core, (scene, **options) -> bytes
    reader: str | None = None  # "module:function" under symgs_core, path -> GaussianScene
    options: tuple[str, ...] = ()  # keyword options the writer takes; others given to ``write`` are not for it
    folder_entry: str | None = None  # the file name that asks for the unbundled layout, e.g. "meta.json"
    folder_writer: str | None = None  # "module:function", (scene, entry path, **options) -> None

    @property
    def artifact(self) -> str:
        """The job's result file holding this format."""
        return f"result{self.extension}"

    def write(self, scene: GaussianScene, **options: Any) -> bytes:
        """The file's bytes; of ``options``, those this format takes (``version`` for `.spz`)."""
        return _resolve(self.writer)(scene, **{k: v for k, v in options.items() if k in self.options})

    def save(self, scene: GaussianScene, path: str | os.PathLike[str], **options: Any) -> None:
        """Write ``scene`` at ``path``: the unbundled layout when ``path`` is named ``folder_entry``, else the file."""
        mine = {k: v for k, v in options.items() if k in self.options}
        if self.folder_writer is not None and Path(path).name.lower() == self.folder_entry:
            _resolve(self.folder_writer)(scene, path, **mine)
        else:
            Path(path).write_bytes(self.write(scene, **mine))

    def read(self, path: str | os.PathLike[str]) -> GaussianScene:
        if self.reader is None:
            raise ValueError(f"{self.title} files cannot be read back by this build")
        return _resolve(self.reader)(path)


def _resolve(target: str):  # noqa: ANN202 - the function named by "module:function"
    module, _, function = target.partition(":")
    return getattr(importlib.import_module(f"symgs_core.{module}"), function)


EXPORTS: tuple[ExportFormat, ...] = (
    ExportFormat(
        "ply", ".ply", "application/x-ply", "PLY",
        "The decoded scene in the graphdeco PLY layout (float32) that every 3DGS viewer reads.",
        "ply:ply_bytes", "ply:load_scene",
    ),
    ExportFormat(
        "spz", ".spz", "application/octet-stream", "SPZ",
        "The decoded scene in Niantic's .spz format, version 3, which most web viewers read.",
        "export.spz:write_spz", "export.spz:load_spz", ("version",),
    ),
    ExportFormat(
        "compressed_ply", ".compressed.ply", "application/x-ply", "PlayCanvas compressed PLY",
        "The decoded scene in PlayCanvas' compressed PLY layout (quantised in chunks of 256 Gaussians).",
        "export.playcanvas:write_compressed_ply", "export.playcanvas:load_compressed_ply",
    ),
    ExportFormat(
        "sog", ".sog", "application/octet-stream", "PlayCanvas SOG",
        "The decoded scene as a PlayCanvas SOG bundle (a zip of meta.json and lossless WebP images), which the "
        "PlayCanvas engine, SuperSplat and splat-transform read.",
        "export.sog:write_sog", "export.sog:load_sog",
        folder_entry="meta.json", folder_writer="export.sog:save_sog_folder",
    ),
    ExportFormat(
        "glb", ".glb", "model/gltf-binary", "glTF binary (KHR_gaussian_splatting)",
        "The decoded scene as glTF binary with the Khronos KHR_gaussian_splatting extension (float attributes, "
        "y-up axes).",
        "export.glb:write_glb", "export.glb:load_glb",
    ),
)  # fmt: skip


def by_name(name: str) -> ExportFormat:
    for fmt in EXPORTS:
        if fmt.name == name:
            return fmt
    raise ValueError(f"unknown export format {name!r}; known: {', '.join(f.name for f in EXPORTS)}")


def by_path(path: str | os.PathLike[str]) -> ExportFormat:
    """The format a file name asks for (the longest matching extension); ValueError naming the known ones."""
    name = Path(path).name.lower()
    matches = [fmt for fmt in EXPORTS if name.endswith(fmt.extension) or name == fmt.folder_entry]
    if not matches:
        raise ValueError(f"unsupported export format for {Path(path).name!r}: use {extensions()}")
    return max(matches, key=lambda fmt: len(fmt.extension))


def extensions() -> str:
    """The known extensions, for help texts and messages."""
    folders = [f"{fmt.folder_entry} (unbundled {fmt.extension})" for fmt in EXPORTS if fmt.folder_entry]
    return ", ".join([fmt.extension for fmt in EXPORTS] + folders)
