"""Speed and accuracy of mirror detection, against exhaustive all-pairs voting, and on the real scenes.

Synthetic cases: a symmetric object of many parts (planted mirror, 30% asymmetric clutter, positional noise, flat and
varied colours, so cluster sizes are heavy-tailed), at 100k, 1M and 10M object Gaussians. Each size runs in a fresh
process (so "peak MiB" is that process's peak resident memory, scene included) and reports the median of the runs:
the time to the refined plane (frame, clustering, pair sampling, voting, peak, refinement) and the time of the
membership (KD-tree correspondence), with the plane's error against the planted one.

``--all-pairs N`` also votes every pair inside every cluster (the paper's exhaustive scheme; chunked, the same
clusters and accumulator) in the N-Gaussian case, in the same process, and compares the peaks. ``--real DIR`` runs
detection on every ``.ply`` under DIR. ``--cli N`` times the whole command, ``symgs detect FILE.ply --json`` (its
default four levels), on the synthetic case of N object Gaussians written as a PLY (``--cli-scene`` adds given PLY
files): each run a fresh process, with the process's wall time, the command's own load and detect times, its CPU time
and its peak resident memory. Prints Markdown; ``--json`` keeps the raw figures.

    python benchmarks/bench_detect.py --sizes 100000,1000000,10000000 --all-pairs 1000000 --real ../shared/data
    python benchmarks/bench_detect.py --sizes "" --cli 1000000,10000000 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# Waiting OpenMP threads must sleep, not spin, on a shared machine (see symgs_core/__init__.py); before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from symgs_core.detect import DetectConfig, detect  # noqa: E402
from symgs_core.detect.clusters import attributes, cluster  # noqa: E402
from symgs_core.detect.frame import normalised_frame  # noqa: E402
from symgs_core.detect.grid import GridSpec, smooth  # noqa: E402
from symgs_core.detect.pairs import enumerate_pairs  # noqa: E402
from symgs_core.mirror import Plane  # noqa: E402
from symgs_core.synthetic import Pose, synthetic_scene  # noqa: E402

PLANE_STEPS = ("frame", "cluster", "pairs", "vote", "peak", "refine")
SYMGS = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]
ALL_PAIRS_CHUNK = 1 << 22


def benchmark_scene(n: int):  # noqa: ANN201 - SyntheticScene
    return synthetic_scene("global", n=n, seed=0, parts=40, clutter=0.3, noise=0.002, pose=Pose.random(0))


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cluster_stats(scene) -> dict:  # noqa: ANN001
    config = DetectConfig()
    groups = cluster(attributes(scene), config.colour_bins, config.opacity_bins, config.scale_bins)
    sizes = groups.sizes.double()
    return {
        "clusters": int(sizes.numel()),
        "largest": int(sizes.max()),
        "median_size": float(sizes.median()),
        "all_pairs": float((sizes * (sizes - 1) / 2).sum()),
        "pairs_in_largest_1pct": float(
            (sizes.sort(descending=True).values[: max(1, sizes.numel() // 100)] ** 2).sum() / (sizes**2).sum()
        ),
    }


def all_pairs_peak(scene, config: DetectConfig) -> dict:  # noqa: ANN001
    """Vote every pair inside every cluster into the same accumulator; the smoothed peak's plane."""
    t0 = time.perf_counter()
    frame = normalised_frame(scene.means.float(), config.radius_quantile)
    x = frame.to_local(scene.means.float())
    groups = cluster(attributes(scene), config.colour_bins, config.opacity_bins, config.scale_bins)
    spec = GridSpec(config.angle_res, config.offset_res, 1.0)
    grid = torch.zeros(spec.shape).view(-1)
    keep = groups.sizes >= 2
    sizes, starts = groups.sizes[keep], groups.starts[keep]
    by_size = torch.argsort(sizes)
    sizes, starts = sizes[by_size], starts[by_size]
    pairs = sizes * (sizes - 1) // 2
    total = 0

    def vote(a: torch.Tensor, b: torch.Tensor) -> None:
        i, j = groups.order[a], groups.order[b]
        diff = x[i] - x[j]
        length = diff.norm(dim=1)
        ok = length > 1e-6
        normal = diff[ok] / length[ok, None]
        offset = (normal * (x[i[ok]] + x[j[ok]])).sum(dim=1) / 2
        cells, _ = spec.cells(normal, offset)
        grid.index_add_(0, cells, torch.ones(cells.numel()))

    k = 0
    while k < sizes.numel():
        if int(pairs[k]) <= ALL_PAIRS_CHUNK:  # a batch of whole clusters
            cum = torch.cumsum(pairs[k:], 0)
            stop = k + max(1, int((cum <= ALL_PAIRS_CHUNK).sum()))
            a, b = enumerate_pairs(starts[k:stop], sizes[k:stop])
            vote(a, b)
            total += a.numel()
            k = stop
            continue
        n, s = int(sizes[k]), int(starts[k])  # a large cluster, a block of rows at a time
        r = 0
        while r < n - 1:
            rows = max(1, min(n - 1 - r, ALL_PAIRS_CHUNK // max(n - 1 - r, 1)))
            rank = torch.arange(r, r + rows)
            partners = n - 1 - rank
            a = torch.repeat_interleave(s + rank, partners)
            first = torch.cumsum(partners, 0) - partners
            b = a + 1 + (torch.arange(a.numel()) - torch.repeat_interleave(first, partners))
            vote(a, b)
            total += a.numel()
            r += rows
        k += 1
    smoothed = smooth(grid.view(spec.shape))
    flat = int(torch.argmax(smoothed))
    coord = spec.unravel(torch.tensor([flat]))[0]
    normal, offset = spec.plane(coord)
    world_n, world_g = frame.plane_to_world(normal.float(), offset)
    return {
        "pairs": total,
        "seconds": time.perf_counter() - t0,
        "peak_votes": int(smoothed.view(-1)[flat]),
        "plane": Plane.from_tensor(world_n, world_g),
        "cell_radians": config.angle_res,
        "cell_offset": config.offset_res * frame.radius,
    }


def worker(n: int, repeats: int, with_all_pairs: bool) -> dict:
    t0 = time.perf_counter()
    s = benchmark_scene(n)
    made = time.perf_counter() - t0
    scene, planted = s.scene, s.planes[0]
    frame = normalised_frame(scene.means, 0.99)
    base = peak_mib()
    runs = []
    config = DetectConfig(max_mirrors=1)
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        mirrors = detect(scene, config)
        runs.append((time.perf_counter() - t0, mirrors, time.process_time() - c0))
    m = runs[0][1][0]
    med = lambda f: statistics.median(f(r) for r in runs)  # noqa: E731
    out = {
        "gaussians": len(scene),
        "make_seconds": made,
        "repeats": repeats,
        "total": med(lambda r: r[0]),
        "cpu_seconds": med(lambda r: r[2]),
        "plane_seconds": med(lambda r: sum(r[1][0].timings.get(k, 0.0) for k in PLANE_STEPS)),
        "membership_seconds": med(lambda r: r[1][0].timings.get("membership", 0.0)),
        "steps": {k: med(lambda r, k=k: r[1][0].timings.get(k, 0.0)) for k in m.timings},
        "angle_deg": m.plane.angle_deg(planted),
        "offset_pct_radius": 100 * m.plane.gap_at(planted, frame.centre) / frame.radius,
        "coverage": m.coverage,
        "votes": m.votes,
        "peak_mib": peak_mib(),
        "scene_mib": base,
        "clusters": cluster_stats(scene),
        "threads": torch.get_num_threads(),
    }
    if with_all_pairs:
        ap = all_pairs_peak(scene, config)
        out["all_pairs"] = {
            "pairs": ap["pairs"],
            "seconds": ap["seconds"],
            "peak_votes": ap["peak_votes"],
            "angle_to_ours_deg": ap["plane"].angle_deg(m.plane),
            "offset_to_ours_pct_radius": 100 * ap["plane"].gap_at(m.plane, frame.centre) / frame.radius,
            "angle_to_planted_deg": ap["plane"].angle_deg(planted),
            "cell_deg": math.degrees(ap["cell_radians"]),
            "cell_pct_radius": 100 * ap["cell_offset"] / frame.radius,
        }
    return out


def real_scene(path: Path, root: Path, max_mirrors: int) -> dict:
    from symgs_core.ply import PlyError, load_scene

    try:
        scene = load_scene(path)
    except PlyError as exc:
        return {"file": str(path.relative_to(root)), "error": str(exc)}
    t0 = time.perf_counter()
    mirrors = detect(scene, DetectConfig(max_mirrors=max_mirrors))
    seconds = time.perf_counter() - t0
    frame = normalised_frame(scene.means, 0.99)
    rows = []
    for m in mirrors:
        s = m.summary()
        s["offset_from_median_pct_radius"] = (
            100 * (float(torch.tensor(m.normal, dtype=torch.float64) @ frame.centre.double()) - m.offset) / frame.radius
        )
        rows.append(s)
    return {
        "file": str(path.relative_to(root)),
        "gaussians": len(scene),
        "sh_degree": scene.sh_degree,
        "seconds": seconds,
        "mirrors": rows,
    }


def command_runs(ply: Path, repeats: int, max_mirrors: int) -> dict:
    """``symgs detect`` of ``ply`` in ``repeats`` fresh processes: medians, and the largest peak memory."""
    runs = []
    for _ in range(repeats):
        argv = [*SYMGS, "detect", str(ply), "--json", "--max-mirrors", str(max_mirrors)]
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        out, err = proc.stdout.read(), proc.stderr.read()  # type: ignore[union-attr]
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            raise RuntimeError(f"symgs detect {ply} failed: {err.decode(errors='replace')[-800:]}")
        report = json.loads(out)
        runs.append({
            "wall": wall, "load": report["timings"]["load"], "detect": report["timings"]["detect"],
            "cpu": usage.ru_utime + usage.ru_stime, "peak_mib": usage.ru_maxrss / 1024,
            "gaussians": report["gaussians"], "mirrors": [m["coverage"] for m in report["mirrors"]],
        })  # fmt: skip
    med = lambda key: statistics.median(r[key] for r in runs)  # noqa: E731
    return {
        "file": str(ply), "gaussians": runs[0]["gaussians"], "repeats": repeats, "max_mirrors": max_mirrors,
        "wall": med("wall"), "load": med("load"), "detect": med("detect"),
        "load_detect": statistics.median(r["load"] + r["detect"] for r in runs), "cpu": med("cpu"),
        "peak_mib": max(r["peak_mib"] for r in runs), "coverage": runs[0]["mirrors"],
        "load_average": os.getloadavg()[0],
    }  # fmt: skip


def write_scene(n: int, path: Path) -> None:
    from symgs_core.export import save_scene

    save_scene(benchmark_scene(n).scene, path)


def _run_worker(args: list[str]) -> dict:
    done = subprocess.run([sys.executable, __file__, *args], check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _markdown(results: list[dict], real: list[dict], commands: list[dict], command: str) -> str:
    lines = [f"    {command}", ""]
    if commands:
        lines += [
            "| scene | Gaussians | process wall (s) | load (s) | detect (s) | load + detect (s) | CPU (s) | peak MiB "
            "| coverage per level | load average |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |",
        ]
        for r in commands:
            lines.append(
                f"| {Path(r['file']).name} | {r['gaussians']:,} | {r['wall']:.2f} | {r['load']:.2f} "
                f"| {r['detect']:.2f} | {r['load_detect']:.2f} | {r['cpu']:.2f} | {r['peak_mib']:,.0f} "
                f"| {', '.join(f'{c:.3f}' for c in r['coverage']) or 'none'} | {r['load_average']:.1f} |"
            )
        lines.append("")
    if results:
        lines += [
            "| Gaussians | plane (s) | membership (s) | total (s) | CPU (s) | angle error | offset error | coverage "
            "| peak MiB |",
            "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for r in results:
            lines.append(
                f"| {r['gaussians']:,} | {r['plane_seconds']:.2f} | {r['membership_seconds']:.2f} | {r['total']:.2f} "
                f"| {r['cpu_seconds']:.2f} "
                f"| {r['angle_deg']:.3f} deg | {r['offset_pct_radius']:.3f}% R | {r['coverage']:.3f} "
                f"| {r['peak_mib']:,.0f} |"
            )
        lines.append("")
        lines.append(
            "Steps (median seconds): "
            + "; ".join(
                f"{r['gaussians']:,}: " + ", ".join(f"{k} {v:.2f}" for k, v in r["steps"].items()) for r in results
            )
        )
        for r in results:
            c = r["clusters"]
            lines.append(
                f"Clusters at {r['gaussians']:,}: {c['clusters']:,}, largest {c['largest']:,}, median size "
                f"{c['median_size']:.0f}, {c['all_pairs']:.3g} pairs in all, {100 * c['pairs_in_largest_1pct']:.0f}% "
                "of them in the largest 1% of clusters."
            )
            if "all_pairs" in r:
                a = r["all_pairs"]
                lines.append(
                    f"All-pairs voting at {r['gaussians']:,}: {a['pairs']:.3g} pairs in {a['seconds']:.1f} s (ours: "
                    f"{r['plane_seconds']:.2f} s to the refined plane, {a['seconds'] / r['plane_seconds']:.0f}x); its "
                    f"peak is {a['angle_to_ours_deg']:.3f} deg and {a['offset_to_ours_pct_radius']:.3f}% R from our "
                    f"plane (one cell: {a['cell_deg']:.2f} deg, {a['cell_pct_radius']:.2f}% R), "
                    f"{a['angle_to_planted_deg']:.3f} deg from the planted one."
                )
        lines.append("")
    if real:
        lines += [
            "| scene | Gaussians | SH | time (s) | level: normal, offset (offset of the median, % R), coverage |",
            "| --- | ---: | ---: | ---: | --- |",
        ]
        for r in real:
            if "error" in r:
                lines.append(f"| {r['file']} | - | - | - | not a Gaussian scene: {r['error']} |")
                continue
            found = (
                "; ".join(
                    f"{m['level']}: ({', '.join(f'{v:+.3f}' for v in m['normal'])}), {m['offset']:+.4g} "
                    f"({m['offset_from_median_pct_radius']:+.2f}%), {m['coverage']:.2f}"
                    for m in r["mirrors"]
                )
                or "none"
            )
            lines.append(f"| {r['file']} | {r['gaussians']:,} | {r['sh_degree']} | {r['seconds']:.1f} | {found} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="100000,1000000", help="object Gaussians per synthetic case")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--all-pairs", type=int, metavar="N", help="also vote all pairs, side by side, in the case of N Gaussians"
    )
    parser.add_argument("--real", type=Path, help="run on every .ply under this folder")
    parser.add_argument("--max-mirrors", type=int, default=4, help="levels searched on the real scenes")
    parser.add_argument("--cli", default="", help="object Gaussians of synthetic cases to time `symgs detect` on")
    parser.add_argument("--cli-scene", type=Path, nargs="*", default=[], help="PLY files to time `symgs detect` on")
    parser.add_argument("--json", type=Path, help="write the raw figures here")
    parser.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--write-scene", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--with-all-pairs", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.write_scene is not None:
        write_scene(int(args.write_scene[0]), Path(args.write_scene[1]))
        return
    if args.worker is not None:
        print(json.dumps(worker(args.worker, args.repeats, args.with_all_pairs)))
        return
    results = []
    for n in (int(v) for v in args.sizes.split(",") if v):
        extra = ["--with-all-pairs"] if n == args.all_pairs else []
        results.append(_run_worker(["--worker", str(n), "--repeats", str(args.repeats), *extra]))
    real = [real_scene(p, args.real, args.max_mirrors) for p in sorted(args.real.rglob("*.ply"))] if args.real else []
    commands = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(v) for v in args.cli.split(",") if v):
            ply = Path(tmp) / f"synthetic_{n}.ply"
            subprocess.run([sys.executable, __file__, "--write-scene", str(n), str(ply)], check=True)
            commands.append(command_runs(ply, args.repeats, args.max_mirrors))
            ply.unlink()
    commands += [command_runs(ply, args.repeats, args.max_mirrors) for ply in args.cli_scene]
    command = "python benchmarks/bench_detect.py " + " ".join(sys.argv[1:])
    print(_markdown(results, real, commands, command))
    print(f"\nLoad average at the end (1, 5, 15 min): {', '.join(f'{v:.1f}' for v in os.getloadavg())}")
    if args.json:
        raw = {"synthetic": results, "real": real, "command": commands}
        args.json.write_text(json.dumps(raw, indent=2, default=str))


if __name__ == "__main__":
    main()
