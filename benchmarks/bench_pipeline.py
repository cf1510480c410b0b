"""End-to-end compression of synthetic and real scenes (self-supervised): levels, counts, bytes, fidelity, time.

    python benchmarks/bench_pipeline.py --synthetic global nested local asymmetric --n 20000
    python benchmarks/bench_pipeline.py --scenes ../shared/data/playbot_cc_by_sa3d/playbot_lod2_125k_sh2.ply

Prints a Markdown table; ``--json FILE`` also writes every report. "baseline" is the same codec on the input alone;
"plain codec" (quantised presets, when a level was accepted) the whole pipeline without mirrors, which the result
never exceeds.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def _db(value: float | None) -> str:
    return "lossless" if value is None else f"{value:.2f}"


def _row(name: str, report: dict, wall: float) -> str:
    """One table line from a report's JSON (``Report.as_json``: null PSNRs are lossless)."""
    levels = [lv for lv in report["levels"] if lv["accepted"]]
    g, fidelity = report["gaussians"], report["fidelity"]
    tried = " / ".join(
        f"{_db(lv['psnr_before'])}->{_db(lv['psnr_after'])}{'' if lv['accepted'] else ' (rolled back)'}"
        for lv in report["levels"]
    )
    secs = ", ".join(f"{k} {v:.1f}" for k, v in report["seconds"].items())
    return (
        f"| {name} | {len(levels)} | {g['input']} | {g['stored']} | {g['input'] / g['stored']:.2f}x | "
        f"{report['baseline_bytes']} | {report.get('plain_codec_bytes') or '-'} | {report['output_bytes']} | "
        f"{report['ratio_to_baseline']:.2f}x | {_db(fidelity['psnr'])} | {_db(fidelity['psnr_object'])} | "
        f"{fidelity['ssim']:.4f} | {report['psnr_floor']:.1f} | {tried or '-'} | {secs} | {wall:.0f} |"
    )


def main() -> None:
    from symgs_core.config import CompressConfig
    from symgs_core.pipeline import compress
    from symgs_core.synthetic import synthetic_scene

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="*", default=[], type=Path)
    parser.add_argument("--synthetic", nargs="*", default=[], help="global | nested | local | asymmetric")
    parser.add_argument("--capture", default="independent", choices=["twins", "independent"])
    parser.add_argument(
        "--jitter",
        type=float,
        default=0.0,
        help="independent noise on every attribute but positions, so twins are not bit-identical",
    )
    parser.add_argument("--n", type=int, default=20000)
    parser.add_argument("--sh-degree", type=int, default=1)
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--max-levels", type=int, default=4)
    parser.add_argument("--resolution", type=int, default=192)
    parser.add_argument("--train-views", type=int, default=128)
    parser.add_argument("--eval-views", type=int, default=8)
    parser.add_argument("--psnr-budget", type=float, default=0.5)
    parser.add_argument("--preset", default="lossless", choices=["small", "balanced", "high", "lossless"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    config = CompressConfig.for_preset(
        args.preset,
        psnr_budget=args.psnr_budget,
        max_levels=args.max_levels,
        iterations=args.iterations,
        resolution=args.resolution,
        train_views=args.train_views,
        eval_views=args.eval_views,
        pictures=False,
        device="cpu",
    )
    gen = torch.Generator().manual_seed(0)

    def jittered(scene):  # noqa: ANN001, ANN202
        if not args.jitter:
            return scene
        noise = lambda t: t + args.jitter * torch.randn(t.shape, generator=gen)  # noqa: E731
        return scene.with_(
            scales=noise(scene.scales),
            opacities=noise(scene.opacities),
            sh_dc=noise(scene.sh_dc),
            sh_rest=noise(scene.sh_rest),
        )

    jobs = [
        (
            f"synthetic {k} ({args.capture}{f', jitter {args.jitter}' if args.jitter else ''}, n={args.n}, "
            f"SH {args.sh_degree})",
            jittered(synthetic_scene(k, n=args.n, seed=0, sh_degree=args.sh_degree, capture=args.capture).scene),
        )
        for k in args.synthetic
    ]
    jobs += [(p.name, p) for p in args.scenes]
    print(f"config: {config}")
    print()
    print(
        "| scene | levels | input | stored | fewer | baseline B | plain codec B | archive B | vs baseline | PSNR dB | "
        "object PSNR dB | SSIM | floor dB | per level PSNR before->after (fitting cameras) | seconds per stage | "
        "wall s |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|")
    reports = {}
    for name, scene in jobs:
        t0 = time.perf_counter()
        result = compress(scene, config=config)
        wall = time.perf_counter() - t0
        reports[name] = result.report.as_json()
        print(_row(name, reports[name], wall), flush=True)
    if args.json:
        args.json.write_text(json.dumps(reports, indent=2))


if __name__ == "__main__":
    main()
