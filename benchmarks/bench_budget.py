"""A budget without cliffs: the archive's size and fidelity as ``--psnr-budget`` is swept at one preset.

    python benchmarks/bench_budget.py ../shared/data/kacytran_try_iter7000/point_cloud.ply --preset high

Each budget is one job (self-supervised, no mirror levels: the codec alone, as on an upload without photographs).
Prints one Markdown table: per scene and budget, the floor the budget sets on the fitting cameras, the archive's
bytes, how it stores its values (quantised, or float32 where no quantiser meets the floor), its PSNR on the
evaluation cameras (which fitted nothing), and the change from the next larger budget. The size should grow, and the
PSNR rise, step by step as the budget shrinks, with no jump to float32 while a finer quantiser can still meet the
floor.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

# Waiting OpenMP threads must sleep, not spin, on a shared machine (see symgs_core/__init__.py); before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

BUDGETS = (0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001)


def main() -> None:
    from symgs_core.config import PRESET_NAMES, CompressConfig
    from symgs_core.pipeline import compress

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", type=Path, nargs="+")
    parser.add_argument("--preset", default="high", choices=PRESET_NAMES)
    parser.add_argument("--budgets", default=",".join(map(str, BUDGETS)), help="dB, comma-separated")
    args = parser.parse_args()
    budgets = sorted((float(b) for b in args.budgets.split(",")), reverse=True)

    print("| scene | budget (dB) | floor, fitting cameras (dB) | bytes | x smaller than PLY | values "
          "| PSNR, evaluation cameras (dB) | bytes / previous | seconds |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---|---:|---:|---:|")
    for scene in args.scenes:
        previous: int | None = None
        for budget in budgets:
            config = CompressConfig.for_preset(args.preset, psnr_budget=budget, max_levels=0, pictures=False,
                                               device="cpu")  # fmt: skip
            t0 = time.perf_counter()
            report = compress(scene, config=config).report
            seconds = time.perf_counter() - t0
            size = report.output_bytes
            values = "float32" if report.codec.steps is None else "quantised"
            growth = f"{size / previous:.3f}" if previous else "-"
            psnr = report.fidelity.psnr
            floor = report.psnr_floor if report.psnr_floor is not None else math.inf
            print(f"| {report.scene} | {budget:g} | {floor:.2f} | {size:,} | {report.ratio_to_ply or 0:.1f} | "
                  f"{values} | {psnr:.2f} | {growth} | {seconds:.0f} |", flush=True)  # fmt: skip
            previous = size


if __name__ == "__main__":
    main()
