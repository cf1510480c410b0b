"""Fidelity of our exports to the archive they come from, read back by a third-party reader.

For each scene: ``symgs compress`` (or an archive already in ``--archives``), the archive decoded, then each export
written from the decode and read back by PlayCanvas ``splat-transform`` (the reader web platforms use), and rendered
from held-out cameras against the decode itself, as ``symgs evaluate DECODE.ply EXPORT.ply`` does. Rows:

    ours .spz v3 / v4           our writer (``symgs decompress -o x.spz``)
    ours .compressed.ply        our PlayCanvas compressed PLY writer
    splat-transform .spz        splat-transform's own .spz of the decode (its default, version 4; the reference
                                choices: 12 fractional bits, SH rounded to 5 and 4 bits)
    splat-transform .compressed.ply

and, for our rows and splat-transform's .spz, where the loss lies: the decode with one attribute taken from the
read-back export (PSNR against the decode; the lowest names the attribute that costs most).

    SYMGS_NPM_CACHE=<folder with splat-transform> .venv/bin/python benchmarks/bench_export.py \\
        ../shared/data/donut_mipsplatting/donut_graphdeco_sh0.ply \\
        ../shared/data/kacytran_try_iter7000/point_cloud.ply --archives bench-export
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from symgs_core.export import compressed_ply_order, save_scene, write_compressed_ply, write_spz
from symgs_core.pipeline import decompress
from symgs_core.ply import load_scene
from symgs_core.scene import GaussianScene
from symgs_core.views import evaluate, self_supervised_views

SYMGS = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]
COMPRESS = ["--quiet"]  # the default a user gets
ATTRIBUTES = ("means", "quats", "scales", "opacities", "sh_dc", "sh_rest")


def _run(args: list[str]) -> None:
    done = subprocess.run(args, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, args[:3]))} failed: {done.stderr.strip()[-800:]}")


def archive_of(scene: Path, folder: Path) -> Path:
    archive = folder / f"{scene.stem}.symgs"
    if not archive.exists():
        folder.mkdir(parents=True, exist_ok=True)
        _run([*SYMGS, "compress", str(scene), "-o", str(archive), *COMPRESS])
    return archive


def swapped(reference: GaussianScene, back: GaussianScene, name: str) -> GaussianScene:
    """``reference`` with attribute ``name`` as ``back`` (the same Gaussians, in the same order) holds it."""
    value = getattr(back, name)
    if name == "quats":  # q and -q are one rotation
        value = value * torch.where((value * reference.quats).sum(1, keepdim=True) < 0, -1.0, 1.0)
    return reference.with_(**{name: value})


def bench(scene: Path, archives: Path, exe: str, views: int, resolution: int) -> list[str]:
    archive = archive_of(scene, archives)
    decode = decompress(archive)
    cameras = self_supervised_views(decode, train=1, fit=1, eval=views, resolution=resolution,
                                    eval_resolution=resolution, background=torch.zeros(3))  # fmt: skip

    def psnr(candidate: GaussianScene) -> float:
        return evaluate(candidate, cameras.eval, cameras.background, with_ssim=False).psnr

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        save_scene(decode, folder / "decode.ply")
        exports = {
            "ours .spz v3": ("ours3.spz", lambda p: p.write_bytes(write_spz(decode, version=3))),
            "ours .spz v4": ("ours4.spz", lambda p: p.write_bytes(write_spz(decode, version=4))),
            "ours .compressed.ply": ("ours.compressed.ply", lambda p: p.write_bytes(write_compressed_ply(decode))),
            "splat-transform .spz": ("st.spz", lambda p: _run([exe, "-w", "-q", str(folder / "decode.ply"), str(p)])),
            "splat-transform .compressed.ply": (
                "st.compressed.ply", lambda p: _run([exe, "-w", "-q", str(folder / "decode.ply"), str(p)])),
        }  # fmt: skip
        for label, (name, write) in exports.items():
            path = folder / name
            write(path)
            _run([exe, "-w", "-q", str(path), str(folder / "back.ply")])
            back = load_scene(folder / "back.ply")
            if len(back) != len(decode):
                raise SystemExit(f"{label}: {len(back)} Gaussians read back, {len(decode)} written")
            reference = decode
            if name == "ours.compressed.ply":  # the format reorders the Gaussians, ours in a known order
                reference = decode.select(compressed_ply_order(decode))
            if name == "st.compressed.ply":  # splat-transform's order is its own: no attribute swap
                where = "-"
            else:
                where = ", ".join(f"{a} {psnr(swapped(reference, back, a)):.1f}" for a in ATTRIBUTES
                                  if getattr(decode, a).numel())  # fmt: skip
            rows.append(f"| {scene.stem} | {label} | {path.stat().st_size:,} | {psnr(back):.2f} | {where} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--archives", type=Path, default=Path("bench-export"), help="compressed archives (kept)")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--resolution", type=int, default=256)
    args = parser.parse_args()
    # The 2.x reader: it reads .spz in the axes our writer and Niantic's reference use (3.x reads them as PLY axes).
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.npm_tools import SPLAT_TRANSFORM_SPZ, splat_transform

    exe = os.environ.get("SPLAT_TRANSFORM") or splat_transform(SPLAT_TRANSFORM_SPZ)
    print("| scene | export | bytes | PSNR vs decode (dB) | one attribute from the export (dB) |")
    print("|---|---|---:|---:|---|")
    for scene in args.scenes:
        for row in bench(scene, args.archives, exe, args.views, args.resolution):
            print(row, flush=True)


if __name__ == "__main__":
    main()
