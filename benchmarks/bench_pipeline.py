"""Mirrors against the same preset without them: each scene compressed twice, bytes and evaluation PSNR side by side.

    python benchmarks/bench_pipeline.py --scenes ../shared/data/fox_cc0_mujoco_warp/fox.ply
    python benchmarks/bench_pipeline.py --synthetic global local --capture independent --n 20000
    python benchmarks/bench_pipeline.py --synthetic global --capture twins --noise 0 0.002 0.008 --clutter 0.3
    python benchmarks/bench_pipeline.py --synthetic global asymmetric --photos 64 --work bench-out/photos
    python benchmarks/bench_pipeline.py --captures ../shared/data/snowmiku_plush_capture_mit --work bench-out/captures

Every setting is the preset's (``CompressConfig.for_preset``) unless given. PSNR is on the evaluation cameras, which
fitted nothing: full frame and the object's own pixels. "gain" is the archive without mirrors over the archive with
them (the pipeline keeps a level only when it makes the archive smaller, so it is never below 1). Prints a Markdown
table; ``--json FILE`` also writes every report.

``--photos K``: the paper's protocol (``symgs_core.bench.photos``). Fidelity is measured against photographs of a
symmetric truth, not against renders of the upload (a sample of the same object whose mirrored half is an
independent reconstruction): K training photographs and 8 test photographs are written as a NeRF-Synthetic folder
under ``--work``, and both runs compress the upload with them: the fine-tune trains on photographs, decisions hold
the input's own PSNR on the fitting photographs minus the budget, and the test photographs are reported.

``--scenes PLY --images DIR``: a trained scene with the photographs it was trained from, one folder per scene.

``--captures DIR``: the same protocol on a real capture: a COLMAP folder of photographs with its structure-from-motion
points, or a NeRF-Synthetic folder (started from random points). A scene is first trained on its training split
(``symgs_core.bench.capture``; written to, and on later runs read from, ``--work``), then compressed with the
capture's photographs; its test split is reported and fitted nothing, neither the training nor the compression.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path

import torch

TEST_PHOTOS = 8


def _db(value: float) -> str:
    return "lossless" if math.isinf(value) else f"{value:.2f}"


def _outcome(level) -> str:  # noqa: ANN001 - symgs_core.report.LevelReport
    if level.accepted:
        return ""
    return " (not fine-tuned)" if level.iterations == 0 and level.psnr_after == level.psnr_before else " (rolled back)"


def _refined(report) -> str:  # noqa: ANN001 - symgs_core.report.Report
    """The upload's own fine-tune against the photographs: fitting PSNR, steps and the plain codec's bytes."""
    r = report.refinement
    if r is None:
        return "-"
    after = f"{r.bytes_after:,}" if r.bytes_after is not None else "not coded"
    return (f"{r.psnr_before:.2f}->{r.psnr_after:.2f} in {r.steps} steps; {r.bytes_before:,} -> {after} B, "
            f"{'kept' if r.kept else 'not kept'}")  # fmt: skip


def _row(name: str, on, off, wall_on: float, wall_off: float) -> str:  # noqa: ANN001 - symgs_core.report.Report
    levels = on.accepted_levels
    tried = " / ".join(f"{lv.psnr_before:.1f}->{lv.psnr_after:.1f}{_outcome(lv)}" for lv in on.levels)
    return (
        f"| {name} | {len(levels)} | {on.gaussians.input} | {on.gaussians.stored} | {off.output_bytes:,} | "
        f"{on.output_bytes:,} | {off.output_bytes / on.output_bytes:.3f}x | {_db(off.fidelity.psnr)} / "
        f"{_db(off.fidelity.psnr_object)} | {_db(on.fidelity.psnr)} / {_db(on.fidelity.psnr_object)} | "
        f"{_db(on.psnr_floor)} | {_refined(off)} | {tried or '-'} | {wall_off:.0f} | {wall_on:.0f} |"
    )


def main() -> None:
    from symgs_core.bench.capture import ITERATIONS, ROUNDS, TrainSettings, cached_capture
    from symgs_core.config import PRESET_NAMES, CompressConfig
    from symgs_core.pipeline import compress
    from symgs_core.synthetic import synthetic_scene

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="*", default=[], type=Path)
    parser.add_argument("--images", nargs="*", default=[], type=Path,
                        help="each --scenes entry's posed photographs (NeRF-Synthetic or COLMAP folder), in order")
    parser.add_argument("--synthetic", nargs="*", default=[], help="global | nested | local | asymmetric")
    parser.add_argument("--capture", default="independent", choices=["twins", "independent"])
    parser.add_argument("--noise", nargs="*", type=float, default=[0.0],
                        help="positional noise of the generated objects (fraction of their size), one row each")
    parser.add_argument("--clutter", type=float, default=0.0, help="asymmetric Gaussians per object Gaussian")
    parser.add_argument("--surroundings", type=float, default=0.0,
                        help="with --photos: the object stands on a slab of this many asymmetric Gaussians per "
                             "object Gaussian, photographed from above it")
    parser.add_argument("--n", type=int, default=20000)
    parser.add_argument("--sh-degree", type=int, default=1)
    parser.add_argument("--preset", default=None, choices=PRESET_NAMES, help="default: the default preset")
    parser.add_argument("--iterations", type=int)
    parser.add_argument("--max-levels", type=int)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--photos", type=int, default=0,
                        help="photograph a symmetric truth of each generated scene, this many training photographs, "
                             "and fit and score against them (0: renders of the input)")
    parser.add_argument("--photo-resolution", type=int, default=256)
    parser.add_argument("--work", type=Path, default=Path("bench-out/photos"),
                        help="where --photos writes them and --captures its trained scenes")
    parser.add_argument("--captures", nargs="*", default=[], type=Path,
                        help="COLMAP (with sparse points) or NeRF-Synthetic folders")
    parser.add_argument("--train-rounds", type=int, default=ROUNDS, help="rounds of training a capture's scene")
    parser.add_argument("--train-iterations", type=int, default=ITERATIONS, help="Adam steps per round")
    parser.add_argument("--tune-gain", type=float,
                        help="dB a fine-tune is taken to recover at most (default: the pipeline's); a large value "
                             "fine-tunes every membership the gate would judge without one, to see what it leaves out")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.tune_gain is not None:
        from symgs_core.pipeline import levels

        levels.TUNE_GAIN = args.tune_gain  # read by the level loop at each decision
    torch.set_num_threads(args.threads)
    config = CompressConfig.for_preset(args.preset, iterations=args.iterations, max_levels=args.max_levels,
                                       device="cpu", pictures=False)  # fmt: skip
    def label(kind: str, noise: float = 0.0) -> str:
        extra = (f", noise {noise:g}" if noise else "") + (f", clutter {args.clutter:g}" if args.clutter else "")
        extra += f", on a slab of {args.surroundings:g}x its Gaussians" if args.surroundings else ""
        return f"synthetic {kind} ({args.capture}, n={args.n}, SH {args.sh_degree}{extra})"

    if args.photos and (args.noise != [0.0] or args.clutter):
        parser.error("--noise and --clutter shape the scenes scored against their own renders, not --photos")
    if args.surroundings and not args.photos:
        parser.error("--surroundings goes with --photos")
    if args.photos:
        from symgs_core.bench.photos import photographed

        jobs = [(label(k), photographed(k, args.work / k, n=args.n, photos=args.photos, tests=TEST_PHOTOS,
                                        resolution=args.photo_resolution, sh_degree=args.sh_degree,
                                        capture=args.capture, surroundings=args.surroundings), args.work / k)
                for k in args.synthetic]  # fmt: skip
    else:
        jobs = [(label(k, noise), synthetic_scene(k, n=args.n, seed=0, sh_degree=args.sh_degree, capture=args.capture,
                                                  noise=noise, clutter=args.clutter).scene, None)
                for k in args.synthetic for noise in args.noise]  # fmt: skip
    if args.images and len(args.images) != len(args.scenes):
        parser.error(f"--images names {len(args.images)} folders for {len(args.scenes)} scenes")
    jobs += [(p.name, p, images) for p, images in zip(args.scenes, args.images or [None] * len(args.scenes))]
    training = TrainSettings(iterations=args.train_rounds * args.train_iterations, rounds=args.train_rounds)
    for folder in args.captures:
        ply = cached_capture(folder, args.work / folder.name, training,
                             say=lambda m, f=folder: print(f"{f.name}: {m}", flush=True))  # fmt: skip
        jobs.append((f"{folder.name} (trained: {ply.name})", ply, folder))
    print(f"config: {config}\n")
    print("| scene | levels | input | stored | no mirrors B | mirrors B | gain | PSNR dB without (full / object) | "
          "PSNR dB with (full / object) | floor dB | upload fine-tuned: fitting PSNR, plain codec | "
          "levels tried, fitting PSNR before->after | s without | s with |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---:|")
    reports = {}
    for name, scene, photos in jobs:
        runs = {}
        for mirrors in (False, True):
            t0 = time.perf_counter()
            report = compress(scene, images=photos, config=replace(config, use_mirrors=mirrors)).report
            runs[mirrors] = (report, time.perf_counter() - t0)
        (on, wall_on), (off, wall_off) = runs[True], runs[False]
        reports[name] = {"mirrors": on.as_json(), "no_mirrors": off.as_json()}
        if photos is not None:
            name = f"{name}; input {_db(on.psnr_input)} dB"
        print(_row(name, on, off, wall_on, wall_off), flush=True)
    if args.json:
        args.json.write_text(json.dumps(reports, indent=2))


if __name__ == "__main__":
    main()
