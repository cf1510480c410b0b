"""Decoding speed: a 1,000,000-Gaussian quantised archive to a graphdeco `.ply`, as `symgs decompress` does it.

The scene is eight side-by-side copies of the real playbot capture (125k Gaussians, SH degree 2) when the shared
data is present, else a generated scene of the same size and degree, written as the pipeline writes it: rotations in
their canonical frames, positions along their grid's Morton curve, the higher SH bands as a palette of every distinct
row. Prints the median of ``--repeats`` runs of decode (archive -> scene) and write (scene -> PLY bytes), wall and
process CPU seconds, and the process's peak resident memory. ``--copies 80`` makes it 10M Gaussians; ``--detect``
then also searches the decoded scene's mirrors (``symgs detect``'s four levels) in the same process, so the peak
memory is that of decoding and detecting together.

    .venv/bin/python benchmarks/bench_decode.py --threads 2
    .venv/bin/python benchmarks/bench_decode.py --threads 2 --copies 80 --repeats 1 --detect
"""

from __future__ import annotations

import argparse
import resource
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


def copies_of_playbot(copies: int) -> tuple[GaussianScene, str]:
    if PLAYBOT.exists():
        from symgs_core.ply import load_scene

        base, what = load_scene(PLAYBOT), f"{copies} copies of playbot 125k (SH 2)"
    else:
        from symgs_core.synthetic import synthetic_scene

        base = synthetic_scene("global", n=125_000, seed=0, sh_degree=2).scene
        what = f"{copies} copies of a generated scene"
    row = 4 if copies <= 8 else 10
    shifts = [torch.tensor([3.0 * (i % row), 3.0 * (i // row), 0.0]) for i in range(copies)]
    return GaussianScene.cat([base.with_(means=base.means + shift) for shift in shifts]), what


def peak_mib() -> float:
    """This process's peak resident memory since the last ``reset_peak`` (VmHWM)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def reset_peak() -> None:
    """Start the peak over from the current resident memory (Linux: clear_refs 5 resets VmHWM)."""
    Path("/proc/self/clear_refs").write_text("5")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--factor", type=float, default=3.0, help="QuantSteps scale (balanced ends near 2-6)")
    parser.add_argument("--copies", type=int, default=8, help="copies of the 125k scene (8: 1M, 80: 10M)")
    parser.add_argument("--detect", action="store_true", help="then detect mirrors in the decoded scene")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene, what = copies_of_playbot(args.copies)
    extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
    steps = replace(QuantSteps().scaled(args.factor), sh_palette=palette_start(scene.sh_rest))
    codec = steps.archive_codec(extent, "bench-decode")
    data = write_archive(LevelState.plain(canonical_frames(scene)), {}, codec)
    del scene  # the peak below is decoding's (and detection's), not the source's
    setup_peak = peak_mib()
    timings: dict[str, list[float]] = {"decode": [], "write": [], "total": [], "cpu": []}
    for _ in range(args.repeats):
        decoded = ply = None  # the last repeat's scene and bytes are not held while the next decodes
        reset_peak()
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
          "PLY bytes (s) | total wall (s) | CPU (s) | peak RSS (MiB) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {what} | {len(decoded):,} | {len(data):,} | {len(data) / len(decoded):.2f} | {len(ply):,} | "
          f"{args.threads} | {medians['decode']:.2f} | {medians['write']:.2f} | {medians['total']:.2f} | "
          f"{medians['cpu']:.2f} | {peak_mib():,.0f} |")  # fmt: skip
    print()
    print(f"Medians of {args.repeats} runs; making the archive peaked at {setup_peak:,.0f} MiB.")
    if args.detect:
        from symgs_core.detect import DetectConfig, detect

        del ply
        t0 = time.perf_counter()
        with torch.no_grad():
            mirrors = detect(decoded, DetectConfig(max_mirrors=4))
        print()
        print(f"Then detection in the same process: {time.perf_counter() - t0:.1f} s, {len(mirrors)} mirror(s); "
              f"peak resident memory of the process {peak_mib():,.0f} MiB.")  # fmt: skip


if __name__ == "__main__":
    main()
