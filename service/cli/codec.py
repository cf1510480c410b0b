"""`symgs compress`, `decompress` and `evaluate`: the pipeline on local files, no server."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

from symgs_core.config import DEFAULT_PRESET, DEVICE_CHOICES, PRESET_NAMES, PRESETS
from symgs_core.export.formats import extensions

from .job_options import add_job_options, job_overrides
from .parser import (
    CliError,
    cannot_write,
    check_distinct,
    check_input,
    check_output,
    check_seed,
    error_text,
    write_output,
)  # fmt: skip

HALF_PLY = ".ply.zst"  # symgs_core.bench.half_ply.EXTENSION, named here without importing torch

if TYPE_CHECKING:
    from symgs_core.config import CompressConfig


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compress", help="compress a scene (.ply) into a .symgs archive")
    p.add_argument("scene", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, help="archive to write (.symgs)")
    p.add_argument("--images", type=Path, help="posed images (NeRF-Synthetic or COLMAP folder)")
    p.add_argument("--report", type=Path, help="write the JSON report here")
    p.add_argument("--pictures", type=Path, help="write the PNG pictures and charts (as a job's) into this folder")
    p.add_argument("--device", choices=DEVICE_CHOICES, default="auto")
    p.add_argument("--preset", choices=PRESET_NAMES, default=DEFAULT_PRESET,
                   help="; ".join(f"{name}: {spec.summary}" for name, spec in PRESETS.items()))
    # Left out, each setting takes the preset's value (symgs_core.config): the same job as over HTTP or Python.
    add_job_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress (a bar on a terminal, else plain lines)")
    p.set_defaults(func=_compress)

    d = sub.add_parser("decompress", help="decode a .symgs archive to a scene file (format by extension)")
    d.add_argument("archive", type=Path, help=f"a .symgs archive (or a {HALF_PLY} float16 PLY of `symgs bench`)")
    d.add_argument("-o", "--output", type=Path, required=True, help=f"output scene, by extension: {extensions()}")
    d.add_argument("--spz-version", type=int, choices=[2, 3, 4], default=3, help=".spz version to write (default 3)")
    d.set_defaults(func=_decompress)
    register_evaluate(sub)


def config_from_args(args: argparse.Namespace) -> CompressConfig:
    """The job's settings from ``symgs compress`` arguments: the preset's, then each option given."""
    from symgs_core.config import CompressConfig

    overrides = job_overrides(args)
    try:
        return CompressConfig.for_preset(args.preset, **overrides, device=args.device,
                                         pictures=args.pictures is not None)  # fmt: skip
    except ValueError as exc:
        raise CliError(str(exc)) from exc


def _compress(args: argparse.Namespace) -> int:
    from rich.console import Console

    from symgs_core.pipeline import compress

    from .local_progress import LocalProgress

    check_input("scene file", args.scene)
    if args.images is not None:
        check_input("images folder", args.images, folder=True)
    check_output("-o", args.output)
    check_output("--report", args.report)
    check_output("--pictures", args.pictures, folder=True)
    check_distinct({"scene": args.scene, "-o": args.output, "--report": args.report, "--pictures": args.pictures})
    config = config_from_args(args)
    with LocalProgress(Console(stderr=True), quiet=args.quiet) as progress:
        try:
            result = compress(args.scene, images=args.images, config=config, progress=progress)
        except ValueError as exc:  # PlyError, DatasetError and bad settings all say what is wrong
            raise CliError(error_text(exc)) from exc
    write_output("-o", args.output, result.archive)
    if args.report is not None:
        write_output("--report", args.report, json.dumps(result.report.as_json(), indent=2).encode())
    if args.pictures is not None:
        for name, png in result.images.items():
            write_output("--pictures", args.pictures / f"{name}.png", png)
    r = result.report
    ratio = f"{r.ratio_to_ply:.2f}x vs PLY, " if r.ratio_to_ply else ""
    db = lambda x: "lossless" if math.isinf(x) else f"{x:.2f} dB"  # noqa: E731
    print(
        f"{args.output}: {r.output_bytes} bytes ({ratio}{r.ratio_to_baseline:.2f}x vs baseline), "
        f"{len(r.accepted_levels)} mirror level(s), {r.gaussians.stored}/{r.gaussians.input} Gaussians stored; "
        f"on {r.cameras.evaluation.count} evaluation cameras against {r.cameras.evaluation.source}: "
        f"PSNR {db(r.fidelity.psnr)} (object {db(r.fidelity.psnr_object)}), SSIM {r.fidelity.ssim:.4f}"
    )
    if r.refinement is not None:
        print(f"upload fine-tuned on the photographs first: {r.refinement.reason}")
    for note in r.notes:
        print(f"note: {note}")
    return 0


def _decompress(args: argparse.Namespace) -> int:
    # The codec alone, not the pipeline: decoding needs no renderer, and skipping its imports saves a quarter second.
    from symgs_core.codec import decode_archive, expand_archive
    from symgs_core.export.formats import by_path

    check_input("archive", args.archive)
    try:
        fmt = by_path(args.output)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    check_output("-o", args.output)
    check_distinct({"archive": args.archive, "-o": args.output})
    try:
        if args.archive.name.lower().endswith(HALF_PLY):  # the benchmarks' float16 PLY peer
            from symgs_core.bench.half_ply import read_half_ply

            scene = read_half_ply(args.archive.read_bytes())
        else:
            scene = expand_archive(decode_archive(args.archive.read_bytes()))
    except ValueError as exc:  # ArchiveError, HalfPlyError
        raise CliError(f"{args.archive}: {error_text(exc)}") from exc
    unbundled = fmt.folder_entry is not None and args.output.name.lower() == fmt.folder_entry
    try:
        if unbundled:  # several files in a folder: written in place
            args.output.parent.mkdir(parents=True, exist_ok=True)
            fmt.save(scene, args.output, version=args.spz_version)
        else:
            write_output("-o", args.output, fmt.write(scene, version=args.spz_version))
    except ValueError as exc:  # a scene the format cannot hold (e.g. positions beyond .spz's fixed point)
        raise CliError(f"{args.output}: {error_text(exc)}") from exc
    except OSError as exc:  # a full disk, a folder gone
        raise cannot_write("-o", args.output, exc) from None
    version = f" v{args.spz_version}" if "version" in fmt.options else ""
    print(f"{args.output}: {fmt.title}{version}, {len(scene)} Gaussians, SH degree {scene.sh_degree}")
    return 0


def register_evaluate(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("evaluate", help="PSNR/SSIM of a decoded scene against renders of the original")
    e.add_argument("reference", type=Path, help="the uncompressed scene (.ply)")
    e.add_argument("candidate", type=Path, help=f"a .symgs archive or a decoded scene: {extensions()}")
    e.add_argument("--views", type=int, default=8, help="evaluation cameras around the scene, near and far")
    e.add_argument("--resolution", type=int, default=256)
    e.add_argument("--seed", type=int, default=0, help="another seed turns the camera rig: other cameras")
    e.add_argument("--json", action="store_true", help="print the figures as JSON")
    e.set_defaults(func=_evaluate)


def _evaluate(args: argparse.Namespace) -> int:
    import torch

    from symgs_core.config import CompressConfig
    from symgs_core.export import import_scene
    from symgs_core.pipeline import decompress
    from symgs_core.ply import load_scene
    from symgs_core.views import evaluate, self_supervised_views

    check_input("reference", args.reference)
    check_input("candidate", args.candidate)
    check_seed("--seed", args.seed)
    try:  # the bounds of compress's evaluation cameras
        CompressConfig(eval_views=args.views, eval_resolution=args.resolution)
    except ValueError as exc:
        raise CliError(str(exc).replace("eval_views", "--views").replace("eval_resolution", "--resolution")) from None
    try:
        reference = load_scene(args.reference)
        if not len(reference):
            raise CliError(f"empty_scene: {args.reference}: the reference has no Gaussians, nothing to compare with")
        is_archive = args.candidate.suffix.lower() == ".symgs"
        candidate = decompress(args.candidate) if is_archive else import_scene(args.candidate)
        views = self_supervised_views(
            reference, train=1, fit=1, eval=args.views, resolution=16, eval_resolution=args.resolution,
            background=torch.zeros(3), seed=args.seed,
        )  # fmt: skip
    except ValueError as exc:  # PlyError, ArchiveError, SpzError, ... all name the problem
        raise CliError(error_text(exc)) from exc
    fidelity = evaluate(candidate, views.eval, views.background)
    finite = lambda x: None if math.isinf(x) else x  # noqa: E731
    figures = {
        "reference": str(args.reference), "candidate": str(args.candidate), "bytes": args.candidate.stat().st_size,
        "gaussians": len(candidate), "psnr": finite(fidelity.psnr), "psnr_object": finite(fidelity.psnr_object),
        "ssim": fidelity.ssim, "views": args.views, "resolution": args.resolution, "seed": args.seed,
    }  # fmt: skip
    if args.json:
        print(json.dumps(figures))
    else:
        psnr = (
            "identical renders" if figures["psnr"] is None
            else f"PSNR {fidelity.psnr:.2f} dB (object {fidelity.psnr_object:.2f} dB)"
        )  # fmt: skip
        print(f"{args.candidate}: {figures['bytes']} bytes, {len(candidate)} Gaussians, {psnr}, "
              f"SSIM {fidelity.ssim:.4f} over {args.views} views at {args.resolution}px")  # fmt: skip
    return 0
