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

``--truth``: the same reflections scored against what the scene shows, not against the scene itself, where
photographs of it exist: a generated upload with photographs of its symmetric truth (``symgs_core.bench.photos``) and
the scenes trained from ``--captures`` folders (``symgs_core.bench.capture``, cached under ``--work``). On each
capture's test photographs, which trained nothing, the input, the paired Gaussians replaced by their partners'
reflections and the same Gaussians left out are rendered against the photographs, and against the input's own renders
from the same cameras. Two independent reconstructions of one symmetric surface differ from each other by about both
their errors, so a reflection can stand in for the half it replaces as well as that half did against the truth and
still score low against the input's renders: the reference of a scene without photographs.

    python benchmarks/bench_twins.py ../shared/data/fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply --synthetic
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

GROUPS = {"positions": ("means",), "shape": ("scales", "quats"), "opacity": ("opacities",),
          "colour": ("sh_dc", "sh_rest")}  # fmt: skip
# Steps a near twin's symbols may differ from its partner's: a few times the codec's rounding, far below what a
# fine-tune would have to move.
NEAR = 8
TEST_PHOTOS = 8  # as bench_pipeline scores captures
TRUTH_N = 20_000  # the generated upload of --truth, as bench_pipeline --photos makes it


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


@dataclasses.dataclass
class Halves:
    """The first mirror's pairs: ``scene`` in canonical frames; ``mine`` indexes the ``dropped`` half, ``theirs`` the
    reflected kept half ``mirrored``, pair by pair; ``others`` are the Gaussians no pair holds."""

    scene: Any
    dropped: Any
    mirrored: Any
    mine: torch.Tensor
    theirs: torch.Tensor
    others: Any

    @property
    def paired(self):  # noqa: ANN201 - GaussianScene
        return self.dropped.select(self.mine)

    @property
    def partners(self):  # noqa: ANN201 - GaussianScene
        return self.mirrored.select(self.theirs)


def halves(scene) -> Halves | None:  # noqa: ANN001 - GaussianScene
    """``scene``'s first mirror, its dropped half paired with the reflected kept half; None without a mirror."""
    from symgs_core.codec.frames import canonical_frames
    from symgs_core.detect import DetectConfig, detect
    from symgs_core.mirror import reflect

    found = detect(scene, DetectConfig(max_mirrors=1))
    if not found:
        return None
    mirror = found[0]
    scene = canonical_frames(scene)
    normal = torch.tensor(mirror.plane.normal, dtype=torch.float32)
    dropped = scene.select(mirror.right)
    mirrored = canonical_frames(reflect(scene.select(mirror.left), normal, mirror.plane.offset))
    mine, theirs = (torch.from_numpy(i) for i in pairs(dropped.means.numpy(), mirrored.means.numpy()))
    rest = torch.ones(len(scene), dtype=torch.bool)
    rest[mirror.right[mine]] = False
    return Halves(scene, dropped, mirrored, mine, theirs, scene.select(torch.nonzero(rest).flatten()))


def measure(scene) -> dict:  # noqa: ANN001 - GaussianScene
    from symgs_core.codec.entropy import encode_table
    from symgs_core.codec.steps import QuantSteps
    from symgs_core.pipeline.budget import extent_of
    from symgs_core.scene import GaussianScene

    h = halves(scene)
    if h is None:
        return {"paired": 0}
    steps = QuantSteps()
    extent = extent_of(h.scene)
    codecs = steps.codecs(extent)
    own = symbols(h.paired, steps, extent)
    partner = symbols(h.partners, steps, extent)
    whole = section_bytes(h.scene, codecs, own)
    without = section_bytes(h.others, codecs, own)
    row = {"gaussians": len(h.scene), "paired": len(h.mine)}
    row["near"] = int(np.logical_and.reduce([(np.abs(own[k] - partner[k]) <= NEAR).all(axis=1) for k in own]).sum())
    variants = [h.partners, mixed(h.partners, h.paired), mixed(h.paired, h.partners)]
    row["psnr"] = fitting_psnr(h.scene, [GaussianScene.cat([h.others, v]) for v in variants] + [h.others])
    for group, names in GROUPS.items():
        names = [n for n in names if n in own]  # SH degree 0: no higher bands
        row[group] = (sum(whole[n] - without[n] for n in names),
                      sum(len(encode_table(own[n] - partner[n])) for n in names))  # fmt: skip
    return row


