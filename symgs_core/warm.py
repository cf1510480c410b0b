"""Every compiled kernel built before the first job.

numba compiles detection's kernels and the CPU renderer's on first use and caches them on disk (beside their modules,
or in the user's cache directory where those are read-only). Without this, a fresh worker host or container spends
its first job compiling them: on one H200 host the first job's detection took 13.6 s and its levels 14.0 s, against
0.7 s and 2.7 s for the next job on the same host, with the cache filled (BENCHMARKS "On a GPU").

    python -m symgs_core.warm     # a worker image's build step; on a host, once after installing
"""

from __future__ import annotations

import sys
import time

# A job small enough to take seconds, large enough that detection finds the planted mirror and a level is fitted:
# every stage, and so every kernel, runs once.
WARM_JOB = {"iterations": 4, "train_views": 2, "fit_views": 2, "eval_views": 1, "resolution": 32,
            "eval_resolution": 32, "max_levels": 1, "device": "cpu", "pictures": False}  # fmt: skip


def warm() -> float:
    """Compress and decompress a small generated scene with a planted mirror on the CPU; the seconds it took."""
    from .config import CompressConfig
    from .detect import DetectConfig, detect
    from .pipeline import compress, decompress
    from .synthetic import synthetic_scene

    start = time.perf_counter()
    scene = synthetic_scene("global", n=1200, seed=3, sh_degree=3, noise=0.002).scene
    decompress(compress(scene, config=CompressConfig.for_preset("balanced", **WARM_JOB)).archive)
    detect(scene, DetectConfig(pairs_per_gaussian=0.5))  # large clusters' pairs sampled, as in scenes of millions
    return time.perf_counter() - start


def main() -> int:
    print(f"symgs kernels compiled and cached in {warm():.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
