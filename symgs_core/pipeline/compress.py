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
from ..codec import decode_archive, expand_archive, section_bytes
from ..codec.steps import QuantSteps
from ..config import PRESETS, CompressConfig
from ..devices import resolve_device
from ..ply_header import PlyError
from ..progress import Cancelled, ProgressEvent, ProgressFn, StopFn
from ..report import Cameras, GaussianCounts, Report, SectionBytes
from ..scene import GaussianScene
from ..views import check_photographs, dataset_views, evaluate, photographed_backdrop, self_supervised_views
from .encode import Fitted, fit_codec, fitted_baseline, fixed_codec, rate_model, stages
from .levels import level_notes, run_levels
from .state import LevelState

BACKDROP_SAME = 2 / 255  # a backdrop this close to the job's background is that background, in 8-bit photographs

# Share of the job's progress bar each stage takes; the mirror levels share theirs.
_STAGES = {
    "load": (0.0, 0.02),
    "views": (0.02, 0.06),
    "codec": (0.06, 0.45),
    "levels": (0.45, 0.88),
    "encode": (0.88, 0.93),
    "evaluate": (0.93, 1.0),
}


@dataclass
class CompressResult:
    archive: bytes
    report: Report
    images: dict[str, bytes] = field(default_factory=dict)


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
    if images is not None:  # the dataset's contents, not where it lies: a job resumed on another host matches
        root = Path(images)
        for file in sorted(p for p in (root.rglob("*") if root.is_dir() else [root]) if p.is_file()):
            h.update(str(file.relative_to(root) if root.is_dir() else file.name).encode())
            with file.open("rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
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

    ``config`` defaults to ``CompressConfig.for_preset()``, the default preset. Decisions hold the budget's floor on
    the fitting cameras; the report scores the evaluation cameras, which fitted nothing. With ``checkpoint_dir``
    every level decision is saved there and a rerun with the same inputs resumes after it.
    """
    config = config or CompressConfig.for_preset()
    if not isinstance(config, CompressConfig):
        raise TypeError(f"config must be a CompressConfig, e.g. CompressConfig.for_preset('small'), got {config!r}")
    report = _Reporter(progress, should_stop)
    device = resolve_device(config.device)
    torch.manual_seed(config.seed)

    t0 = time.perf_counter()
    report("load", 0.0, "loading scene")
    source, input_bytes, name = _load(scene)
    if isinstance(scene, GaussianScene):  # a file's values are checked as it is read; a scene in memory, here alike
        from ..ply import checked_scene

        source = checked_scene(source, name)[0]
    if not len(source):
        raise PlyError("empty_scene", f"{name}: the scene has no Gaussians, there is nothing to compress")
    source = source.to(device)
    report.timed("load", time.perf_counter() - t0)

    t0 = time.perf_counter()
    report("views", 0.0, "preparing views")
    background = torch.zeros(3, device=device)
    if images is not None:
        views = dataset_views(images, source, fit=config.fit_views, eval=config.eval_views,
                              resolution=config.eval_resolution, background=background)  # fmt: skip
        backdrop = photographed_backdrop(views.fit)
        if backdrop is not None and float((backdrop.to(background) - background).abs().max()) > BACKDROP_SAME:
            # Every render of the job (training, fitting, evaluation) draws the upload on the photographs' backdrop.
            background = backdrop.to(device)
            views = views.on(background)
        own = evaluate(source, views.fit, background, with_ssim=False)
        check_photographs(own, views.fit)
        reference = own.worst
        floor = reference - config.budget
    else:
        views = self_supervised_views(
            source, train=config.train_views, fit=config.fit_views, eval=config.eval_views,
            resolution=config.resolution, eval_resolution=config.eval_resolution, background=background,
            seed=config.seed,
        )  # fmt: skip
        reference, floor = math.inf, config.self_supervised_floor()
    report.timed("views", time.perf_counter() - t0)

    _, radius = scene_bounds(source.means.detach().cpu(), source.scales)
    # What the archive carries besides the scene; the same job gives the same bytes whichever door it came by.
    meta = {"input_gaussians": len(source), "sh_degree": source.sh_degree,
            "coordinate_convention": COORDINATE_CONVENTION}  # fmt: skip
    spec = PRESETS[config.preset]
    start = QuantSteps().scaled(spec.step_scale) if config.quantized else None
    fits: dict[int, Fitted] = {}

    def fit(state: LevelState, psnr: float, progress=None) -> Fitted:  # noqa: ANN001 - encode.FitProgress
        """The state's archive at the floor, remembered for the state the levels end on."""
        if start is not None and not spec.fitted:
            fits[id(state)] = fixed_codec(state, views.fit, background, steps=start, meta=meta, name=config.preset)
            return fits[id(state)]
        fits[id(state)] = fit_codec(state, views.fit, background, floor=floor, psnr_before=psnr, start=start,
                                    meta=meta, name=config.preset, should_stop=report.should_stop,
                                    progress=progress)  # fmt: skip
        return fits[id(state)]

    t0 = time.perf_counter()
    report("codec", 0.0, "fitting the plain codec")
    plain_state = LevelState.plain(source)
    plain = fit(plain_state, reference, progress=lambda within, message: report("codec", within, message))
    report.timed("codec", time.perf_counter() - t0)
    # Levels are judged by fitted archives: a preset that fits nothing keeps none.
    max_levels = config.max_levels if config.use_mirrors and spec.fitted else 0
    t0 = time.perf_counter()
    state, psnr, records = run_levels(
        source, views, config=replace(config, max_levels=max_levels), floor=floor, reference=reference,
        extent=radius, judge=lambda st, p: len(fit(st, p).archive), plain_bytes=len(plain.archive),
        rate=rate_model(plain, floor) if plain.rd is not None else None,
        steps=plain.steps, report=report,
        checkpoint=Path(checkpoint_dir) / "levels.pt" if checkpoint_dir is not None else None,
        fingerprint=_fingerprint(source, config, images) if checkpoint_dir is not None else "",
    )  # fmt: skip
    report.timed("levels", time.perf_counter() - t0)
    if not state.normals.shape[0]:  # no level kept: the result is the plain codec's archive, already fitted
        state = plain_state

    t0 = time.perf_counter()
    report("encode", 0.5, "encoding archive")
    fitted = plain if state is plain_state else fits.get(id(state)) or fit(state, psnr)
    archive = fitted.archive
    baseline = fitted_baseline(plain_state, fitted, meta)
    stage_reports = stages(plain_state, state, fitted, reference=reference, mirrored_psnr=psnr, meta=meta,
                           seconds=report.seconds, baseline=baseline)  # fmt: skip
    report.timed("encode", time.perf_counter() - t0)

    t0 = time.perf_counter()
    report("evaluate", 0.0, "evaluating the decoded scene")
    decoded = expand_archive(decode_archive(archive)).to(device)
    fidelity = evaluate(decoded, views.eval, background)
    fitting = evaluate(decoded, views.fit, background)
    psnr_input = evaluate(source, views.eval, background, with_ssim=False).worst if images is not None else math.inf
    report.timed("evaluate", time.perf_counter() - t0)

    result = Report(
        scene=name,
        input_bytes=input_bytes,
        output_bytes=len(archive),
        baseline_bytes=len(baseline),
        plain_codec_bytes=len(plain.archive) if state is not plain_state else None,
        ratio_to_ply=input_bytes / len(archive) if input_bytes else None,
        ratio_to_baseline=len(baseline) / len(archive),
        gaussians=GaussianCounts(len(source), len(fitted.state.stored), len(decoded)),
        levels=tuple(records),
        stages=tuple(stage_reports),
        codec=fitted.codec,
        sections=tuple(SectionBytes(name, size) for name, size in section_bytes(archive)),
        fidelity=fidelity,
        fitting=fitting,
        psnr_input=psnr_input,
        psnr_floor=floor,
        cameras=Cameras(*views.sets, disjoint=True, background=tuple(background.tolist())),
        seconds=dict(report.seconds),
        device=str(device),
        config=config,
        notes=level_notes(records, len(source), photographs=images is not None),
    )
    images_out: dict[str, bytes] = {}
    if config.pictures:
        from ..pictures import job_pictures

        t0 = time.perf_counter()
        report("evaluate", 0.5, "drawing pictures")
        images_out = job_pictures(source, decoded, views, result)
        report.timed("pictures", time.perf_counter() - t0)
        result = replace(result, seconds=dict(report.seconds))
    report("evaluate", 1.0, "done")
    return CompressResult(archive=archive, report=result, images=images_out)


def decompress(archive: bytes | bytearray | memoryview | str | Path) -> GaussianScene:
    """The decoded scene of a ``.symgs`` archive (its bytes or a path)."""
    data = archive if isinstance(archive, bytes | bytearray | memoryview) else Path(archive).read_bytes()
    return expand_archive(decode_archive(bytes(data)))


__all__ = ["CompressResult", "compress", "decompress"]
