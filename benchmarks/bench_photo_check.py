"""Photographs that do not show the upload: the check a job with photographs passes before any work.

A job's decisions hold the upload's own PSNR against its photographs, less the budget. Photographs of another scene,
or poses in another frame than the scene's, put that floor at a few dB, where any mirror and any quantiser pass it.
``views.check_photographs`` refuses them (``images_mismatch``): where the upload renders opaque on the fitting
photographs, it must match them 3 dB better than a flat colour per photograph does. Each row is one upload against
one photograph set, on the fitting set a job would use (the product's defaults):

    generated   each kind's capture-like upload against photographs of its truth ("shown"), and three that do not
                show it: another generated scene, the upload turned a quarter about z, moved by 0.3 radii
    real        scenes of the data folder against the two photograph sets there (none was trained from them), and,
                with ``--captures``, the scenes ``bench_pipeline.py --captures`` trained from each set (cached in its
                work folder), against their own photographs and against the other set's

    python benchmarks/bench_photo_check.py --data ../shared/data --captures bench-out/pipeline-capture
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from symgs_core.bench.photos import photographed
from symgs_core.config import CompressConfig
from symgs_core.datasets import DatasetError
from symgs_core.ply import load_scene
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import check_photographs, dataset_views, evaluate, flat_colour_psnr

KINDS = ("global", "nested", "local", "asymmetric")
PHOTO_SETS = ("nerf_synthetic_lego_400px", "snowmiku_plush_capture_mit")
REAL_UPLOADS = ("donut_mipsplatting/donut_graphdeco_sh0.ply", "fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply",
                "playbot_cc_by_sa3d/playbot_lod3_31k_sh2.ply")  # fmt: skip


def row(upload: str, photographs: str, scene, folder: Path, *, fit: int, resolution: int) -> str:  # noqa: ANN001
    background = torch.zeros(3)
    views = dataset_views(folder, scene, fit=fit, eval=1, resolution=resolution, background=background)
    fitting = evaluate(scene, views.fit, background, with_ssim=False)
    flat = flat_colour_psnr(views.fit)
    try:
        check_photographs(fitting, views.fit)
        verdict = "accepted"
    except DatasetError as exc:
        verdict = exc.code
    drawn = sum(int(v.mask.sum()) for v in views.fit) / sum(v.mask.numel() for v in views.fit)
    margin = fitting.psnr_object - flat
    return (f"| {upload} | {photographs} | {drawn:.1%} | {fitting.psnr_object:.2f} | {flat:.2f} | {margin:+.2f} | "
            f"{verdict} |")  # fmt: skip


def generated(n: int, resolution: int, fit: int) -> list[str]:
    rows = []
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for kind in KINDS:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            shown = photographed(kind, folder, n=n, photos=2 * fit, tests=1, resolution=resolution)
            centre = shown.means.mean(dim=0)
            other = "asymmetric" if kind != "asymmetric" else "global"
            uploads = {
                "shown": shown,
                f"another scene ({other})": synthetic_scene(other, n=n, seed=5, sh_degree=1).scene,
                "turned a quarter": shown.with_(means=(shown.means - centre) @ quarter.T + centre),
                "moved 0.3 radii": shown.with_(means=shown.means + 0.3),
            }
            for name, scene in uploads.items():
                rows.append(row(f"generated {kind}: {name}", f"of generated {kind}", scene, folder, fit=fit,
                                resolution=resolution))  # fmt: skip
    return rows


def real(data: Path, captures: Path | None, fit: int, resolution: int) -> list[str]:
    rows = []
    uploads = [(path, data / path) for path in REAL_UPLOADS if (data / path).exists()]
    if captures is not None:
        from symgs_core.bench.capture import TrainSettings, cached_path

        trained = [(name, cached_path(data / name, captures / name, TrainSettings())) for name in PHOTO_SETS
                   if (data / name).exists()]  # fmt: skip
        uploads += [(f"{name}/{ply.name} (trained from it)", ply) for name, ply in trained if ply.exists()]
    for label, path in uploads:
        scene = load_scene(path)
        for photos in PHOTO_SETS:
            if (data / photos).exists():
                rows.append(row(label, photos, scene, data / photos, fit=fit, resolution=resolution))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="the data folder: real scenes and photograph sets")
    parser.add_argument("--captures", type=Path, help="bench_pipeline.py --captures' work folder (trained scenes)")
    parser.add_argument("--n", type=int, default=5000, help="Gaussians of each generated upload")
    parser.add_argument("--photo-resolution", type=int, default=64, help="generated photographs' side, pixels")
    args = parser.parse_args()
    config = CompressConfig()
    rows = generated(args.n, args.photo_resolution, config.fit_views)
    if args.data is not None:
        rows += real(args.data, args.captures, config.fit_views, config.eval_resolution)
    print("| upload | photographs | drawn | upload where drawn dB | flat colour dB | margin dB | verdict |")
    print("|---|---|---:|---:|---:|---:|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
