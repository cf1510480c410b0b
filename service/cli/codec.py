"""`symgs compress`, `decompress` and `evaluate`: the pipeline on local files, no server."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from symgs_core.export.formats import extensions

from .parser import CliError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compress", help="compress a scene (.ply) into a .symgs archive")
    p.add_argument("scene", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, help="archive to write (.symgs)")
    p.add_argument("--images", type=Path, help="posed images (NeRF-Synthetic or COLMAP folder)")
    p.add_argument("--report", type=Path, help="write the JSON report here")
    p.add_argument("--pictures", type=Path, help="write the PNG pictures and charts (as a job's) into this folder")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    p.add_argument("--preset", choices=["small", "balanced", "high", "lossless"], default="balanced",
                   help="attribute codec and reductions (default balanced); lossless stores float32")
    p.add_argument("--psnr-budget", type=float, default=None,
                   help="dB of held-out PSNR all lossy stages may cost together (default: the preset's)")
    p.add_argument("--max-levels", type=int, default=4)
    p.add_argument("--iterations", type=int, default=200, help="optimisation steps per level")
    p.add_argument("--resolution", type=int, default=192, help="longest side of training/evaluation views")
    p.add_argument("--train-views", type=int, default=128)
    p.add_argument("--eval-views", type=int, default=8)
    p.add_argument("--no-mirrors", action="store_true", help="baseline: the codec alone")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_compress)

    d = sub.add_parser("decompress", help="decode a .symgs archive to a scene file (format by extension)")
    d.add_argument("archive", type=Path)
    d.add_argument("-o", "--output", type=Path, required=True, help=f"output scene, by extension: {extensions()}")
    d.add_argument("--spz-version", type=int, choices=[2, 3, 4], default=3, help=".spz version to write (default 3)")
    d.set_defaults(func=_decompress)
    register_evaluate(sub)


def _compress(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from symgs_core.config import PRESET_BUDGETS, CompressConfig
    from symgs_core.pipeline import compress

    if not args.scene.is_file():
        raise CliError(f"scene file not found: {args.scene}")
    if args.images is not None and not args.images.is_dir():
        raise CliError(f"images folder not found: {args.images}")
    try:
        config = CompressConfig(
            preset=args.preset,
            psnr_budget=PRESET_BUDGETS[args.preset] if args.psnr_budget is None else args.psnr_budget,
            max_levels=args.max_levels,
            iterations=args.iterations,
            resolution=args.resolution,
            train_views=args.train_views,
            eval_views=args.eval_views,
            device=args.device,
            use_mirrors=not args.no_mirrors,
            pictures=args.pictures is not None,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    console = Console(stderr=True)
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        console=console,
        disable=args.quiet,
    ) as bar:
        task = bar.add_task("compress", total=1.0)

        def on_progress(event) -> None:  # noqa: ANN001 - ProgressEvent
            bar.update(task, completed=event.fraction, description=f"{event.stage}: {event.message}"[:60])

        try:
            result = compress(args.scene, images=args.images, config=config, progress=on_progress)
        except ValueError as exc:  # PlyError, DatasetError and bad settings all say what is wrong
            raise CliError(str(exc)) from exc
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(result.archive)
    if args.report is not None:
        args.report.write_text(json.dumps(result.report, indent=2))
    if args.pictures is not None:
        args.pictures.mkdir(parents=True, exist_ok=True)
        for name, png in result.images.items():
            (args.pictures / f"{name}.png").write_bytes(png)
    r = result.report
    levels = [lv for lv in r["levels"] if lv["accepted"]]
    ratio = f"{r['ratio_to_ply']:.2f}x vs PLY, " if r["ratio_to_ply"] else ""
    psnr = "lossless" if r["psnr"] is None else f"{r['psnr']:.2f} dB"
    print(
        f"{args.output}: {r['output_bytes']} bytes ({ratio}{r['ratio_to_baseline']:.2f}x vs baseline), "
        f"{len(levels)} mirror level(s), {r['gaussians']['stored']}/{r['gaussians']['input']} Gaussians stored, "
        f"PSNR {psnr}, SSIM {r['ssim']:.4f} against {r['psnr_reference']}"
    )
    return 0


def _decompress(args: argparse.Namespace) -> int:
    # The codec alone, not the pipeline: decoding needs no renderer, and skipping its imports saves a quarter second.
    from symgs_core.codec import ArchiveError, decode_archive, expand_archive
    from symgs_core.export.formats import by_path

    if not args.archive.is_file():
        raise CliError(f"archive not found: {args.archive}")
    try:
        fmt = by_path(args.output)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    try:
        scene = expand_archive(decode_archive(args.archive.read_bytes()))
    except ArchiveError as exc:
        raise CliError(f"{args.archive}: {exc}") from exc
    try:
        data = fmt.write(scene, version=args.spz_version)
    except ValueError as exc:  # a scene the format cannot hold (e.g. positions beyond .spz's fixed point)
        raise CliError(f"{args.output}: {exc}") from exc
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(data)
    version = f" v{args.spz_version}" if "version" in fmt.options else ""
    print(f"{args.output}: {fmt.title}{version}, {len(scene)} Gaussians, SH degree {scene.sh_degree}")
    return 0


def register_evaluate(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("evaluate", help="PSNR/SSIM of a decoded scene against renders of the original")
    e.add_argument("reference", type=Path, help="the uncompressed scene (.ply)")
    e.add_argument("candidate", type=Path, help=f"a .symgs archive or a decoded scene: {extensions()}")
    e.add_argument("--views", type=int, default=8, help="held-out cameras around the scene")
    e.add_argument("--resolution", type=int, default=256)
    e.add_argument("--json", action="store_true", help="print the figures as JSON")
    e.set_defaults(func=_evaluate)


def _evaluate(args: argparse.Namespace) -> int:
    import torch

    from symgs_core.export import import_scene
    from symgs_core.pipeline import decompress
    from symgs_core.ply import load_scene
    from symgs_core.views import evaluate, self_supervised_views

    for path in (args.reference, args.candidate):
        if not path.is_file():
            raise CliError(f"file not found: {path}")
    try:
        reference = load_scene(args.reference)
        is_archive = args.candidate.suffix.lower() == ".symgs"
        candidate = decompress(args.candidate) if is_archive else import_scene(args.candidate)
        views = self_supervised_views(reference, 1, args.views, args.resolution, torch.zeros(3))
    except ValueError as exc:  # PlyError, ArchiveError, SpzError, ... all name the problem
        raise CliError(str(exc)) from exc
    value, ssim_value = evaluate(candidate, views.test, views.background)
    figures = {
        "reference": str(args.reference), "candidate": str(args.candidate), "bytes": args.candidate.stat().st_size,
        "gaussians": len(candidate), "psnr": None if value == float("inf") else value, "ssim": ssim_value,
        "views": args.views, "resolution": args.resolution,
    }  # fmt: skip
    if args.json:
        print(json.dumps(figures))
    else:
        psnr = "identical renders" if figures["psnr"] is None else f"PSNR {value:.2f} dB"
        print(f"{args.candidate}: {figures['bytes']} bytes, {len(candidate)} Gaussians, {psnr}, SSIM {ssim_value:.4f}"
              f" over {args.views} views at {args.resolution}px")
    return 0
