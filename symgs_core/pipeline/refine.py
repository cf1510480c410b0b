"""Against photographs, the upload fine-tuned as a whole before any mirror is sought (``refine``).

A scene trained short of what its photographs allow (a trainer stopped early, at a lower resolution, or on fewer
photographs) gains fidelity on photographs it did not train on when it is fine-tuned further, and the codec spends
what it gains: the floor stays the upload's own fitting PSNR less the budget. The fine-tune runs in stretches, as a
mirror level's does, while each gains and, by the plain archive's rate model, the archive could still shrink
(``pace.Pace``); the fine-tuned scene is then coded and kept only where its archive is smaller than the upload's.
A scene trained to convergence gains nothing in its first stretch and is coded as it was uploaded. The mirror levels
then start from the scene kept, so mirrors are judged against the same plain codec, with or without them; where the
fine-tuned scene holds no mirror, the first is sought in the upload (``levels.LevelSearch.detect_from``), as the
fine-tune trains the halves apart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..cameras import scene_bounds
from ..report import Refinement
from ..scene import GaussianScene
from .checkpoint import load_refined, save_refined, scene_fingerprint
from .codec_fit import CodecFitted
from .encode import Fitted, rate_model
from .job import TUNE_SHARE, Job, grown
from .optimize import optimize_level
from .pace import MIN_GAIN_DB, Pace, Stretches
from .state import LevelState


@dataclass(frozen=True)
class Refined(CodecFitted):
    """``upload``: the scene as uploaded; ``source``, ``reference`` and ``plain`` are the scene the later stages
    code, its fitting PSNR and its plain archive (the fine-tuned scene's where that was kept); ``refinement``: what
    the fine-tune did (None: no photographs, or a preset that fits nothing)."""

    upload: GaussianScene
    refinement: Refinement | None


def refine(fitted: CodecFitted, job: Job) -> Refined:
    config, plain = job.config, fitted.plain
    if not job.photographs or plain.rd is None or config.iterations == 0:
        return grown(fitted, Refined, upload=fitted.source, refinement=None)
    checkpoint = None
    if job.checkpoint_dir is not None:
        checkpoint = (job.checkpoint_dir / "refined.pt", scene_fingerprint(fitted.source, job.settings_digest))
        resumed = load_refined(*checkpoint, fitted.source.device)
        if resumed is not None:
            scene, record = resumed
            judged = None if scene is None else fitted.codec(LevelState.plain(scene), record.psnr_after)
            return _going_on(fitted, scene, judged, record, job)
    t0 = time.perf_counter()
    tuned, psnr, steps = _fine_tune(fitted, job)
    gained, judged = psnr - fitted.reference, None
    if gained < MIN_GAIN_DB:
        kept, after = False, None
        reason = f"{steps} steps gained {gained:+.2f} dB on the fitting photographs: the upload is coded as it came"
    else:
        encoding = job.reporter.part("refine", TUNE_SHARE, 1.0, "encoding the fine-tuned scene to compare")
        judged = fitted.codec(LevelState.plain(tuned), psnr, encoding)
        after = len(judged.archive)
        kept = after < len(plain.archive)
        reason = (f"{steps} steps gained {gained:+.2f} dB on the fitting photographs; its archive is {after:,} "
                  f"bytes against the upload's {len(plain.archive):,}: "
                  f"{'kept' if kept else 'the upload is coded as it came'}")  # fmt: skip
    record = Refinement(steps, fitted.reference, psnr, len(plain.archive), after, kept, reason,
                        time.perf_counter() - t0)  # fmt: skip
    scene = tuned if kept else None
    if checkpoint is not None:
        save_refined(*checkpoint, scene, record)
    return _going_on(fitted, scene, judged if kept else None, record, job)


def _going_on(fitted: CodecFitted, scene: GaussianScene | None, judged: Fitted | None, record: Refinement,
              job: Job) -> Refined:  # fmt: skip
    """``fitted`` going on from ``scene`` (None: the upload), whose plain archive is ``judged``."""
    job.reporter.timed("refine", record.seconds)
    job.reporter("refine", 1.0, record.reason)
    if scene is None or judged is None:
        return grown(fitted, Refined, upload=fitted.source, refinement=record)
    moved = replace(fitted, source=scene.to(fitted.source.device), reference=record.psnr_after, plain=judged)
    return grown(moved, Refined, upload=fitted.source, refinement=record)


def _fine_tune(fitted: CodecFitted, job: Job) -> tuple[GaussianScene, float, int]:
    """The whole scene fine-tuned on the training photographs in stretches of a quarter of ``iterations``, while a
    stretch gains and ``Pace`` says the plain archive could still shrink; the scene, its fitting PSNR and the steps
    run."""
    config, views, plain = job.config, fitted.views, fitted.plain
    pace = Pace(fitted.floor, rate_model(plain, fitted.floor), fitted.reference, len(plain.archive),
                len(plain.archive))  # fmt: skip
    stretches = Stretches(views, fitted.reference, config.iterations, pace)

    def on_step(step: int, loss: Tensor) -> None:
        if step % 10 == 0:
            job.reporter("refine", TUNE_SHARE * step / max(config.iterations, 1),
                         f"fine-tuning the upload on its photographs: step {step}/{config.iterations} "
                         f"loss {float(loss):.4f}")  # fmt: skip

    _, radius = scene_bounds(fitted.source.means.detach().cpu(), fitted.source.scales)
    torch.manual_seed(config.seed)
    tuned, steps = optimize_level(
        LevelState.plain(fitted.source), views.train, views.background, iterations=config.iterations,
        extent=radius, steps=plain.steps, seed=config.seed, check_every=stretches.every, keep_going=stretches,
        should_stop=job.reporter.should_stop, on_step=on_step,
    )  # fmt: skip
    return tuned.stored, stretches.fitting_psnr(tuned, steps), steps
