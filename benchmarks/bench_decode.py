"""Decoding speed: a 1,000,000-Gaussian quantised archive to a graphdeco `.ply`, as `symgs decompress` does it.

The scene is eight side-by-side copies of the real playbot capture (125k Gaussians, SH degree 2) when the shared
data is present, else a generated scene of the same size and degree, written as the pipeline writes it: rotations in
their canonical frames, positions along their grid's Morton curve, the higher SH bands as a palette of every distinct
row. Prints the median of ``--repeats`` runs of decode (archive -> scene) and write (scene -> PLY bytes), wall and
process CPU seconds.

    .venv/bin/python benchmarks/bench_decode.py --threads 2
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from symgs_core.codec import QuantSteps
from symgs_core.codec.frames import canonical_frames
from symgs_core.pipeline import decompress
from symgs_core.pipeline.budget import palette_start
from symgs_core.pipeline.encode import write_archive
from symgs_core.pipeline.state import LevelState
from symgs_core.ply import ply_bytes
from symgs_core.scene import GaussianScene

PLAYBOT = Path(__file__).resolve().parents[1].parent / "shared/data/playbot_cc_by_sa3d/playbot_lod2_125k_sh2.ply"


def million() -> tuple[GaussianScene, str]:
    if PLAYBOT.exists():
        from symgs_core.ply import load_scene

        base, what = load_scene(PLAYBOT), "8 copies of playbot 125k (SH 2)"
    else:
        from symgs_core.synthetic import synthetic_scene

        base, what = synthetic_scene("global", n=125_000, seed=0, sh_degree=2).scene, "8 copies of a generated scene"
    copies = [base.with_(means=base.means + torch.tensor([3.0 * (i % 4), 3.0 * (i // 4), 0.0])) for i in range(8)]
    return GaussianScene.cat(copies), what


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--factor", type=float, default=3.0, help="QuantSteps scale (balanced ends near 2-6)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene, what = million()
    extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
    steps = replace(QuantSteps().scaled(args.factor), sh_palette=palette_start(scene.sh_rest))
    codec = steps.archive_codec(extent, "bench-decode")
    data = write_archive(LevelState.plain(canonical_frames(scene)), {}, codec)
    timings: dict[str, list[float]] = {"decode": [], "write": [], "total": [], "cpu": []}
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        decoded = decompress(data)
        t1 = time.perf_counter()
        ply = ply_bytes(decoded)
        t2, c2 = time.perf_counter(), time.process_time()
        timings["decode"].append(t1 - t0)
        timings["write"].append(t2 - t1)
        timings["total"].append(t2 - t0)
        timings["cpu"].append(c2 - c0)
    medians = {k: statistics.median(v) for k, v in timings.items()}
    print("| scene | Gaussians | archive bytes | bytes per Gaussian | PLY bytes | threads | decode (s) | "
          "PLY bytes (s) | total wall (s) | CPU (s) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {what} | {len(scene):,} | {len(data):,} | {len(data) / len(scene):.2f} | {len(ply):,} | {args.threads} | "
          f"{medians['decode']:.2f} | {medians['write']:.2f} | {medians['total']:.2f} | {medians['cpu']:.2f} |")
    print()
    print(f"Medians of {args.repeats} runs.")


if __name__ == "__main__":
    main()
