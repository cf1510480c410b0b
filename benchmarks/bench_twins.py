"""Are a scene's mirrored halves twins? What a quantised residual against the mirrored partner would cost.

For each scene the first mirror is detected; each Gaussian of the half a mirror would drop is paired with the nearest
reflection of a kept one (closest pairs first, each kept Gaussian used once). Two ways to store the paired Gaussians
are then priced with the codec's own section coders, at the steps of scale 1 (``QuantSteps()``, rotations in their
canonical frames, as the quantised archive holds them):

    plain     what the plain codec spends on them: the sections of the whole scene less those of the scene without
              them (positions as Morton gaps, so a dense set's positions cost what their neighbourhood leaves open)
    residual  the differences between their symbols and their partners' reflected symbols, coded the same way; a
              residual is exact at the codec's steps, so it costs no fidelity beyond the plain codec's own rounding

A ratio residual / plain below 1 is what a residual would save at most: the residual price leaves out which kept
Gaussian is each one's partner, which a decoder would need too. Above 1 it would cost more than storing the Gaussians
outright, and the halves carry no information about each other that the codec does not already use. "near twins"
counts the paired Gaussians whose every symbol lies within ``NEAR`` steps of their partner's: those a mirror could
replace, without a fine-tune, at about the codec's own error.

What a mirror without residuals does instead is replace the paired Gaussians by their partners' reflections. The
last columns render that, before any fine-tune, on the default fitting cameras against the input's own renders (the
reference when a scene comes without photographs), beside the same Gaussians simply left out: where the replaced
scene scores no better than the one without them, the reflections carry nothing of the Gaussians they replace.
Between them, each half of what a reflection carries on its own: the partners' reflected geometry (position, shape
and opacity) with the paired Gaussians' own colours, and the paired Gaussians' own geometry with their partners'
reflected colours. Where both stay far below the floor, neither a mirror that stores colours per copy nor one that
stores geometry per copy would come near it.

    python benchmarks/bench_twins.py ../shared/data/fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply --synthetic
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch

GROUPS = {"positions": ("means",), "shape": ("scales", "quats"), "opacity": ("opacities",),
          "colour": ("sh_dc", "sh_rest")}  # fmt: skip
# Steps a near twin's symbols may differ from its partner's: a few times the codec's rounding, far below what a
# fine-tune would have to move.
NEAR = 8


def pairs(dropped: np.ndarray, mirrored: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into ``dropped`` [D, 3], into ``mirrored`` [K, 3]) of nearest pairs, closest first, each once."""
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(mirrored).query(dropped, k=1)
    used = np.zeros(len(mirrored), dtype=bool)
    mine, theirs = [], []
    for i in np.argsort(distance, kind="stable"):
        if not used[nearest[i]]:
            used[nearest[i]] = True
            mine.append(i)
            theirs.append(nearest[i])
    return np.array(mine, dtype=np.int64), np.array(theirs, dtype=np.int64)


def symbols(scene, steps, extent: float) -> dict[str, np.ndarray]:  # noqa: ANN001 - GaussianScene, QuantSteps
    """Each attribute [N, C] on the codec's grid (origin 0): what a residual subtracts."""
    grid = lambda x, step: np.round(x.double().numpy().reshape(len(x), -1) / step).astype(np.int64)  # noqa: E731
    out = {
        "means": grid(scene.means, steps.position * extent),
        "scales": grid(scene.scales, steps.scale),
        "quats": grid(torch.nn.functional.normalize(scene.quats, dim=1)[:, 1:], steps.rotation),
        "opacities": grid(torch.sigmoid(scene.opacities), steps.opacity),
        "sh_dc": grid(scene.sh_dc, steps.dc),
    }
    if scene.sh_rest.shape[1]:
        out["sh_rest"] = grid(scene.sh_rest, steps.sh[0])
    return out


def section_bytes(scene, codecs, names) -> dict[str, int]:  # noqa: ANN001 - GaussianScene, section codecs
    """Bytes of the sections ``names`` of ``scene`` as ``codecs`` write them."""
    tensors = scene.tensors()
    return {k: len(codecs[k].encode(tensors[k].numpy()).payload) for k in names}


def fitting_psnr(scene, scenes: list) -> list[float]:  # noqa: ANN001 - GaussianScene
    """PSNR (dB, the worse of full frame and object pixels) of each of ``scenes`` on the default fitting cameras,
    against renders of ``scene``."""
    from symgs_core.config import CompressConfig
    from symgs_core.views import evaluate, self_supervised_views

    config, background = CompressConfig.for_preset(), torch.zeros(3)
    views = self_supervised_views(scene, train=0, fit=config.fit_views, eval=0, resolution=config.resolution,
                                  eval_resolution=config.eval_resolution, background=background, seed=config.seed)
    return [evaluate(s, views.fit, background, with_ssim=False).worst for s in scenes]


