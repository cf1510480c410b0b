"""Compress and decompress end to end. ``compress`` runs the job's stages in order, each a function of the state
the one before returned: load and views (``prepare``), the plain codec (``codec_fit``), against photographs the upload
fine-tuned as a whole (``refine``), the mirror levels (``levels``), then the archive, its evaluation and the report
(``result``)."""

from __future__ import annotations

from pathlib import Path

import torch

from .. import heap
from ..codec import decode_archive, expand_archive
from ..config import CompressConfig
from ..devices import resolve_device
from ..progress import ProgressFn, StopFn
from ..scene import GaussianScene
from . import codec_fit, levels, prepare, refine, result
from .job import Job, Reporter, stage_shares
from .result import CompressResult


def compress(
    scene: GaussianScene | str | Path,
    *,
    images: str | Path | None = None,
    config: CompressConfig | None = None,
    progress: ProgressFn | None = None,
    checkpoint_dir: str | Path | None = None,
    should_stop: StopFn | None = None,
    charts: bool = True,
) -> CompressResult:
    """Compress a scene (or a .ply path) into a ``.symgs`` archive and a report.

    ``config`` defaults to ``CompressConfig.for_preset()``, the default preset. Decisions hold the budget's floor on
    the fitting cameras; the report scores the evaluation cameras, which fitted nothing. With ``checkpoint_dir``
    every level decision is saved there and a rerun with the same inputs resumes after it. ``charts`` False leaves
    the two charts drawn from the report alone out of the pictures, for a caller that draws them with more points.
    """
    config = config or CompressConfig.for_preset()
    if not isinstance(config, CompressConfig):
        raise TypeError(f"config must be a CompressConfig, e.g. CompressConfig.for_preset('small'), got {config!r}")
    shares = stage_shares(config, photographs=images is not None)
    job = Job(config, resolve_device(config.device), Reporter(progress, should_stop, shares),
              Path(images) if images is not None else None,
              Path(checkpoint_dir) if checkpoint_dir is not None else None, charts)  # fmt: skip
    torch.manual_seed(config.seed)
    with heap.kept():  # a large scene's arrays, freed and allocated again render after render
        loaded = prepare.load(scene, job)
        viewed = prepare.views(loaded, job)
        # The plain fit is passed on, not kept: where the fine-tune replaces it, its rate model would stay alive.
        refined = refine.refine(codec_fit.fit(viewed, job), job)
        levelled = levels.levels(refined, job)
        encoded = result.encode(levelled, job)
        evaluated = result.evaluate(encoded, job)
        return result.report(evaluated, job)


def decompress(archive: bytes | bytearray | memoryview | str | Path) -> GaussianScene:
    """The decoded scene of a ``.symgs`` archive (its bytes or a path)."""
    data = archive if isinstance(archive, bytes | bytearray | memoryview) else Path(archive).read_bytes()
    return expand_archive(decode_archive(bytes(data)))


__all__ = ["CompressResult", "compress", "decompress"]
