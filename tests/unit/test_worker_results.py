"""The files a finished job leaves: an export the scene cannot be written in is left out and named, the rest stand."""

from __future__ import annotations

import math
from pathlib import Path

from api_schemas.jobs import JobParams
from symgs_core.config import CompressConfig
from symgs_core.export.formats import EXPORTS
from symgs_core.pipeline import compress
from symgs_core.synthetic import synthetic_scene
from worker.runner import _write_results
from worker.storage import DirectoryStorage
from worker.store import JobRecord


def test_an_export_the_scene_does_not_fit_is_named_and_the_others_are_written(tmp_path: Path) -> None:
    scene = synthetic_scene("global", n=400, seed=3, sh_degree=0).scene
    tiny = scene.with_(means=scene.means * 1e-9, scales=scene.scales + math.log(1e-9))  # below .spz's fixed point
    storage = DirectoryStorage(tmp_path)
    job = "0" * 32
    record = JobRecord(id=job, owner="owner", params=JobParams(), queue="cpu", scene={})
    config = CompressConfig.for_preset("fast", fit_views=2, eval_views=2, eval_resolution=32, device="cpu",
                                       pictures=False)  # fmt: skip
    skipped = _write_results(storage, record, compress(tiny, config=config))
    written = set(storage.artifact_names(owner="owner", job_id=job))
    assert skipped.startswith("result.spz not written:") and "fixed point" in skipped
    assert "result.spz" not in written
    assert {"result.symgs", "report.json"} | {f.artifact for f in EXPORTS if f.artifact != "result.spz"} <= written


def test_a_finished_job_links_only_the_exports_it_has() -> None:
    from service.api.job_view import public_job

    scene = {"filename": "scene.ply", "bytes": 1, "gaussians": 1, "sh_degree": 0}
    written = ["result.symgs", *(f.artifact for f in EXPORTS if f.artifact != "result.spz")]
    done = JobRecord(id="1" * 32, owner="owner", params=JobParams(), queue="cpu", scene=scene, state="succeeded",
                     progress=1.0, artifacts=written, message="result.spz not written: ...")  # fmt: skip
    running = JobRecord(id="2" * 32, owner="owner", params=JobParams(), queue="cpu", scene=scene, state="running")
    assert {f.name for f in EXPORTS} - set(public_job(done).links.exports) == {"spz"}
    assert set(public_job(running).links.exports) == {f.name for f in EXPORTS}