def mixed(geometry, colour):  # noqa: ANN001, ANN201 - GaussianScene
    """Gaussians with the positions, shapes and opacities of ``geometry`` and the SH colours of ``colour``."""
    return dataclasses.replace(geometry, sh_dc=colour.sh_dc, sh_rest=colour.sh_rest)


def measure(scene) -> dict:  # noqa: ANN001 - GaussianScene
    from symgs_core.codec.entropy import encode_table
    from symgs_core.codec.frames import canonical_frames
    from symgs_core.codec.steps import QuantSteps
    from symgs_core.detect import DetectConfig, detect
    from symgs_core.mirror import reflect
    from symgs_core.pipeline.budget import extent_of
    from symgs_core.scene import GaussianScene

    found = detect(scene, DetectConfig(max_mirrors=1))
    if not found:
        return {"paired": 0}
    mirror = found[0]
    scene = canonical_frames(scene)
    steps = QuantSteps()
    extent = extent_of(scene)
    codecs = steps.codecs(extent)
    normal = torch.tensor(mirror.plane.normal, dtype=torch.float32)
    kept, dropped = scene.select(mirror.left), scene.select(mirror.right)
    mirrored = canonical_frames(reflect(kept, normal, mirror.plane.offset))
    mine, theirs = pairs(dropped.means.numpy(), mirrored.means.numpy())
    twins = mirror.right[torch.from_numpy(mine)]
    rest = torch.ones(len(scene), dtype=torch.bool)
    rest[twins] = False
    own = symbols(dropped.select(torch.from_numpy(mine)), steps, extent)
    partner = symbols(mirrored.select(torch.from_numpy(theirs)), steps, extent)
    others = scene.select(torch.nonzero(rest).flatten())
    whole = section_bytes(scene, codecs, own)
    without = section_bytes(others, codecs, own)
    row = {"gaussians": len(scene), "paired": len(mine)}
    row["near"] = int(np.logical_and.reduce([(np.abs(own[k] - partner[k]) <= NEAR).all(axis=1) for k in own]).sum())
    partners, paired = mirrored.select(torch.from_numpy(theirs)), dropped.select(torch.from_numpy(mine))
    variants = [partners, mixed(partners, paired), mixed(paired, partners)]
    row["psnr"] = fitting_psnr(scene, [GaussianScene.cat([others, v]) for v in variants] + [others])
    for group, names in GROUPS.items():
        names = [n for n in names if n in own]  # SH degree 0: no higher bands
        row[group] = (sum(whole[n] - without[n] for n in names),
                      sum(len(encode_table(own[n] - partner[n])) for n in names))  # fmt: skip
    return row


def main() -> None:
    from symgs_core.ply import load_scene
    from symgs_core.synthetic import synthetic_scene

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="*", type=Path)
    parser.add_argument("--synthetic", action="store_true",
                        help="also generated scenes: exact twins and independent halves")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    jobs = [(p.name, lambda p=p: load_scene(p)) for p in args.scenes]
    if args.synthetic:
        for capture in ("twins", "independent"):
            jobs.append((f"synthetic global ({capture}, n=50000)",
                         lambda c=capture: synthetic_scene("global", n=50000, seed=0, sh_degree=1, capture=c).scene))
    heads = " | ".join(f"{g} plain / residual B" for g in GROUPS)
    print(f"| scene | Gaussians | dropped half, paired | near twins (within {NEAR} steps) | {heads} | all: plain B | "
          "residual B | residual / plain | fitting PSNR dB, paired replaced by reflections / reflected geometry, own "
          "colours / own geometry, reflected colours / left out |")
    print("|---|---:|---:|---:|" + "---:|" * len(GROUPS) + "---:|---:|---:|---:|")
    for name, load in jobs:
        row = measure(load())
        if not row["paired"]:
            print(f"| {name} | - | no mirror found |" + " |" * (len(GROUPS) + 5))
            continue
        plain, residual = (sum(row[g][i] for g in GROUPS) for i in (0, 1))
        cells = " | ".join(f"{row[g][0]:,} / {row[g][1]:,}" for g in GROUPS)
        print(f"| {name} | {row['gaussians']:,} | {row['paired']:,} | {row['near']:,} | {cells} | {plain:,} | "
              f"{residual:,} | {residual / plain:.3f} | {' / '.join(f'{p:.2f}' for p in row['psnr'])} |",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
