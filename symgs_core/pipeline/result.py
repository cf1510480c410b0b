"""The last stages of a job: the archive kept and where its size went (``encode``), its decode scored on the
evaluation cameras, which fitted nothing (``evaluate``), and the report with the job's pictures (``report``)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

from ..codec import decode_archive, expand_archive, section_bytes
from ..report import Cameras, Fidelity, GaussianCounts, Report, SectionBytes, StageReport
from ..scene import GaussianScene
from ..views import evaluate as scored
from .encode import Fitted, fitted_baseline, stages
from .job import Job, grown
from .levels import Levelled, level_notes
from .state import LevelState


@dataclass
class CompressResult:
    """The archive, the report, the job's pictures by name, and the archive decoded (on the job's device), which is
    what every export of the job is written from: the archive is decoded once."""

    archive: bytes
    report: Report
    decoded: GaussianScene
    images: dict[str, bytes] = field(default_factory=dict)


@dataclass(frozen=True)
class Encoded(Levelled):
    """``fitted``: the archive kept (the plain codec's where no level was kept); ``baseline``: the codec alone on the
    input; ``stages``: where the size went."""

    fitted: Fitted
    baseline: bytes
    stages: tuple[StageReport, ...]

    @property
    def mirrored(self) -> bool:
        return bool(self.levels.state.normals.shape[0])


@dataclass(frozen=True)
class Evaluated(Encoded):
    """``decoded``: the archive decoded, on the job's device; ``fidelity`` and ``fitting``: its scores on the
    evaluation and fitting cameras; ``psnr_input``: the input's own on the evaluation cameras against photographs
    (+inf without)."""

    decoded: GaussianScene
    fidelity: Fidelity
    fitting: Fidelity
    psnr_input: float


def encode(levelled: Levelled, job: Job) -> Encoded:
    t0 = time.perf_counter()
    job.reporter("encode", 0.5, "encoding archive")
    plain_state, outcome, codec = LevelState.plain(levelled.source), levelled.levels, levelled.codec
    state = outcome.state if outcome.state.normals.shape[0] else plain_state
    if state is plain_state:
        fitted = levelled.plain
    else:  # a state resumed from a checkpoint was not judged in this run: judged now, as the levels judge
        fitted = outcome.fitted or replace(codec, floor=outcome.floor)(state, outcome.psnr)
    for judged in (levelled.plain, fitted):
        judged.release()
    baseline = fitted_baseline(plain_state, fitted, codec.meta)
    accounted = stages(plain_state, state, fitted, reference=levelled.reference, mirrored_psnr=outcome.psnr,
                       meta=codec.meta, seconds=job.reporter.seconds, baseline=baseline)  # fmt: skip
    job.reporter.timed("encode", time.perf_counter() - t0)
    return grown(levelled, Encoded, fitted=fitted, baseline=baseline, stages=tuple(accounted))


def evaluate(encoded: Encoded, job: Job) -> Evaluated:
    t0 = time.perf_counter()
    job.reporter("evaluate", 0.0, "evaluating the decoded scene")
    views = encoded.views
    decoded = expand_archive(decode_archive(encoded.fitted.archive)).to(encoded.source.device)
    fidelity = scored(decoded, views.eval, views.background)
    fitting = encoded.fitted.fitting  # rendered when the codec checked this archive
    if fitting is None:
        fitting = scored(decoded, views.fit, views.background)
    psnr_input = math.inf
    if job.photographs:
        psnr_input = scored(encoded.upload, views.eval, views.background, with_ssim=False).worst
    job.reporter.timed("evaluate", time.perf_counter() - t0)
    return grown(encoded, Evaluated, decoded=decoded, fidelity=fidelity, fitting=fitting, psnr_input=psnr_input)


def report(evaluated: Evaluated, job: Job) -> CompressResult:
    archive, fitted, outcome = evaluated.fitted.archive, evaluated.fitted, evaluated.levels
    source, views = evaluated.source, evaluated.views
    result = Report(
        scene=evaluated.name,
        input_bytes=evaluated.input_bytes,
        output_bytes=len(archive),
        baseline_bytes=len(evaluated.baseline),
        plain_codec_bytes=len(evaluated.plain.archive) if evaluated.mirrored else None,
        ratio_to_ply=evaluated.input_bytes / len(archive) if evaluated.input_bytes else None,
        ratio_to_baseline=len(evaluated.baseline) / len(archive),
        gaussians=GaussianCounts(len(source), len(fitted.state.stored), len(evaluated.decoded)),
        levels=tuple(outcome.records),
        stages=evaluated.stages,
        codec=fitted.codec,
        sections=tuple(SectionBytes(name, size) for name, size in section_bytes(archive)),
        fidelity=evaluated.fidelity,
        fitting=evaluated.fitting,
        psnr_input=evaluated.psnr_input,
        psnr_floor=evaluated.floor,
        cameras=Cameras(*views.sets, disjoint=True, background=tuple(views.background.tolist()),
                        photographs=views.read),
        seconds=dict(job.reporter.seconds),
        device=str(job.device),
        config=job.config,
        notes=level_notes(outcome.records, len(source), photographs=job.photographs),
        refinement=evaluated.refinement,
        psnr_mirror_floor=outcome.floor if outcome.records else None,
    )
    images: dict[str, bytes] = {}
    if job.config.pictures:
        from ..pictures import job_pictures

        t0 = time.perf_counter()
        job.reporter("evaluate", 0.5, "drawing pictures")
        images = job_pictures(evaluated.upload, evaluated.decoded, views, result, charts=job.charts)
        job.reporter.timed("pictures", time.perf_counter() - t0)
        result = replace(result, seconds=dict(job.reporter.seconds))
    job.reporter("evaluate", 1.0, "done")
    return CompressResult(archive=archive, report=result, images=images, decoded=evaluated.decoded)
