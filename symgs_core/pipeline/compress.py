"""Compress and decompress end to end: views, mirror levels, archive, report."""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from ..cameras import COORDINATE_CONVENTION, scene_bounds
from ..codec import decode_archive, expand_archive
from ..config import CompressConfig
from ..progress import Cancelled, ProgressEvent, ProgressFn, StopFn
from ..scene import GaussianScene
from ..views import ViewSet, dataset_views, evaluate, self_supervised_views
from .encode import mirror_floor, reduce_and_encode, write_archive
from .levels import LevelRecord, run_levels
from .state import LevelState

# Share of the job's progress bar each stage takes; the mirror levels share theirs.
_STAGES = {
    "load": (0.0, 0.03),
    "views": (0.03, 0.12),
    "levels": (0.12, 0.9),
    "encode": (0.9, 0.95),
    "evaluate": (0.95, 1.0),
}


@dataclass
class CompressResult:
    archive: bytes
    report: dict
    images: dict[str, bytes] = field(default_factory=dict)


def resolve_device(choice: str) -> torch.device:
    if choice == "cuda" or (choice == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise ValueError("device 'cuda' requested but no CUDA device is available")
        return torch.device("cuda")
    return torch.device("cpu")


class _Reporter:
    def __init__(self, progress: ProgressFn | None, should_stop: StopFn | None) -> None:
        self.progress, self.should_stop = progress, should_stop
        self.seconds: dict[str, float] = {}
        self.reached = 0.0  # the bar never moves back, though a stage may run its steps twice (mirrors on and off)

    def __call__(self, stage: str, within: float, message: str, level: int | None = None) -> None:
        if self.should_stop is not None and self.should_stop():
            raise Cancelled()
        lo, hi = _STAGES[stage]
        if self.progress is not None:
            self.reached = max(self.reached, lo + (hi - lo) * min(max(within, 0.0), 1.0))
            self.progress(ProgressEvent(stage, level, self.reached, message))

    def timed(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


def _load(scene: GaussianScene | str | Path) -> tuple[GaussianScene, int, str]:
    if isinstance(scene, GaussianScene):
        return scene, 0, "scene"
    from ..ply import load_scene

    path = Path(scene)
    return load_scene(path), path.stat().st_size, path.name


def _fingerprint(scene: GaussianScene, config: CompressConfig, images: str | Path | None) -> str:
    h = hashlib.sha256()
    for t in scene.tensors().values():
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    h.update(json.dumps(asdict(config), sort_keys=True, default=str).encode())
    h.update(str(images).encode())
    return h.hexdigest()


def compress(
    scene: GaussianScene | str | Path,
    *,
    images: str | Path | None = None,
    config: CompressConfig | None = None,
    progress: ProgressFn | None = None,
    checkpoint_dir: str | Path | None = None,
    should_stop: StopFn | None = None,
) -> CompressResult:
    """Compress a scene (or a .ply path) into a ``.symgs`` archive and a report.

    Mirror levels are accepted while they keep the held-out PSNR within ``config.psnr_budget``; with
    ``checkpoint_dir`` every level decision is saved there and a rerun with the same inputs resumes after it.
    """
    config = config or CompressConfig()
    report = _Reporter(progress, should_stop)
    device = resolve_device(config.device)
    torch.manual_seed(config.seed)

    t0 = time.perf_counter()
    report("load", 0.0, "loading scene")
    source, input_bytes, name = _load(scene)
    source = source.to(device)
    report.timed("load", time.perf_counter() - t0)

    t0 = time.perf_counter()
    report("views", 0.0, "preparing views")
    background = torch.zeros(3, device=device)
    if images is not None:
        views: ViewSet = dataset_views(images, config.resolution, background, device, max_test=config.eval_views)
        reference_psnr, _ = evaluate(source, views.test, background)
        floor = reference_psnr - config.psnr_budget
    else:
        views = self_supervised_views(
            source, config.train_views, config.eval_views, config.resolution, background, seed=config.seed
        )
        reference_psnr, floor = math.inf, config.self_supervised_floor()
    report.timed("views", time.perf_counter() - t0)

    _, radius = scene_bounds(source.means.detach().cpu())
    meta = {
        "source": name,
        "input_gaussians": len(source),
        "sh_degree": source.sh_degree,
        "coordinate_convention": COORDINATE_CONVENTION,
    }
    max_levels = config.max_levels if config.use_mirrors else 0
    state, records = run_levels(
        source,
        views,
        config=replace(config, max_levels=max_levels),
        floor=mirror_floor(config, floor, reference_psnr),
        extent=radius,
        report=report,
        checkpoint=Path(checkpoint_dir) / "levels.pt" if checkpoint_dir is not None else None,
        fingerprint=_fingerprint(source, config, images),
        size_of=(lambda st: len(write_archive(st, meta))) if config.preset == "lossless" else None,
    )

    t0 = time.perf_counter()
    report("encode", 0.0, "encoding archive")

    def encode(levels: LevelState):  # noqa: ANN202 - stages.Coded
        return reduce_and_encode(
            LevelState.plain(source), levels, views.train, views.test, background, config=config, floor=floor,
            reference=reference_psnr, extent=radius, meta=meta, report=report,
        )  # fmt: skip

    coded = encode(state)
    plain_codec_bytes = None
    if state.normals.shape[0] and config.preset != "lossless":
        # Mirrors spend budget the quantiser could have spent: keep them only if the whole result is smaller than
        # the same stages without them (a scene is never made worse than the plain codec makes it).
        report("encode", 0.5, "encoding without mirrors, to compare")
        plain = encode(LevelState.plain(source))
        plain_codec_bytes = len(plain.archive)
        if plain_codec_bytes <= len(coded.archive):
            coded = plain
            for record in records:
                if record.accepted:
                    record.accepted = False
                    record.reason = "within budget, but the plain codec alone made a smaller archive"
    state, archive, baseline = coded.state, coded.archive, coded.baseline
    report.timed("encode", time.perf_counter() - t0)

    t0 = time.perf_counter()
    report("evaluate", 0.0, "evaluating the decoded scene")
    decoded = expand_archive(decode_archive(archive)).to(device)
    final_psnr, final_ssim = evaluate(decoded, views.test, background)
    report.timed("evaluate", time.perf_counter() - t0)

    out = {
        "input_bytes": input_bytes,
        "output_bytes": len(archive),
        "baseline_bytes": len(baseline),
        "ratio_to_ply": input_bytes / len(archive) if input_bytes else None,
        "ratio_to_baseline": len(baseline) / len(archive),
        "plain_codec_bytes": plain_codec_bytes,
        "gaussians": {"input": len(source), "stored": len(state.stored), "decoded": len(decoded)},
        "levels": [r.as_dict() for r in records],
        "stages": coded.stages,
        "codec": {"name": coded.codec, "preset": config.preset, "quantization": coded.quantization},
        "psnr": final_psnr,
        "ssim": final_ssim,
        "psnr_input": reference_psnr,
        "psnr_floor": floor,
        "psnr_reference": views.source,
        "seconds": report.seconds,
        "device": str(device),
        "config": asdict(config),
    }
    images: dict[str, bytes] = {}
    if config.pictures:
        from ..pictures import job_pictures

        t0 = time.perf_counter()
        report("evaluate", 0.5, "drawing pictures")
        images = job_pictures(source, decoded, views, records, _json_safe(out))
        report.timed("pictures", time.perf_counter() - t0)
    report("evaluate", 1.0, "done")
    return CompressResult(archive=archive, report=_json_safe(out), images=images)


def decompress(archive: bytes | str | Path) -> GaussianScene:
    """The decoded scene of a ``.symgs`` archive (bytes or a path)."""
    data = archive if isinstance(archive, bytes | bytearray) else Path(archive).read_bytes()
    return expand_archive(decode_archive(bytes(data)))


def _json_safe(value):  # noqa: ANN001, ANN202 - infinities become null so the report is strict JSON
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


__all__ = ["CompressResult", "LevelRecord", "compress", "decompress"]
