"""Quantisation alone: one common factor on the preset's steps against the fitted steps, and the SH palette's section.

For each scene and floor (PSNR against renders of the input on the fitting cameras, as the pipeline fits), no
mirrors, pruning or SH reduction; rotations in their canonical frames (``codec.frames``) and SH palette entries
weighted by their renders (``stages.with_sh_weights``), as the pipeline quantises them: ``budget.fit_quantization``
from ``QuantSteps()`` (one factor for every step), then ``budget.fit_steps`` (balanced steps, common factor, one
attribute at a time, SH per coefficient or as a palette). Prints a table of each archive's bytes, its PSNR on the
fitting cameras and on the evaluation cameras (which fitted nothing), and its bytes per section. ``--palette-sizes``
also codes each scene's higher SH bands alone, per coefficient and as palettes of those sizes, on the same steps,
with the RMS error of each.

    python benchmarks/bench_steps.py ../shared/data/padilla_captures_cc_by/plant_113k_sh0.ply --floors 60.36
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

# Waiting OpenMP threads must sleep, not spin, on a shared machine (see symgs_core/__init__.py); before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from symgs_core.codec import read_header  # noqa: E402
from symgs_core.codec.frames import canonical_frames  # noqa: E402
from symgs_core.codec.palette import ShPaletteCodec  # noqa: E402
from symgs_core.codec.quantize import ShRestCodec  # noqa: E402
from symgs_core.codec.steps import QuantSteps  # noqa: E402
from symgs_core.pipeline import decompress  # noqa: E402
from symgs_core.pipeline.budget import extent_of, fit_quantization, fit_steps  # noqa: E402
from symgs_core.pipeline.encode import with_sh_weights, write_archive  # noqa: E402
from symgs_core.pipeline.state import LevelState  # noqa: E402
from symgs_core.ply import load_scene  # noqa: E402
from symgs_core.views import evaluate, self_supervised_views  # noqa: E402


def _row(scene: str, floor: float, name: str, state: LevelState, fit, views, seconds: float) -> str:  # noqa: ANN001
    """A table line: the archive of ``fit`` (a QuantFit), its PSNR on the fitting cameras it was fitted on and on
    the evaluation cameras, which fitted nothing."""
    archive = write_archive(state, {}, fit.steps.archive_codec(extent_of(state.stored), "bench-steps"))
    sections = ", ".join(f"{s['name']} {s['length']:,}" for s in read_header(archive)["sections"])
    palette = f"{fit.steps.sh_palette:,}" if fit.steps.sh_palette else "-"
    held = evaluate(decompress(archive), views.eval, views.background).psnr
    return (f"| {scene} | {floor:.2f} | {name} | {len(archive):,} | {fit.psnr:.2f} | {held:.2f} | {palette} | "
            f"{seconds:.0f} | {sections} |")  # fmt: skip


def palette_rows(scene: str, sh_rest: np.ndarray, sizes: list[int], steps: tuple[float, ...]) -> list[str]:
    """Table lines: bytes and RMS error of ``sh_rest`` [N, K, 3] per coefficient and as palettes of ``sizes``."""
    out = []
    for label, codec in [("per coefficient", ShRestCodec(steps))] + [
        (f"palette {size:,}", ShPaletteCodec(size, steps)) for size in sizes
    ]:
        coded = codec.encode(sh_rest)
        decoded = codec.decode(coded.payload, sh_rest.shape, coded.params, coded.raw_length)
        rms = float(np.sqrt(np.mean((decoded.astype(np.float64) - sh_rest) ** 2)))
        out.append(f"| {scene} | {label} | {len(coded.payload):,} | {rms:.4f} |")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--floors", required=True, help="comma-separated floor (dB) per scene, or one for all")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--train-views", type=int, default=16)
    parser.add_argument("--fit-views", type=int, default=8)
    parser.add_argument("--eval-views", type=int, default=8)
    parser.add_argument("--palette-sizes", default="", help="comma-separated palette sizes for the SH section alone")
    parser.add_argument("--palette-step-factor", type=float, default=3.0, help="SH steps: QuantSteps().sh times this")
    args = parser.parse_args()
    floors = [float(f) for f in args.floors.split(",")]
    floors = floors * len(args.scenes) if len(floors) == 1 else floors
    if len(floors) != len(args.scenes):
        parser.error(f"{len(args.scenes)} scenes but {len(floors)} floors")
    sizes = [int(s) for s in args.palette_sizes.split(",") if s]
    print("| scene | floor (dB) | steps | bytes | PSNR, fitting cameras | PSNR, evaluation cameras | SH palette | "
          "seconds | bytes per section |")  # fmt: skip
    print("|---|---:|---|---:|---:|---:|---:|---:|---|")
    palettes = []
    for path, floor in zip(args.scenes, floors):
        scene = load_scene(path)
        views = self_supervised_views(scene, train=args.train_views, fit=args.fit_views, eval=args.eval_views,
                                      resolution=args.resolution, eval_resolution=args.resolution,
                                      background=torch.zeros(3))  # fmt: skip
        fitting = list(views.fit)
        state = LevelState.plain(canonical_frames(scene))
        t0 = time.perf_counter()
        start = with_sh_weights(QuantSteps(), state, views.train)
        common = fit_quantization(state, fitting, views.background, floor=floor, start=start,
                                  psnr_before=math.inf)  # fmt: skip
        print(_row(path.name, floor, "one common factor", state, common, views, time.perf_counter() - t0), flush=True)
        t0 = time.perf_counter()
        fitted = fit_steps(state, fitting, views.background, floor=floor, start=start, psnr_before=math.inf)
        print(_row(path.name, floor, "fitted steps", state, fitted, views, time.perf_counter() - t0), flush=True)
        if sizes and scene.sh_degree:
            steps = QuantSteps().scaled(args.palette_step_factor).sh
            palettes += palette_rows(path.name, scene.sh_rest.numpy(), sizes, steps)
    if palettes:
        print()
        print(f"| scene | higher SH bands coded (steps QuantSteps().sh x {args.palette_step_factor:g}) | bytes | "
              "RMS error |")  # fmt: skip
        print("|---|---|---:|---:|")
        print("\n".join(palettes))


if __name__ == "__main__":
    main()
