"""The first two stages of a job: the scene checked and on the job's device (``load``), then its three camera sets,
the backdrop every render is drawn on and the floor the decisions hold (``views``)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from ..ply_header import PlyError
from ..scene import GaussianScene
from ..views import ViewSet, check_photographs, dataset_views, evaluate, photographed_backdrop, self_supervised_views
from .job import Job, grown

BACKDROP_SAME = 2 / 255  # a backdrop this close to the job's background is that background, in 8-bit photographs


@dataclass(frozen=True)
class Loaded:
    """The input scene, checked and on the job's device, with the file's size and name (0 and "scene" for a scene
    given in memory)."""

    source: GaussianScene
    input_bytes: int
    name: str


@dataclass(frozen=True)
class Viewed(Loaded):
    """The camera sets (``views.background`` [3] is what every render of the job is drawn on); ``reference``: the
    input's own fitting PSNR (+inf against renders of it, finite against photographs); ``floor``: the fitting PSNR
    every decision holds."""

    views: ViewSet
    reference: float
    floor: float


def load(scene: GaussianScene | str | Path, job: Job) -> Loaded:
    t0 = time.perf_counter()
    job.reporter("load", 0.0, "loading scene")
    if isinstance(scene, GaussianScene):  # a file's values are checked as it is read; a scene in memory, here alike
        from ..ply import checked_scene

        source, input_bytes, name = checked_scene(scene, "scene")[0], 0, "scene"
    else:
        from ..ply import load_scene

        path = Path(scene)
        source, input_bytes, name = load_scene(path), path.stat().st_size, path.name
    if not len(source):
        raise PlyError("empty_scene", f"{name}: the scene has no Gaussians, there is nothing to compress")
    loaded = Loaded(source.to(job.device), input_bytes, name)
    job.reporter.timed("load", time.perf_counter() - t0)
    return loaded


def views(loaded: Loaded, job: Job) -> Viewed:
    t0 = time.perf_counter()
    job.reporter("views", 0.0, "preparing views")
    config, source = job.config, loaded.source
    background = source.means.new_zeros(3)
    if job.images is not None:
        sets = dataset_views(job.images, source, fit=config.fit_views, eval=config.eval_views,
                             resolution=config.eval_resolution, background=background)  # fmt: skip
        backdrop = photographed_backdrop(sets.fit)
        if backdrop is not None and float((backdrop.to(background) - background).abs().max()) > BACKDROP_SAME:
            # Every render of the job (training, fitting, evaluation) draws the upload on the photographs' backdrop.
            sets = sets.on(backdrop.to(background.device))
        own = evaluate(source, sets.fit, sets.background, with_ssim=False)
        check_photographs(own, sets.fit)
        reference = own.worst
        floor = reference - config.budget
    else:
        sets = self_supervised_views(
            source, train=config.train_views, fit=config.fit_views, eval=config.eval_views,
            resolution=config.resolution, eval_resolution=config.eval_resolution, background=background,
            seed=config.seed,
        )  # fmt: skip
        reference, floor = math.inf, config.self_supervised_floor()
    viewed = grown(loaded, Viewed, views=sets, reference=reference, floor=floor)
    job.reporter.timed("views", time.perf_counter() - t0)
    return viewed
