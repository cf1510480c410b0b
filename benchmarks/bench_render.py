"""Speed of the CPU renderer: forward + backward through ``render`` on a dense object filling the view.

The object is an ellipsoid shell of flat Gaussians lying in its surface, spaced so that neighbours overlap, with
random colours (SH degree 3) and opacities in 0.5..1: every pixel of the silhouette is covered by front and back
layers, the case that matters when fine-tuning real objects. Prints a Markdown table of medians; each case runs in
a fresh process, so "peak MiB" is what render + backward added to the process's peak resident memory, beyond the
scene. "CPU time" is the process's CPU seconds per forward + backward (all threads): on a machine shared with other
work it moves much less than the wall-clock figures.

    python benchmarks/bench_render.py --threads 2
"""

from __future__ import annotations

import argparse
import gc
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

import numba
import torch

from symgs_core.cameras import Camera
from symgs_core.render import render
from symgs_core.scene import GaussianScene

AXES = (1.0, 0.75, 0.9)


def _quats_from_z(normals: torch.Tensor) -> torch.Tensor:
    """Quaternions [N, 4] (w, x, y, z) turning the z axis onto unit ``normals`` [N, 3]."""
    z = torch.tensor([0.0, 0.0, 1.0])
    axis = torch.linalg.cross(z.expand_as(normals), normals, dim=-1)
    w = 1.0 + normals[:, 2]
    q = torch.cat([w[:, None], axis], dim=-1)
    flipped = w < 1e-6  # normal = -z: half a turn about x
    q[flipped] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    return torch.nn.functional.normalize(q, dim=-1)


def dense_object(n: int, seed: int = 0) -> GaussianScene:
    """``n`` Gaussians tiling the surface of an ellipsoid with semi-axes ``AXES``."""
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(n, dtype=torch.float64) + 0.5
    zs = 1.0 - 2.0 * i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = torch.sqrt(1.0 - zs * zs)
    sphere = torch.stack([r * torch.cos(phi), r * torch.sin(phi), zs], dim=-1)
    axes = torch.tensor(AXES, dtype=torch.float64)
    means = sphere * axes
    normals = torch.nn.functional.normalize(sphere / axes, dim=-1)
    a, b, c, p = *AXES, 1.6075  # Knud Thomsen's approximation of the ellipsoid's area
    area = 4.0 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3.0) ** (1.0 / p)
    spacing = math.sqrt(area / n)
    scales = torch.log(torch.tensor([0.9 * spacing, 0.9 * spacing, 0.1 * spacing])).expand(n, 3).clone()
    scales += 0.2 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    opacity = 0.5 + 0.5 * torch.rand(n, generator=g, dtype=torch.float64)
    return GaussianScene(
        means=means.float(),
        quats=_quats_from_z(normals.float()),
        scales=scales.float(),
        opacities=torch.log(opacity / (1.0 - opacity)).float(),
        sh_dc=(1.5 * torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.75).float(),
        sh_rest=0.1 * torch.randn(n, 15, 3, generator=g),
    )


def framing_camera(size: int) -> Camera:
    """An oblique view in which the ellipsoid fills most of the image."""
    eye = 2.1 * torch.nn.functional.normalize(torch.tensor([0.6, -0.8, 0.25]), dim=0)
    return Camera.look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 60.0, size, size)


def _peak_rss_bytes() -> int:
    """Peak resident memory of this process so far (Linux reports kilobytes, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024


def real_view(path: str, size: int, view: int) -> tuple[GaussianScene, Camera]:
    """A real scene and camera ``view`` of the 8 spread over its bounding sphere."""
    from symgs_core.cameras import scene_cameras
    from symgs_core.ply import load_scene

    scene = load_scene(path)
    return scene, scene_cameras(scene.means, 8, size, size)[view]


def measure(n: int, size: int, repeats: int, scene_path: str | None = None, view: int = 0) -> dict[str, float]:
    """Run in a fresh process: time a first small render (kernel load or compile), then medians over ``repeats``
    steps on the case's scene (the dense object of ``n`` Gaussians, or the scene at ``scene_path``), and the peak
    memory those steps added beyond the scene itself."""
    small = dense_object(1000)
    small.means.requires_grad_(True)
    t0 = time.perf_counter()
    render(small, framing_camera(64)).image.sum().backward()
    first = time.perf_counter() - t0

    scene, cam = real_view(scene_path, size, view) if scene_path else (dense_object(n), framing_camera(size))
    for t in scene.tensors().values():
        t.requires_grad_(True)
    target = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1))
    gc.collect()
    before = _peak_rss_bytes()
    fwd, total, cpu = [], [], []
    for _ in range(repeats + 1):  # the first step warms the allocator and is not timed
        for t in scene.tensors().values():
            t.grad = None
        c0 = time.process_time()
        t0 = time.perf_counter()
        result = render(scene, cam)
        t1 = time.perf_counter()
        (result.image - target).abs().mean().backward()
        fwd.append(t1 - t0)
        total.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {
        "first": first,
        "fwd": statistics.median(fwd[1:]),
        "total": statistics.median(total[1:]),
        "cpu": statistics.median(cpu[1:]),
        "peak_mib": (_peak_rss_bytes() - before) / 2**20,
        "count": len(scene),
        "pairs": result.aux["num_intersections"],
    }


def _run_case(
    n: int, size: int, args: argparse.Namespace, env: dict[str, str] | None = None, scene: str | None = None
) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--case", str(n), str(size), "--repeats", str(args.repeats)]
    cmd += ["--threads", str(args.threads), "--view", str(args.view)] + (["--scene", scene] if scene else [])
    done = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="CPU threads for torch and numba (default 2)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512], help="image sizes (square)")
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 50_000, 200_000], help="Gaussian counts")
    parser.add_argument("--repeats", type=int, default=7, help="timed repeats per case (median reported)")
    parser.add_argument("--scene", action="append", default=[], help="also time a real scene (.ply), any number")
    parser.add_argument("--view", type=int, default=0, choices=range(8), help="which of 8 orbit views of --scene")
    parser.add_argument("--case", type=int, nargs=2, metavar=("N", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    if args.case:
        print(json.dumps(measure(*args.case, args.repeats, args.scene[0] if args.scene else None, args.view)))
        return 0

    # Each case runs in its own process so peak memory is its own and the first call shows the kernel start-up.
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        cold = _run_case(1000, 64, args, env)["first"]
        warm = _run_case(1000, 64, args, env)["first"]
    wait = os.environ.get("OMP_WAIT_POLICY", "unset")
    print("| scene | Gaussians | image | tile pairs | forward (s) | forward + backward (s) | CPU time (s) | peak MiB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    cases = [("dense ellipsoid", n, size, None) for size in args.sizes for n in args.counts]
    cases += [(f"{Path(path).name}, view {args.view}", 0, size, path) for path in args.scene for size in args.sizes]
    for name, n, size, path in cases:
        m = _run_case(n, size, args, scene=path)
        print(
            f"| {name} | {m['count']:,} | {size}x{size} | {m['pairs']:,} | {m['fwd']:.3f} | {m['total']:.3f} "
            f"| {m['cpu']:.3f} | {m['peak_mib']:.0f} |"
        )
        sys.stdout.flush()
    print()
    print(f"Threads: {args.threads}, repeats: {args.repeats}, torch {torch.__version__}, numba {numba.__version__}, "
          f"OMP_WAIT_POLICY {wait}. First render + backward in a fresh process: {cold:.1f} s compiling the kernels, "
          f"{warm:.2f} s loading them from the cache.")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
