"""`symgs train`: a Gaussian scene trained from posed photographs on this machine, to compress with them after."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .parser import CliError, check_distinct, check_input, check_output, check_seed, error_text, write_output


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a scene (.ply) from posed photographs")
    p.add_argument("photos", type=Path, help="posed photographs: a NeRF-Synthetic, instant-ngp or COLMAP folder")
    p.add_argument("-o", "--output", type=Path, required=True, help="scene to write (.ply)")
    p.add_argument("--iterations", type=int, help="Adam steps in all (default: 3000 on the CPU, 30000 on CUDA)")
    p.add_argument("--resolution", type=int,
                   help="longest side of the photographs in training, pixels (default: 256 on the CPU, the "
                        "photographs' own on CUDA)")  # fmt: skip
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="cuda: 3DGS's schedule with gsplat; cpu: a reduced one (auto: cuda where gsplat runs)")
    p.add_argument("--strategy", choices=["default", "mcmc"], help="CUDA: gsplat's densification (default: default)")
    p.add_argument("--seed", type=int)
    p.add_argument("--quiet", action="store_true", help="no progress (a bar on a terminal, else plain lines)")
    p.set_defaults(func=_train)


def _device(choice: str) -> str:
    """The device ``choice`` trains on: CUDA where asked, or where ``auto`` finds it with gsplat."""
    import torch

    from symgs_core.render._gsplat import gsplat_importable

    runs = torch.cuda.is_available() and gsplat_importable()
    if choice == "cuda" and not runs:
        missing = "gsplat (pip install 'symgs[gpu]')" if torch.cuda.is_available() else "a CUDA device"
        raise CliError(f"--device cuda needs {missing}; --device cpu trains on the CPU")
    return "cuda" if choice == "cuda" or (choice == "auto" and runs) else "cpu"


def _train(args: argparse.Namespace) -> int:
    from rich.console import Console

    from symgs_core.bench.capture import RESOLUTION, TrainSettings, held_out_psnr, train
    from symgs_core.datasets import DatasetError, dataset_frames
    from symgs_core.ply import ply_bytes

    from .local_progress import LocalProgress

    check_input("photographs folder", args.photos, folder=True)
    check_output("-o", args.output)
    check_distinct({"photographs folder": args.photos, "-o": args.output})
    if args.output.suffix.lower() != ".ply":
        raise CliError(f"-o {args.output}: the scene is written as a .ply file")
    check_seed("--seed", args.seed)
    device = _device(args.device)
    if args.strategy is not None and device == "cpu":
        raise CliError("--strategy chooses gsplat's densification, on CUDA; the CPU schedule grows its own way")
    try:
        settings = TrainSettings.for_device(device, iterations=args.iterations, resolution=args.resolution,  # type: ignore[arg-type]
                                            strategy=args.strategy, seed=args.seed)  # fmt: skip
    except ValueError as exc:
        raise CliError(str(exc).replace("iterations", "--iterations").replace("resolution", "--resolution")) from None
    try:
        dataset_frames(args.photos, "train")
    except DatasetError as exc:
        raise CliError(f"cannot read photographs {args.photos}: {error_text(exc)}") from None
    start = time.perf_counter()
    with LocalProgress(Console(stderr=True), quiet=args.quiet, command="train") as progress:
        try:
            scene = train(args.photos, settings, progress=progress)
        except ValueError as exc:  # DatasetError: a photograph that cannot be read, a lens too strong to undo
            raise CliError(error_text(exc)) from None
    seconds = time.perf_counter() - start
    write_output("-o", args.output, ply_bytes(scene))
    resolution = f"{settings.resolution or RESOLUTION} px" if settings.resolution or device == "cpu" else "full size"
    try:
        psnr, count = held_out_psnr(scene, args.photos, settings.resolution)
        held_out = f"; PSNR {psnr:.2f} dB on {count} held-out photographs"
    except DatasetError:  # a set whose every photograph trains: nothing held out to score
        held_out = ""
    print(f"{args.output}: {len(scene):,} Gaussians, SH degree {scene.sh_degree}, trained on {device} in "
          f"{seconds:.0f} s ({settings.iterations} steps at {resolution}){held_out}")  # fmt: skip
    return 0
