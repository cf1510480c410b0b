"""`symgs bench`: our presets with and without mirrors, a budget sweep, and the peers' formats, on size, fidelity and
time; writes bench.json, bench.md, charts and every output file (local, no server)."""

from __future__ import annotations

import argparse
from pathlib import Path

from symgs_core.config import DEVICE_CHOICES, PRESET_NAMES

from .job_options import add_job_options, job_overrides
from .parser import CliError, check_output, check_seed

# The job settings a bench takes; it varies the budget and the mirrors itself (--presets, --sweep, --mirrors).
BENCH_SETTINGS = ("max_levels", "iterations", "train_views", "fit_views", "eval_views", "resolution",
                  "eval_resolution", "seed")  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark presets, a budget sweep and the peers' formats: bench.json and charts")
    p.add_argument("scenes", type=Path, nargs="+", help="scenes (.ply)")
    p.add_argument("--out", type=Path, required=True, help="folder for bench.json, bench.md, charts/ and files/")
    p.add_argument("--presets", default=",".join(PRESET_NAMES), help="comma-separated presets (default: all)")
    p.add_argument("--mirrors", choices=["both", "on", "off"], default="both", help="runs with and/or without mirrors")
    p.add_argument("--sweep", type=int, default=8,
                   help="at most this many runs of ours at budgets aimed at the peers' PSNRs (0: none)")
    p.add_argument("--no-peers", action="store_true", help="no peers: our runs only")
    p.add_argument("--no-sog", action="store_true", help="leave out SOG (its k-means takes minutes on a CPU)")
    p.add_argument("--no-install", action="store_true", help="do not install splat-transform with npm when missing")
    p.add_argument("--peer-timeout", type=float, default=300.0, help="seconds per peer (writing and decoding back)")
    p.add_argument("--sog-timeout", type=float, default=900.0, help="seconds for SOG (writing and decoding back)")
    p.add_argument("--other-seed", type=int, default=1, help="seed of the second, independent evaluation rig")
    p.add_argument("--other-views", type=int, default=8, help="cameras of the second rig")
    p.add_argument("--trained", type=Path, nargs="*", default=[],
                   help="those of the scenes known to be as a trainer wrote them; the others are told by their values "
                   "(a field on a container's grid: decoded from one), and the two kinds are reported apart")
    # Left out, each setting takes the preset's value (symgs_core.config), as `symgs compress` does.
    add_job_options(p, BENCH_SETTINGS)
    p.add_argument("--device", choices=DEVICE_CHOICES, default="auto")
    p.set_defaults(func=_bench)


def _splat_transform(args: argparse.Namespace) -> tuple[str | None, str]:
    """The peer tool to run and, when there is none, why."""
    from symgs_core.bench import splat_transform

    if args.no_peers:
        return None, "peers not asked for"
    found = splat_transform.find()
    if found or args.no_install:
        return found, f"splat-transform {splat_transform.VERSION} is not installed (--no-install)"
    print(f"installing {splat_transform.PACKAGE} into {splat_transform.cache_folder()}", flush=True)
    try:
        return splat_transform.install(), ""
    except splat_transform.ToolError as exc:
        return None, str(exc)


def _bench(args: argparse.Namespace) -> int:
    from symgs_core.bench.peers import PEERS
    from symgs_core.bench.run import BenchSettings
    from symgs_core.bench.suite import run_bench
    from symgs_core.bench.tables import markdown

    presets = tuple(p.strip() for p in args.presets.split(",") if p.strip())
    unknown = [p for p in presets if p not in PRESET_NAMES]
    if unknown:
        raise CliError(f"unknown presets {unknown}; known: {', '.join(PRESET_NAMES)}")
    missing = [str(s) for s in args.scenes if not s.is_file()]
    if missing:
        raise CliError(f"scene files not found: {', '.join(missing)}")
    if args.sweep < 0 or args.other_views < 1 or args.peer_timeout <= 0 or args.sog_timeout <= 0:
        raise CliError("--sweep must be >= 0, --other-views >= 1, and the timeouts positive")
    check_seed("--other-seed", args.other_seed)
    check_output("--out", args.out, folder=True)
    known = set(args.trained)
    if not known <= set(args.scenes):
        raise CliError("--trained names scenes that are not among the scenes benched")
    trained = [scene in known for scene in args.scenes]
    overrides = {**job_overrides(args, BENCH_SETTINGS), "device": args.device}
    exe, why = _splat_transform(args)
    peers = () if args.no_peers else tuple(p for p in PEERS if not (args.no_sog and p.slow))
    settings = BenchSettings(
        presets=presets, mirrors={"both": (True, False), "on": (True,), "off": (False,)}[args.mirrors],
        overrides={k: v for k, v in overrides.items() if v is not None}, peers=peers, splat_transform=exe,
        unavailable=why, peer_timeout=args.peer_timeout, slow_timeout=args.sog_timeout, sweep=args.sweep,
        other_seed=args.other_seed, other_views=args.other_views,
    )  # fmt: skip
    try:
        settings.config("balanced")
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    try:
        doc = run_bench(args.scenes, args.out, settings, say=lambda m: print(m, flush=True), trained=trained)
    except ValueError as exc:  # PlyError and bad settings name the problem
        raise CliError(str(exc)) from exc
    from symgs_core.bench.rows import BenchRow

    print(markdown([BenchRow.from_json(r) for r in doc["rows"]]), end="")
    failing = doc["claims_failing_on_other_cameras"]
    for claim in failing:
        print(f"NOT CONFIRMED on other cameras: {claim['scene']}, smaller than {claim['peer']} "
              f"({claim['equal_psnr_ratio']:.2f}x at {claim['peer_psnr_db']:.2f} dB)")  # fmt: skip
    print(f"wrote {args.out / 'bench.json'}, {args.out / 'bench.md'}, charts in {args.out / 'charts'}; "
          f"{len(doc['claims'])} claims, {len(failing)} not confirmed on other cameras")  # fmt: skip
    return 0
