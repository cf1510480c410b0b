"""The stages after the mirror levels: pruning, SH reduction, quantisation, entropy coding, and their accounting.

Each stage reports what it saved in bytes and cost in dB (held-out PSNR), so a report shows where the size went:
mirrors, pruning and SH reduction are measured on the lossless (float32 + zstd) archive of what they leave;
quantisation against the fixed-width size of its symbols (what a plain quantiser would store); entropy coding is
the final archive. Preset ``lossless`` runs no reduction and stores float32, as the archive always did.

Quantised presets store each rotation in its canonical frame (``codec.frames``) and give the SH palette the render
weight of every SH row (``with_sh_weights``). Pruning and SH reduction spend budget the quantiser could spend: when
they removed anything, the steps are also fitted straight after the mirrors, and the reductions stay only if the
archive with them is the smaller (their records then say ``kept: false``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from torch import Tensor

from ..codec import ArchiveContents, coding_order, encode_archive
from ..codec.frames import canonical_frames
from ..codec.order import grid_cells
from ..codec.palette import RowWeights
from ..codec.registry import ArchiveCodec, archive_codec
from ..codec.steps import QuantSteps
from ..config import PRESETS, CompressConfig
from ..mirror import Plane
from ..report import CodecReport, StageReport
from ..views import evaluate
from .budget import archive_bytes, extent_of, fit_steps, split_budget
from .prune import contributions, prune, reduce_sh
from .state import LevelState


def preset_steps(config: CompressConfig) -> QuantSteps:
    """The preset's starting steps; the search then scales them to spend the preset's budget."""
    return QuantSteps().scaled(PRESETS[config.preset].step_scale)


def write_archive(state: LevelState, meta: dict, codec: str | ArchiveCodec = "lossless") -> bytes:
    """The archive of ``state`` in coding order, written by ``codec`` (an archive codec or a registered name)."""
    planes = [Plane.from_tensor(n, g) for n, g in zip(state.normals, state.offsets)]
    stored, bits = state.stored.detach().to("cpu"), state.bits.cpu()
    cells = grid_cells(archive_codec(codec).sections["means"], stored.means.numpy())
    perm = coding_order(stored, bits, cells)
    return encode_archive(ArchiveContents(stored.select(perm), planes, bits[perm], meta), codec=codec)


def mirror_floor(config: CompressConfig, floor: float, reference: float) -> float:
    """The floor the mirror levels are judged against: all of it for ``lossless``, their share otherwise."""
    return floor if not config.quantized else split_budget(floor, reference)["mirrors"]


def _fixed_width_bytes(state: LevelState, steps: QuantSteps) -> int:
    """Bytes of the quantised symbols at the narrowest fixed width per attribute (no entropy coding)."""
    stored = state.stored.detach().to("cpu")
    extent = extent_of(stored)
    total_bits = 0.0
    grids = {
        "means": steps.position * max(extent, 1e-12), "scales": steps.scale, "sh_dc": steps.dc,
        "quats": steps.rotation, "opacities": steps.opacity,
    }  # fmt: skip
    for name, step in grids.items():
        values = stored.tensors()[name].numpy().astype(np.float64)
        if name == "opacities":
            values = 1.0 / (1.0 + np.exp(-values))
        span = float(values.max() - values.min()) if values.size else 0.0
        per = values[0].size if values.ndim > 1 else 1
        if name == "quats":
            per, span = 3, 2.0**0.5  # three of four components in [-1/sqrt2, 1/sqrt2], plus a 2-bit index
            total_bits += 2 * len(values)
        total_bits += len(values) * per * math.ceil(math.log2(span / step + 2))
    rest = stored.sh_rest.numpy()
    # A palette stores its entries once and an index per Gaussian; per coefficient, the bands each Gaussian keeps.
    entries = min(steps.sh_palette, len(stored)) if steps.sh_palette else 0
    for lvl, step in zip(range(1, stored.sh_degree + 1), steps.sh):
        band = rest[:, lvl * lvl - 1 : (lvl + 1) ** 2 - 1, :]
        stored_values = band[np.abs(band).reshape(len(band), -1).max(axis=1) * 2 >= step]
        if stored_values.size:
            span = float(stored_values.max() - stored_values.min())
            count = entries * band[0].size if entries else stored_values.size
            total_bits += count * math.ceil(math.log2(span / step + 2))
    if stored.sh_degree:
        total_bits += len(stored) * (math.ceil(math.log2(entries + 1)) if entries else 2)
    return int(total_bits // 8) + state.bits.shape[1] * ((len(stored) + 7) // 8)


@dataclass
class Coded:
    """The stored state after every stage, its archive, the codec alone on the input (baseline), the accounting."""

    state: LevelState
    archive: bytes
    baseline: bytes
    codec: CodecReport
    stages: list[StageReport] = field(default_factory=list)


def _stage(
    name: str, before: int, after: int, psnr_before: float, psnr_after: float, seconds: float, **extra: Any
) -> StageReport:
    cost = psnr_before - psnr_after if math.isfinite(psnr_before) and math.isfinite(psnr_after) else None
    return StageReport(name, before, after, before - after, psnr_after, cost, seconds, **extra)


_LOSSLESS = CodecReport("lossless", None, None, 0)


def _canonical(state: LevelState) -> LevelState:
    """``state`` with each stored rotation in its frame closest to the identity (``codec.frames``)."""
    return LevelState(canonical_frames(state.stored.detach()), state.normals, state.offsets, state.bits)


def with_sh_weights(start: QuantSteps, state: LevelState, train: list) -> QuantSteps:
    """``start`` with the render weight of each SH row of ``state`` over the training views, for the SH palette."""
    if not state.stored.sh_degree:
        return start
    weights = contributions(state, [view.camera for view in train]).numpy()
    return replace(start, sh_weights=RowWeights.of(state.stored.sh_rest.detach().cpu().numpy(), weights))


def _undone(record: StageReport, psnr: float) -> StageReport:
    """A reduction's record once the archive without it was the smaller: it saved nothing and cost nothing; the
    fitting PSNR is ``psnr``, that of the state before the reductions, and ``psnr_if_kept`` what it measured."""
    return replace(record, bytes_after=record.bytes_before, saved_bytes=0, psnr_after=psnr,
                   psnr_if_kept=record.psnr_after, cost_db=0.0, kept=False,
                   reason="the archive quantised without pruning and SH reduction was smaller")  # fmt: skip


def reduce_and_encode(
    source_state: LevelState,
    state: LevelState,
    train: list,
    test: list,
    background: Tensor,
    *,
    config: CompressConfig,
    floor: float,
    reference: float,
    extent: float,
    meta: dict,
    report,  # noqa: ANN001 - pipeline._Reporter
) -> Coded:
    """Run pruning, SH reduction and quantisation on ``state`` (after the mirrors) within the shared budget."""
    t0 = time.perf_counter()
    input_bytes = len(write_archive(source_state, meta))
    mirrored_bytes = len(write_archive(state, meta)) if state.normals.shape[0] else input_bytes
    psnr = evaluate(state.expanded(), test, background).worst if state.normals.shape[0] else reference
    stages = [_stage("mirrors", input_bytes, mirrored_bytes, reference, psnr, time.perf_counter() - t0)]
    if not config.quantized:
        archive = write_archive(state, meta)
        stages.append(_stage("entropy_coding", mirrored_bytes, len(archive), psnr, psnr, 0.0))
        return Coded(state, archive, write_archive(source_state, meta), _LOSSLESS, stages)

    floors = split_budget(floor, reference)
    mirrored, mirrored_psnr = state, psnr
    before_bytes = mirrored_bytes
    for name, run in (
        ("pruning", lambda st: prune(st, train, test, background, floor=floors["pruning"], extent=extent,
                                     iterations=config.iterations // 4)),
        ("sh_reduction", lambda st: reduce_sh(st, train, test, background, floor=floors["sh_reduction"])),
    ):  # fmt: skip
        t0 = time.perf_counter()
        report("encode", 0.0, f"{name.replace('_', ' ')}")
        result = run(state)
        if result is None:
            stages.append(_stage(name, before_bytes, before_bytes, psnr, psnr, time.perf_counter() - t0, removed=0))
            continue
        state = result.state
        after_bytes = len(write_archive(state, meta))
        stages.append(_stage(name, before_bytes, after_bytes, psnr, result.psnr, time.perf_counter() - t0,
                             removed=result.removed, threshold=result.threshold))  # fmt: skip
        before_bytes, psnr = after_bytes, result.psnr
        report.timed(name, time.perf_counter() - t0)

    t0 = time.perf_counter()
    report("encode", 0.3, "fitting quantisation steps")
    quantization_floor = floors["quantization"]
    reduced, exact = state is not mirrored, state
    state = _canonical(state)
    start = with_sh_weights(preset_steps(config), state, train)
    fit = fit_steps(state, test, background, floor=quantization_floor, start=start, psnr_before=psnr)
    if reduced:
        # Pruning and SH reduction spend budget the quantiser could have spent: they stay only if the archive with
        # them is smaller than the one quantised straight after the mirrors (playbot 125k: SH reduction cost 25%
        # of the error budget and the archive came out larger).
        report("encode", 0.6, "fitting quantisation steps without pruning and SH reduction, to compare")
        direct = _canonical(mirrored)
        direct_fit = fit_steps(direct, test, background, floor=quantization_floor,
                               start=with_sh_weights(preset_steps(config), direct, train),
                               psnr_before=mirrored_psnr)  # fmt: skip
        if direct_fit is not None and (
            fit is None or archive_bytes(direct.stored, direct_fit.steps) < archive_bytes(state.stored, fit.steps)
        ):
            state, exact, fit, psnr, before_bytes = direct, mirrored, direct_fit, mirrored_psnr, mirrored_bytes
            stages = [_undone(st, psnr) if st.stage in ("pruning", "sh_reduction") else st for st in stages]
    report.timed("quantize", time.perf_counter() - t0)
    if fit is None:  # nothing lossy fits the budget that is left: store the attributes exactly
        state = exact
        archive = write_archive(state, meta)
        stages.append(_stage("quantization", before_bytes, before_bytes, psnr, psnr, time.perf_counter() - t0))
        stages.append(_stage("entropy_coding", before_bytes, len(archive), psnr, psnr, 0.0))
        return Coded(state, archive, write_archive(source_state, meta), _LOSSLESS, stages)
    codec = fit.steps.archive_codec(extent_of(state.stored), config.preset)
    fixed = _fixed_width_bytes(state, fit.steps)
    stages.append(_stage("quantization", before_bytes, fixed, psnr, fit.psnr, time.perf_counter() - t0))
    t0 = time.perf_counter()
    archive = write_archive(state, meta, codec)
    stages.append(_stage("entropy_coding", fixed, len(archive), fit.psnr, fit.psnr, time.perf_counter() - t0))
    report = CodecReport(config.preset, fit.steps.report(), floors["quantization"], len(fit.tries))
    plain_codec = replace(fit.steps, sh_weights=None).archive_codec(extent_of(source_state.stored), config.preset)
    baseline = write_archive(_canonical(source_state), meta, plain_codec)
    return Coded(state, archive, baseline, report, stages)
