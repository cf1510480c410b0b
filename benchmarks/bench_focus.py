"""Where the photographs look: is there a mirror there for a job to find?

A job with photographs searches the ball its cameras look at on its own (``cameras.focus``), where an object stands
among its surroundings. For each capture (trained as ``bench_pipeline --captures`` trains it, read from ``--work``)
this prints that ball, what detection finds there with its default settings, and, beside it, the best plane of an
exhaustive search there: every normal of a half-sphere (``--directions``) at every offset across the ball (steps of
``OFFSET_STEP`` of its radius), each scored by the share of a sample of the ball's Gaussians a reflection matches (the
matcher detection uses), the best few refitted as detection refits its planes (closest points, the polish of the
matched share, closest points again) and the best of those matched in full. A mirror replaces at most the Gaussians
it matches on one side, so the bytes an archive could save by it are at most their share of the scene's Gaussians:
"most a mirror could save" is N / (N - dropped), with the larger of the two planes' dropped sides, the gain no
fine-tune could exceed. ``--generated``: the same for a generated symmetric object of 5,000 Gaussians standing on a
slab of 20 times as many (``symgs_core.bench.photos``), where the answer is known.

    python benchmarks/bench_focus.py --generated --captures ../shared/data/snowmiku_plush_capture_mit
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

OFFSET_STEP = 0.05  # of the ball's (robust) radius
REFIT = 8  # best sampled planes refitted and matched in full
GENERATED_N = 5000
GENERATED_SURROUNDINGS = 20.0


def best_plane(scene, directions: int) -> tuple[float, float, int, int]:  # noqa: ANN001 - GaussianScene
    """(coverage of the best plane, share random planes match, its left, its right) over ``scene``'s Gaussians."""
    from symgs_core.cameras import fibonacci_directions
    from symgs_core.detect import DetectConfig
    from symgs_core.detect.clusters import attributes
    from symgs_core.detect.frame import normalised_frame
    from symgs_core.detect.membership import Matcher
    from symgs_core.detect.pairs import distinct_axes

    config = DetectConfig()
    frame = normalised_frame(scene.means.float(), config.radius_quantile)
    assert frame is not None
    matcher = Matcher(frame.to_local(scene.means.float()), attributes(scene), distinct_axes(scene, config.axis_ratio),
                      tolerance=config.match_tolerance, attribute_weight=config.attribute_weight)  # fmt: skip
    normals = fibonacci_directions(2 * directions)
    normals = normals[normals[:, 0] >= 0]  # a plane and its flip are one plane
    offsets = np.arange(-0.5, 0.5 + 1e-9, OFFSET_STEP)
    scored = sorted(((matcher.sampled_share(n, float(g))[0], i, float(g)) for i, n in enumerate(normals)
                     for g in offsets), reverse=True)  # fmt: skip
    best = (0.0, 0, 0)
    for _, i, g in scored[:REFIT]:
        normal, offset = matcher.settle(normals[i], g, config.icp_iters)
        sides = matcher.sides(normal, offset)
        coverage = (sides.left.numel() + sides.right.numel()) / len(scene)
        best = max(best, (coverage, int(sides.left.numel()), int(sides.right.numel())))
    return best[0], matcher.chance_coverage(6, config.seed), best[1], best[2]


def row(name: str, scene, folder: Path, directions: int) -> str:  # noqa: ANN001 - GaussianScene
    from symgs_core.cameras import focus
    from symgs_core.datasets import dataset_frames
    from symgs_core.detect import DetectConfig, detect

    t0 = time.perf_counter()
    aimed = focus([frame.camera for frame in dataset_frames(folder, "train")])
    if aimed is None:
        return f"| {name} | {len(scene):,} | no one point | - | - | - | - | - |"
    held = aimed.holds(scene.means)
    found = detect(scene, DetectConfig(max_mirrors=1), focus=aimed)
    inside = [m for m in found if bool(torch.isin(m.left, held).float().mean() > 0.5)]
    detected = "none" if not inside else f"{inside[0].left.numel() + inside[0].right.numel():,} Gaussians matched"
    coverage, chance, left, right = best_plane(scene.select(held), directions)
    n = len(scene)
    dropped = max([right] + [m.right.numel() for m in inside])
    return (f"| {name} | {n:,} | {aimed.radius:.3g} ({held.numel():,}, {held.numel() / n:.0%}) | {detected} | "
            f"{coverage:.1%} ({chance:.1%}) | {left:,} / {right:,} | {n / (n - dropped):.3f}x | "
            f"{time.perf_counter() - t0:.0f} |")  # fmt: skip


def main() -> None:
    from symgs_core.bench.capture import cached_capture
    from symgs_core.bench.photos import photographed
    from symgs_core.ply import load_scene

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", nargs="*", default=[], type=Path, help="COLMAP or NeRF-Synthetic folders")
    parser.add_argument("--work", type=Path, default=Path("bench-out/pipeline-capture"),
                        help="where the captures' trained scenes are (trained there when absent)")
    parser.add_argument("--generated", action="store_true", help="first, a generated object among surroundings")
    parser.add_argument("--directions", type=int, default=400, help="normals of the exhaustive search")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print("| scene | Gaussians | photographs look at: radius (Gaussians inside) | detection there | best plane of an "
          "exhaustive search there: matched (random planes) | its left / right | most a mirror could save | s |")
    print("|---|---:|---|---|---|---|---:|---:|")
    with torch.no_grad():
        if args.generated:
            folder = args.work / "generated-on-a-slab"
            upload = photographed("global", folder, n=GENERATED_N, photos=64, tests=8, resolution=64, sh_degree=1,
                                  surroundings=GENERATED_SURROUNDINGS)  # fmt: skip
            name = f"generated global (independent halves), on a slab of {GENERATED_SURROUNDINGS:g}x its Gaussians"
            print(row(name, upload, folder, args.directions), flush=True)
        for folder in args.captures:
            ply = cached_capture(folder, args.work / folder.name, say=lambda m, f=folder: print(f"{f.name}: {m}"))
            print(row(f"{folder.name} (trained: {ply.name})", load_scene(ply), folder, args.directions), flush=True)


if __name__ == "__main__":
    main()
