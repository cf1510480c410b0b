"""Web exports of decoded scenes: our `.sog` read back by PlayCanvas ``splat-transform`` and our `.glb`, their bytes,
write times and fidelity; optionally splat-transform's own SOG of the same scene beside ours.

Each input is a `.symgs` archive (the reference is its own decode, what a job exports) or a `.ply` (the reference is
the scene itself). The SOG is written by ``write_sog``, converted by ``splat-transform`` to a PLY on the CPU and
rendered from ``--views`` held-out cameras at ``--resolution`` px against renders of the reference; the `.glb` is
read back by our reader (its attributes are float32, so it should be lossless up to rounding). Prints a Markdown
table.

    .venv/bin/python benchmarks/bench_web_exports.py --splat-transform PATH/TO/splat-transform SCENE.symgs SCENE.ply
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from symgs_core.bench import splat_transform
from symgs_core.export import read_glb, write_glb, write_sog
from symgs_core.ply import load_scene
from symgs_core.scene import GaussianScene
from symgs_core.views import evaluate, self_supervised_views


def reference_of(path: Path) -> GaussianScene:
    if path.suffix == ".symgs":
        from symgs_core.pipeline import decompress

        return decompress(path.read_bytes())
    return load_scene(path)


def fidelity(scene: GaussianScene, views) -> str:  # noqa: ANN001 - a views.ViewSet
    value = evaluate(scene, views.eval, views.background).psnr
    return "lossless" if value == float("inf") else f"{value:.2f} dB"


def convert(tool: str, source: Path, target: Path) -> float:
    start = time.perf_counter()
    subprocess.run([tool, "-w", "-q", "-g", "cpu", str(source), str(target)], check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("inputs", nargs="+", type=Path, help=".symgs archives or .ply scenes")
    parser.add_argument("--splat-transform", help="the splat-transform executable (default: the pinned one, installed "
                        "on first use)")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--peer", action="store_true", help="also splat-transform's own SOG (a CPU k-means: slow)")
    args = parser.parse_args()
    args.splat_transform = args.splat_transform or splat_transform.find() or splat_transform.install()
    print("| input | Gaussians | SH | our .sog | write s | read back by splat-transform | our .glb | write s | .glb "
          "read back |" + (" splat-transform .sog | its write s | read back |" if args.peer else ""))
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|---:|" if args.peer else ""))
    for path in args.inputs:
        reference = reference_of(path)
        views = self_supervised_views(reference, train=1, fit=1, eval=args.views, resolution=16,
                                      eval_resolution=args.resolution, background=torch.zeros(3))  # fmt: skip

        with tempfile.TemporaryDirectory() as folder:
            work = Path(folder)
            start = time.perf_counter()
            sog = write_sog(reference)
            sog_s = time.perf_counter() - start
            (work / "ours.sog").write_bytes(sog)
            convert(args.splat_transform, work / "ours.sog", work / "ours.ply")
            start = time.perf_counter()
            glb = write_glb(reference)
            glb_s = time.perf_counter() - start
            row = [
                path.name, f"{len(reference):,}", str(reference.sh_degree), f"{len(sog):,} B", f"{sog_s:.1f}",
                fidelity(load_scene(work / "ours.ply"), views), f"{len(glb):,} B", f"{glb_s:.2f}",
                fidelity(read_glb(glb), views),
            ]  # fmt: skip
            if args.peer:
                from symgs_core.export import save_scene

                save_scene(reference, work / "reference.ply")
                peer_s = convert(args.splat_transform, work / "reference.ply", work / "theirs.sog")
                convert(args.splat_transform, work / "theirs.sog", work / "theirs.ply")
                size = (work / "theirs.sog").stat().st_size
                row += [f"{size:,} B", f"{peer_s:.1f}", fidelity(load_scene(work / "theirs.ply"), views)]
        print("| " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()