def against_truth(scene, photographs: Path) -> dict | None:  # noqa: ANN001 - GaussianScene
    """Full-frame PSNR on the test photographs of the folder ``photographs`` (at the resolution the captures train
    at, on black as they train): the input, the paired Gaussians replaced by reflections, and left out, against the
    photographs; the last two also against the input's renders from the same cameras."""
    from symgs_core.bench.capture import RESOLUTION
    from symgs_core.render import render
    from symgs_core.scene import GaussianScene
    from symgs_core.views import View, dataset_eval_views, evaluate

    h = halves(scene)
    if h is None:
        return None
    background = torch.zeros(3)
    photos = dataset_eval_views(photographs, h.scene, eval=TEST_PHOTOS, resolution=RESOLUTION, background=background)
    with torch.no_grad():
        renders = [View(v.camera, render(h.scene, v.camera, background).image, v.mask) for v in photos]
    replaced = GaussianScene.cat([h.others, h.partners])
    psnr = lambda s, views: evaluate(s, views, background, with_ssim=False).psnr  # noqa: E731
    return {"gaussians": len(h.scene), "paired": len(h.mine),
            "photos": [psnr(s, photos) for s in (h.scene, replaced, h.others)],
            "renders": [psnr(s, renders) for s in (replaced, h.others)]}  # fmt: skip


def truth_table(args: argparse.Namespace) -> None:
    from symgs_core.bench.capture import RESOLUTION, cached_capture
    from symgs_core.bench.photos import photographed
    from symgs_core.ply import load_scene

    kind = "global"
    jobs = [(f"synthetic {kind} (independent, n={TRUTH_N}, SH 1), photographs of its twin truth",
             lambda: photographed(kind, args.work / f"truth-{kind}", n=TRUTH_N, photos=2, tests=TEST_PHOTOS,
                                  resolution=RESOLUTION), args.work / f"truth-{kind}")]  # fmt: skip
    for folder in args.captures:
        ply = cached_capture(folder, args.work / folder.name,
                             say=lambda m, f=folder: print(f"{f.name}: {m}", flush=True))  # fmt: skip
        jobs.append((f"{folder.name} (trained: {ply.name})", lambda p=ply: load_scene(p), folder))
    print("| scene | Gaussians | dropped half, paired | test photographs: input / paired replaced by reflections / "
          "left out (dB) | the input's renders, same cameras: replaced / left out (dB) |")
    print("|---|---:|---:|---:|---:|")
    for name, load, folder in jobs:
        row = against_truth(load(), folder)
        if row is None:
            print(f"| {name} | - | no mirror found | | |")
            continue
        cells = [" / ".join(f"{p:.2f}" for p in row[k]) for k in ("photos", "renders")]
        print(f"| {name} | {row['gaussians']:,} | {row['paired']:,} | {cells[0]} | {cells[1]} |", flush=True)


def main() -> None:
    from symgs_core.ply import load_scene
    from symgs_core.synthetic import synthetic_scene

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="*", type=Path)
    parser.add_argument("--synthetic", action="store_true",
                        help="also generated scenes: exact twins and independent halves")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--truth", action="store_true",
                        help="score the reflections against photographs instead: a generated upload and --captures")
    parser.add_argument("--captures", nargs="*", default=[], type=Path, help="capture folders, with --truth")
    parser.add_argument("--work", type=Path, default=Path("bench-out/twins"),
                        help="where --truth writes its photographs and trained scenes")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.truth:
        truth_table(args)
        return
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
