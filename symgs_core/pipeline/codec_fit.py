"""The codec stage: the plain scene's archive at the floor (``fit``), and the codec that makes it (``FloorCodec``),
which the level loop asks again for each level it judges."""

from __future__ import annotations

import time
from dataclasses import dataclass

from ..cameras import COORDINATE_CONVENTION
from ..codec.steps import QuantSteps
from ..progress import StopFn
from ..views import ViewSet
from .encode import FitProgress, Fitted, check_views, fit_codec, fixed_codec
from .job import Job, grown
from .prepare import Viewed
from .state import LevelState


@dataclass(frozen=True)
class FloorCodec:
    """A state's archive at the job's floor on the fitting views: written at the preset's steps as they are (a preset
    that fits nothing), or the smallest the floor allows (``encode.fit_codec``). ``start``: the preset's starting
    steps (None: float32). ``meta``: what the archive carries besides the scene, the same whichever door a job came
    by, so the same job gives the same bytes."""

    views: ViewSet
    floor: float
    start: QuantSteps | None
    fitted: bool
    meta: dict
    name: str
    should_stop: StopFn | None = None

    def __call__(self, state: LevelState, psnr: float, progress: FitProgress | None = None) -> Fitted:
        """``state``'s archive; ``psnr`` is its own fitting PSNR."""
        if self.start is not None and not self.fitted:
            return fixed_codec(state, self.views.fit, self.views.background, steps=self.start, meta=self.meta,
                               name=self.name)  # fmt: skip
        return fit_codec(state, self.views.fit, self.views.background, floor=self.floor, psnr_before=psnr,
                         start=self.start, meta=self.meta, name=self.name, check=check_views(self.views.train),
                         should_stop=self.should_stop, progress=progress)  # fmt: skip


@dataclass(frozen=True)
class CodecFitted(Viewed):
    """``plain``: the scene's archive without a mirror, made by ``codec``."""

    codec: FloorCodec
    plain: Fitted


def fit(viewed: Viewed, job: Job) -> CodecFitted:
    t0 = time.perf_counter()
    job.reporter("codec", 0.0, "fitting the plain codec")
    source, spec = viewed.source, job.preset
    meta = {"input_gaussians": len(source), "sh_degree": source.sh_degree,
            "coordinate_convention": COORDINATE_CONVENTION}  # fmt: skip
    codec = FloorCodec(
        viewed.views, viewed.floor, QuantSteps().scaled(spec.step_scale) if job.config.quantized else None,
        spec.fitted, meta, job.config.preset, job.reporter.should_stop,
    )
    plain = codec(LevelState.plain(source), viewed.reference,
                  progress=lambda within, message: job.reporter("codec", within, message))  # fmt: skip
    job.reporter.timed("codec", time.perf_counter() - t0)
    return grown(viewed, CodecFitted, codec=codec, plain=plain)
