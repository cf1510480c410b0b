"""``python -m symgs_core.warm`` leaves nothing for a job to compile: a worker image runs it at build time so that no
job of a fresh container spends seconds in numba's compiler."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# Another scene than the warm-up's (size, SH degree, seed), a job with photographs off and pictures on, and a
# detection whose clusters are sampled: what a job of an upload runs.
JOB = """
from symgs_core.config import CompressConfig
from symgs_core.detect import DetectConfig, detect
from symgs_core.pipeline import compress, decompress
from symgs_core.synthetic import synthetic_scene

scene = synthetic_scene("global", n=3000, seed=11, sh_degree=1, noise=0.001, clutter=0.3).scene
config = CompressConfig.for_preset("small", iterations=4, train_views=2, fit_views=2, eval_views=1, resolution=40,
                                   eval_resolution=40, max_levels=2, device="cpu")
decompress(compress(scene, config=config).archive)
detect(scene, DetectConfig(pairs_per_gaussian=0.25))
"""


def _run(code: list[str], cache: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "NUMBA_DEBUG_CACHE": "1"}
    return subprocess.run([sys.executable, *code], capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)


def test_after_the_warm_up_a_job_compiles_no_kernel(tmp_path) -> None:
    warmed = _run(["-m", "symgs_core.warm"], tmp_path)
    assert warmed.returncode == 0, warmed.stderr[-2000:]
    assert "data saved" in warmed.stdout + warmed.stderr  # the cache was empty: the warm-up compiled into it
    job = _run(["-c", JOB], tmp_path)
    assert job.returncode == 0, job.stderr[-2000:]
    compiled = [line for line in (job.stdout + job.stderr).splitlines() if "data saved" in line]
    assert not compiled, "compiled by the job, not by the warm-up:\n" + "\n".join(compiled)
