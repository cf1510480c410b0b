"""`symgs detect`: find the mirror planes of a scene and how much of it each explains."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from .parser import CliError, check_input, error_text


def register(subparsers: argparse._SubParsersAction) -> None:
    detect = subparsers.add_parser(
        "detect",
        help="find mirror planes in a scene",
        description="Find the reflective symmetries of a scene, most dominant first. Each mirror is the plane "
        "n.x = offset (in the scene's own coordinates) with its votes, the Gaussians it keeps and reflects (left), "
        "those it drops (right) and its coverage, (left + right) / the Gaussians searched at its level. Level l "
        "searches what level l - 1 keeps. The time per step is printed.",
    )
    detect.add_argument("scene", type=Path, help="scene .ply (graphdeco layout, SH degree 0..3)")
    detect.add_argument(
        "--images",
        type=Path,
        help="the scene's posed photographs (NeRF-Synthetic or COLMAP folder): what their cameras look at is also "
        "searched on its own, as a job with them does (an object among its surroundings)",
    )
    detect.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    detect.add_argument(
        "--max-mirrors", type=int, default=4, metavar="K", help="mirror levels to search (default %(default)s)"
    )
    detect.add_argument(
        "--min-coverage", type=float, metavar="C", help="smallest coverage reported, 0..1 (default: the library's)"
    )
    detect.set_defaults(func=run_detect)


def run_detect(args: argparse.Namespace) -> int:
    import torch

    from symgs_core.cameras import focus
    from symgs_core.datasets import DatasetError, dataset_frames
    from symgs_core.detect import DetectConfig, detect
    from symgs_core.ply import PlyError, load_scene

    if args.max_mirrors < 0:
        raise CliError(f"--max-mirrors must be >= 0, got {args.max_mirrors}")
    overrides: dict[str, Any] = {"max_mirrors": args.max_mirrors}
    if args.min_coverage is not None:
        overrides["min_coverage"] = args.min_coverage
    try:
        config = DetectConfig(**overrides)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    check_input("scene file", args.scene)
    t0 = time.perf_counter()
    try:
        scene = load_scene(args.scene)
    except PlyError as exc:
        raise CliError(f"cannot read {args.scene}: {error_text(exc)}") from None
    aimed = None
    if args.images is not None:
        check_input("images folder", args.images, folder=True)
        try:
            aimed = focus([frame.camera for frame in dataset_frames(args.images, "train")])
        except DatasetError as exc:
            raise CliError(f"cannot read {args.images}: {error_text(exc)}") from None
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    with torch.no_grad():
        mirrors = detect(scene, config, focus=aimed)
    detect_s = time.perf_counter() - t0

    steps: dict[str, float] = {}
    for mirror in mirrors:
        for step, seconds in mirror.timings.items():
            steps[step] = steps.get(step, 0.0) + seconds
    summaries = [m.summary() for m in mirrors]
    report = {
        "scene": str(args.scene),
        "gaussians": len(scene),
        "focus": None if aimed is None else {"centre": aimed.centre.tolist(), "radius": aimed.radius},
        "mirrors": summaries,
        "timings": {"load": load_s, "detect": detect_s, **steps},
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"{args.scene}: {len(scene):,} Gaussians, {len(mirrors)} mirror(s) in {detect_s:.2f} s (load {load_s:.2f} s)")
    if args.images is not None:
        print("  the photographs' cameras look at " + ("no one point" if aimed is None else
              f"({', '.join(f'{v:.4g}' for v in aimed.centre.tolist())}), radius {aimed.radius:.4g}"))  # fmt: skip
    for m in summaries:
        n = ", ".join(f"{v:+.4f}" for v in m["normal"])
        print(
            f"  level {m['level']}: normal ({n}) offset {m['offset']:+.5g}  votes {m['votes']}  "
            f"left {m['left']:,}  right {m['right']:,}  out {m['out']:,}  coverage {m['coverage']:.3f}"
        )
        print("           " + "  ".join(f"{step} {seconds:.3f}s" for step, seconds in m["timings"].items()))
    if not mirrors:
        print("  no mirror explains enough of the scene")
    return 0
