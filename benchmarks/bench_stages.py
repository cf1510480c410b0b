"""What each stage of a compression job saved and cost, from its report: the mirror levels tried, then pruning,
SH reduction, quantisation and entropy coding (``Report.stages``), and the archive's fidelity on the evaluation
cameras.

    python benchmarks/bench_stages.py ../shared/data/playbot_cc_by_sa3d/playbot_lod2_125k_sh2.ply --preset balanced

Prints two Markdown tables: the stages (bytes before and after, PSNR on the fitting cameras after each, measured or
predicted) and the levels (PSNR before and after each fine-tune, on the fitting cameras, and the decision).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

# Waiting OpenMP threads must sleep, not spin, on a shared machine (see symgs_core/__init__.py); before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _db(value: float | None) -> str:
    return "lossless" if value is None or math.isinf(value) else f"{value:.2f}"


def main() -> None:
    from symgs_core.config import PRESET_NAMES, CompressConfig
    from symgs_core.pipeline import compress

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--preset", default="balanced", choices=PRESET_NAMES)
    parser.add_argument("--iterations", type=int)
    parser.add_argument("--max-levels", type=int)
    parser.add_argument("--train-views", type=int)
    parser.add_argument("--fit-views", type=int)
    parser.add_argument("--eval-views", type=int)
    parser.add_argument("--resolution", type=int)
    parser.add_argument("--eval-resolution", type=int)
    args = parser.parse_args()
    config = CompressConfig.for_preset(
        args.preset, iterations=args.iterations, max_levels=args.max_levels, train_views=args.train_views,
        fit_views=args.fit_views, eval_views=args.eval_views, resolution=args.resolution,
        eval_resolution=args.eval_resolution, pictures=False, device="cpu",
    )  # fmt: skip
    t0 = time.perf_counter()
    report = compress(args.scene, config=config).report
    wall = time.perf_counter() - t0

    print("| stage | bytes before | bytes after | saved | PSNR after, fitting cameras (dB) | seconds | note |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for s in report.stages:
        removed = f"{s.removed:,} removed" if s.removed is not None else ""
        predicted = "PSNR predicted by the sensitivity model" if s.predicted else ""
        note = "; ".join(x for x in (removed, predicted) if x) or "-"
        print(f"| {s.stage.replace('_', ' ')} | {s.bytes_before:,} | {s.bytes_after:,} | {s.saved_bytes:,} | "
              f"{_db(s.psnr_after)} | {s.seconds:.1f} | {note} |")  # fmt: skip
    print()
    f = report.fidelity
    print(f"Archive: {report.output_bytes:,} bytes ({report.ratio_to_ply or 0:.1f}x smaller than the PLY, "
          f"{report.ratio_to_baseline:.2f}x the codec alone); on {report.cameras.evaluation.count} evaluation cameras "
          f"{_db(f.psnr)} dB full frame, {_db(f.psnr_object)} dB on the object's pixels; floor "
          f"{_db(report.psnr_floor)} dB on the fitting cameras; {wall:.0f} s.")  # fmt: skip
    print()
    print("| level | coverage | PSNR before fine-tune (dB) | after (dB) | steps | stored after | archive bytes | kept "
          "| why |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|---:|---|---|")
    for lv in report.levels:
        archive = f"{lv.archive_bytes:,}" if lv.archive_bytes is not None else "-"
        print(f"| {lv.level} | {lv.coverage:.2f} | {_db(lv.psnr_before)} | {_db(lv.psnr_after)} | {lv.iterations} | "
              f"{lv.stored_after:,} | {archive} | {'yes' if lv.accepted else 'no'} | {lv.reason or '-'} |")  # fmt: skip
    if not report.levels:
        print("| - | - | - | - | - | - | - | - | no level tried |")

if __name__ == "__main__":
    main()
