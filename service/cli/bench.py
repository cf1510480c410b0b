"""`symgs bench`: presets with and without mirrors against the peers' formats, tables and charts (local, no server)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .parser import CliError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark presets and peers on scenes: CSV, Markdown and two PNG charts")
    p.add_argument("scenes", type=Path, nargs="+", help="scenes (.ply)")
    p.add_argument("--presets", default="small,balanced,high",
                   help="comma-separated presets (default all lossy; empty: only the peers and the matched run)")
    p.add_argument("--mirrors", choices=["both", "on", "off"], default="both", help="runs with and/or without mirrors")
    p.add_argument("--out", type=Path, default=Path("bench-out"), help="folder for bench.csv, bench.md and charts")
    p.add_argument("--no-peers", action="store_true", help="skip .spz, compressed PLY and SOG")
    p.add_argument("--no-match", action="store_true", help="skip the run matched to the .spz v3 PSNR")
    p.add_argument("--peer-cache", type=Path, help="keep and reuse the peers' results in this folder")
    p.add_argument("--peer-timeout", type=float, default=1800.0, help="seconds before a peer's run is given up")
    p.add_argument("--resolution", type=int, default=192)
    p.add_argument("--train-views", type=int, default=24)
    p.add_argument("--eval-views", type=int, default=8)
    p.add_argument("--iterations", type=int, default=50, help="optimisation steps per mirror level")
    p.add_argument("--max-levels", type=int, default=2)
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    p.set_defaults(func=_bench)


def _bench(args: argparse.Namespace) -> int:
    from symgs_core.bench import bench_scene, write_outputs
    from symgs_core.config import PRESETS, CompressConfig

    presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    unknown = [p for p in presets if p not in PRESETS]
    if unknown:
        raise CliError(f"unknown presets {unknown}; known: {', '.join(PRESETS)}")
    missing = [str(s) for s in args.scenes if not s.is_file()]
    if missing:
        raise CliError(f"scene files not found: {', '.join(missing)}")
    try:
        config = CompressConfig.for_preset(
            resolution=args.resolution, train_views=args.train_views, eval_views=args.eval_views,
            iterations=args.iterations, max_levels=args.max_levels, device=args.device, pictures=False,
        )  # fmt: skip
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    mirrors = {"both": (True, False), "on": (True,), "off": (False,)}[args.mirrors]
    rows = []
    for scene in args.scenes:
        try:
            rows += bench_scene(scene, presets=presets, config=config, mirrors=mirrors, peers=not args.no_peers,
                                match=not args.no_match, peer_cache=args.peer_cache, peer_timeout=args.peer_timeout,
                                progress=lambda m: print(m, flush=True))  # fmt: skip
        except ValueError as exc:
            raise CliError(f"{scene}: {exc}") from exc
    files = write_outputs(rows, args.out)
    print(files["markdown"].read_text(), end="")
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return 0
