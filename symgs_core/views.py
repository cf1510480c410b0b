"""Three disjoint camera sets, their target images, and the fidelity of a scene on them.

training    the views the fine-tune trains on
fitting     the views every decision is taken on: level acceptance, quantiser steps, pruning, SH bands
evaluation  the views the report scores; nothing is fitted on them

With posed photographs the dataset's test split is the evaluation set, a spread subset of its training split is the
fitting set and the rest trains. Without them the targets are renders of the uncompressed scene from three rigs
whose directions are turned apart (no camera appears in two sets), each spanning the distances a viewer takes, from
close-ups at 1.6 radii to the whole object at 2.8; fitting and evaluation are rendered at the resolution a report
is read at, training at a cheaper one.

Fidelity is reported over the full frame and over the object's own pixels (where the uncompressed scene renders at
least half opaque): over a black background the full-frame figure hides the object's loss (a guitar filling a tenth
of the frame: 36.5 dB full frame, 26.1 dB on its own pixels). A floor holds on both (``Fidelity.worst``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from .cameras import Camera, View, fibonacci_directions, near_for, scene_bounds
from .devices import HOST
from .metrics import mse_to_psnr, ssim
from .report import CameraSet, Fidelity, PhotoScale
from .scene import GaussianScene

if TYPE_CHECKING:
    from .datasets import Photograph

# Distances (in scene radii) a viewer's camera takes, close-up to the whole object in the frame.
DISTANCES = (1.6, 2.8)
FOV_DEG = 50.0
OBJECT_ALPHA = 0.5  # a pixel belongs to the object where the uncompressed scene renders at least this opaque
# Photographs show a flat backdrop around the upload where at least BACKDROP_SHARE of their pixels lie around it and
# BACKDROP_AGREE of those lie within BACKDROP_SPREAD of their median colour in every channel.
BACKDROP_SHARE = 0.01
BACKDROP_SPREAD = 0.1
BACKDROP_AGREE = 0.9
MATCH_MARGIN_DB = 3.0  # how much better than a flat colour an upload must match its photographs (check_photographs)
_SET_SEEDS = {"training": 1, "fitting": 2, "evaluation": 3}


class PhotoTarget(NamedTuple):
    """A photograph before it is laid on a background, with the object's pixels in its view."""

    photograph: Photograph
    mask: Tensor  # [H, W] bool

    def on(self, background: Tensor) -> View:
        return View(self.photograph.camera, self.photograph.on(background), self.mask, self.photograph.name)


class RenderedTargets(Sequence[View]):
    """Views whose targets are renders of a scene, made on first access and kept.

    Training draws many self-supervised views; rendering each only when the optimiser first asks for it keeps the
    set-up cost proportional to the views actually used.
    """

    def __init__(self, scene: GaussianScene, cameras: list[Camera], background: Tensor) -> None:
        self.scene, self.cameras, self.background = scene.detach(), cameras, background
        self._views: dict[int, View] = {}  # the camera moved to the scene's device once, with its target

    def __len__(self) -> int:
        return len(self.cameras)

    @torch.no_grad()
    def __getitem__(self, index: int) -> View:  # type: ignore[override]
        from .render import render

        if index not in self._views:
            camera = self.cameras[index].to(self.scene.device)
            out = render(self.scene, camera, self.background)
            self._views[index] = View(camera, out.image.detach(), out.alpha.detach() >= OBJECT_ALPHA)
        return self._views[index]


@dataclass
class ViewSet:
    """The three camera sets with their targets, over ``background`` [3]."""

    train: Sequence[View]
    fit: Sequence[View]
    eval: Sequence[View]
    background: Tensor
    sets: tuple[CameraSet, CameraSet, CameraSet]
    # The three sets' photographs before a background (None: targets rendered from the scene), for ``on``.
    photographs: tuple[list[PhotoTarget], list[PhotoTarget], list[PhotoTarget]] | None = None
    read: PhotoScale | None = None  # how the photographs were read (None: no photographs)

    @property
    def source(self) -> str:
        return self.sets[2].source

    def on(self, background: Tensor) -> ViewSet:
        """The same photographs laid on ``background`` [3], from what was read: no image is read again, and the
        object's pixels (where the scene renders opaque, whatever it is drawn on) are not rendered again."""
        if self.photographs is None:
            raise ValueError("only photographs are laid on another background; renders are drawn on theirs")
        return _laid(self.photographs, background, self.sets, self.read)


def _laid(
    photographs: tuple[list[PhotoTarget], list[PhotoTarget], list[PhotoTarget]],
    background: Tensor,
    sets: tuple[CameraSet, CameraSet, CameraSet],
    read: PhotoScale | None,
) -> ViewSet:
    train, fit, eval = ([target.on(background) for target in targets] for targets in photographs)
    return ViewSet(train, fit, eval, background, sets, photographs, read)


def _turn(seed: int) -> Tensor:
    """A rotation [3, 3] drawn from ``seed``: each set's rig is turned apart from the others."""
    gen = torch.Generator(HOST).manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64, device=HOST))
    q = q * torch.sign(torch.diagonal(r))[None, :]
    return q * torch.sign(torch.linalg.det(q))


def viewer_cameras(
    center: Tensor, radius: float, count: int, resolution: int, *, seed: int, name: str = "view"
) -> list[Camera]:
    """``count`` cameras looking at ``center`` [3] from directions spread over the sphere (turned by a rotation
    drawn from ``seed``) and distances spread over ``DISTANCES`` radii (a low-discrepancy sequence, so a few
    cameras already cover near and far)."""
    turn = _turn(seed)
    directions = fibonacci_directions(count) @ turn.T
    c = center.to(HOST, torch.float64)
    near, far = DISTANCES
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    cams = []
    for i, d in enumerate(directions):
        distance = (near + (far - near) * ((0.5 + i * golden) % 1.0)) * radius
        up = turn[:, 2] if abs(float(d @ turn[:, 2])) < 0.99 else turn[:, 1]
        cams.append(Camera.look_at(c + distance * d, c, up, FOV_DEG, resolution, resolution, name=f"{name}_{i:03d}",
                                   near=near_for(radius)))  # fmt: skip
    return cams


def self_supervised_views(
    scene: GaussianScene,
    *,
    train: int,
    fit: int,
    eval: int,
    resolution: int,
    eval_resolution: int,
    background: Tensor,
    seed: int = 0,
) -> ViewSet:
    """The three sets, targets rendered from ``scene``; each set's rig is turned apart by its own rotation."""
    center, radius = scene_bounds(scene.means.detach(), scene.scales)
    counts = {"training": train, "fitting": fit, "evaluation": eval}
    sizes = {"training": resolution, "fitting": eval_resolution, "evaluation": eval_resolution}
    sets, targets = [], []
    for name, count in counts.items():
        cams = viewer_cameras(center, radius, count, sizes[name], seed=1000 * seed + _SET_SEEDS[name], name=name)
        targets.append(RenderedTargets(scene, cams, background))
        sets.append(CameraSet(name, count, "renders of the input", sizes[name], DISTANCES))
    return ViewSet(targets[0], targets[1], targets[2], background, (sets[0], sets[1], sets[2]))


def dataset_views(
    folder: str | Path,
    scene: GaussianScene,
    *,
    fit: int,
    eval: int,
    resolution: int,
    background: Tensor,
) -> ViewSet:
    """Posed photographs of a NeRF-Synthetic or COLMAP folder, decoded at a scale whose longest side is
    ``resolution`` (``photo_reading``): the test split (at most ``eval`` images, evenly spaced) evaluates, ``fit``
    training images, evenly spaced, fit, and the other training images train. The object's pixels are where
    ``scene`` (the uncompressed upload) renders opaque. Opaque photographs are their own background: each is judged
    with the surroundings it shows."""

    from .datasets import DatasetError, load_photographs

    read = photo_reading(folder, resolution)
    scale, width = read.scale, _side(read)
    photos = load_photographs(folder, split="train", scale=scale)
    if len(photos) < 2:
        raise DatasetError(
            "too_few_images",
            f"{Path(folder).name}: {len(photos)} training photograph(s) besides the held-out test views; at least 2 "
            "are needed (one to train, one to fit)",
        )
    count = min(fit, len(photos) // 2)
    fit_index = {round((i + 0.5) * len(photos) / count - 0.5) for i in range(count)}

    def described(name: str, n: int) -> CameraSet:
        return CameraSet(name, n, "photographs", width, None)

    targets = [_photo_target(scene, p) for p in photos]
    train_targets = [t for i, t in enumerate(targets) if i not in fit_index]
    fit_targets = [t for i, t in enumerate(targets) if i in fit_index]
    eval_targets = _eval_targets(folder, scene, eval=eval, scale=scale)
    sets = (described("training", len(train_targets)), described("fitting", len(fit_targets)),
            described("evaluation", len(eval_targets)))  # fmt: skip
    return _laid((train_targets, fit_targets, eval_targets), background, sets, read)


def flat_colour_psnr(views: Sequence[View]) -> float:
    """PSNR, over the object's pixels of ``views``, of the best flat colour per view (its mean there); NaN where
    no view has any."""
    error, pixels = 0.0, 0
    for view in views:
        target, mask = view.image, view.mask
        if mask.any():
            drawn = target[mask]
            error += float(((drawn - drawn.mean(dim=0)) ** 2).mean(dim=-1).sum())
            pixels += int(mask.sum())
    return mse_to_psnr(error / pixels) if pixels else math.nan


def photographed_backdrop(views: Sequence[View]) -> Tensor | None:
    """The flat colour [3] the photographs of ``views`` show around the upload (where it renders less than half
    opaque), when they show one: at least ``BACKDROP_SHARE`` of their pixels lie there, and ``BACKDROP_AGREE`` of
    those within ``BACKDROP_SPREAD`` of its median in every channel. None: real surroundings, or none in view.

    Photographs without an alpha channel carry their backdrop (NeRF-Synthetic's white, a studio sweep); rendered on
    any other, the upload would miss every pixel around it, and every decision would chase that."""
    around = torch.cat([view.image[~view.mask].reshape(-1, 3) for view in views])
    total = sum(int(view.mask.numel()) for view in views)
    if not total or len(around) < BACKDROP_SHARE * total:
        return None
    colour = around.median(dim=0).values
    agree = float(((around - colour).abs().amax(dim=1) <= BACKDROP_SPREAD).double().mean())
    return colour if agree >= BACKDROP_AGREE else None


def check_photographs(fitting: Fidelity, views: Sequence[View]) -> None:
    """Refuse photographs that do not show the upload: where it renders opaque in ``views`` (the fitting set, on
    which the upload scores ``fitting``), it must match them ``MATCH_MARGIN_DB`` better than a flat colour does
    (``flat_colour_psnr``): its error there at most half the flat colour's.

    Uploads of what the photographs show beat the flat colour by 9 to 17 dB; the photographs of another scene, or
    poses in another frame than the scene's, fall below it (BENCHMARKS, "Photographs that do not show the upload").
    Against such photographs every decision would chase noise: the floor sits at a few dB and any mirror passes it.
    """
    from .datasets import DatasetError

    frame = ("their poses are not in its frame (a scene trained by nerfstudio needs the dataparser_transforms.json "
             "of its run beside transforms.json)")  # fmt: skip
    flat = flat_colour_psnr(views)
    if math.isnan(flat):
        raise DatasetError("images_mismatch", "the upload draws nothing in the photographs' views: they do not show "
                           f"this scene, or {frame}")  # fmt: skip
    if math.isinf(flat):  # a flat colour matches them exactly: nothing of a scene is in them
        raise DatasetError("images_mismatch", "where the upload is drawn, the photographs show one flat colour: they "
                           f"do not show this scene, or {frame}")  # fmt: skip
    if not fitting.psnr_object >= flat + MATCH_MARGIN_DB:
        raise DatasetError(
            "images_mismatch",
            f"where the upload is drawn, it matches the photographs at {fitting.psnr_object:.1f} dB, hardly better "
            f"than a flat colour does ({flat:.1f} dB): they do not show this scene, or {frame}",
        )


def photo_scale(folder: str | Path, resolution: int) -> tuple[float, int]:
    """The scale that brings the training photographs' longest side to ``resolution`` (never up), and that side."""
    read = photo_reading(folder, resolution)
    return read.scale, _side(read)


def _side(read: PhotoScale) -> int:
    return round(max(read.width, read.height) * read.scale)


def photo_reading(folder: str | Path, resolution: int) -> PhotoScale:
    """How photographs are read for judges at ``resolution``: at the scale that brings the training photographs'
    longest side to it, never above their own size (a render larger than its photograph only invents pixels), with
    the reason a report gives for it."""
    from .datasets import dataset_frames

    first = dataset_frames(folder, "train")[0]
    width, height = first.camera.width, first.camera.height
    scale = min(1.0, resolution / max(width, height))
    lens = first.lens
    own = f"{width}x{height}" + ("" if lens is None else f" (undistorted from {lens.width}x{lens.height})")
    if scale < 1.0:
        reason = (f"decoded at {scale:.3g} of their {own}: the judges render at the job's eval_resolution, "
                  f"{resolution} px on the longest side, and the fine-tune trains there too; a larger "
                  f"eval_resolution, up to {max(width, height)}, judges closer to their own size at more time a "
                  "render")  # fmt: skip
    else:
        reason = f"read at their own size, {own}: the job's eval_resolution ({resolution} px) asks for no less"
    return PhotoScale(width, height, scale, reason)


@torch.no_grad()
def _photo_target(scene: GaussianScene, photograph: Photograph) -> PhotoTarget:
    from .render import render

    alpha = photograph.alpha
    on_device = replace(photograph, camera=photograph.camera.to(scene.device),
                        colour=photograph.colour.to(scene.device),
                        alpha=None if alpha is None else alpha.to(scene.device))  # fmt: skip
    # The scene's opacity does not depend on what it is drawn on: one render serves every background.
    return PhotoTarget(on_device, render(scene, on_device.camera).alpha >= OBJECT_ALPHA)


def _eval_targets(folder: str | Path, scene: GaussianScene, *, eval: int, scale: float) -> list[PhotoTarget]:
    """The test split's photographs at the training photographs' ``scale`` (``photo_scale``)."""
    from .datasets import load_photographs

    return [_photo_target(scene, p) for p in load_photographs(folder, split="test", max_views=eval, scale=scale)]


def dataset_eval_views(
    folder: str | Path, scene: GaussianScene, *, eval: int, resolution: int, background: Tensor
) -> list[View]:
    """The evaluation set of ``dataset_views`` alone (its test split), without loading the training photographs."""
    scale, _ = photo_scale(folder, resolution)
    return [target.on(background) for target in _eval_targets(folder, scene, eval=eval, scale=scale)]


EVAL_BATCH = 16  # views rendered together: one gsplat call on a GPU, and a bound on the images held at once
BOUND_BATCH = 4  # views rendered together where ``worst_psnr`` may stop early


def _errors(
    scene: GaussianScene, views: Sequence[View], background: Tensor, batch: int, with_ssim: bool
) -> Iterator[tuple[Tensor, int, list[Tensor]]]:
    """Per batch of views: (the squared errors' sums [3] over the batch: full frame, object pixels, object pixel
    count, on the scene's device; the frames' pixels; the batch's SSIMs)."""
    from .render import render_many

    for start in range(0, len(views), batch):
        chunk = [views[i] for i in range(start, min(start + batch, len(views)))]
        sums, pixels, ssims = [], 0, []
        for view, out in zip(chunk, render_many(scene, [v.camera for v in chunk], background)):
            target, mask = view.image, view.mask
            error = ((out.image - target) ** 2).mean(dim=-1)
            sums.append(torch.stack([error.sum(), (error * mask).sum(), mask.sum()]).double())
            pixels += error.numel()
            if with_ssim:
                ssims.append(ssim(out.image, target))
        yield torch.stack(sums).sum(dim=0), pixels, ssims


@torch.no_grad()
def evaluate(scene: GaussianScene, views: Sequence[View], background: Tensor, *, with_ssim: bool = True) -> Fidelity:
    """Fidelity of ``scene`` on ``views``: PSNRs from the squared error summed over every view (full frame, and the
    object's pixels), SSIM the mean over views (NaN without ``with_ssim``: decisions read the PSNRs alone). The sums
    stay on the scene's device until the end: one wait for the device per call, not per view."""
    if not views:
        raise ValueError("evaluate needs at least one view")
    batches = list(_errors(scene, views, background, EVAL_BATCH, with_ssim))
    full, obj, object_pixels = torch.stack([b[0] for b in batches]).sum(dim=0).tolist()
    pixels = sum(b[1] for b in batches)
    ssims = [s for b in batches for s in b[2]]
    psnr = mse_to_psnr(full / pixels)
    psnr_object = mse_to_psnr(obj / object_pixels) if object_pixels else psnr
    return Fidelity(psnr, psnr_object, float(torch.stack(ssims).double().mean()) if ssims else math.nan)


@torch.no_grad()
def worst_psnr(
    scene: GaussianScene, views: Sequence[View], background: Tensor, *, below: float,
    settled: Callable[[float], bool] | None = None,
) -> float:  # fmt: skip
    """``evaluate(...).worst``, but once the views rendered so far put it below ``below`` whatever the rest show,
    or bound it where ``settled`` says a PSNR no higher decides the question, the rest are not rendered and that
    bound is returned instead (no lower than the true PSNR). Squared errors only add up: the sums over some views,
    divided by every view's pixels, bound the mean from below. A decision that only asks "below ``below``?" gets
    the same answer from fewer renders."""
    if not views:
        raise ValueError("worst_psnr needs at least one view")
    pixels = sum(v.mask.numel() for v in views)
    object_pixels = float(sum(v.mask.sum() for v in views))
    sums, seen = torch.zeros(3, dtype=torch.float64, device=scene.device), 0
    for batch, count, _ in _errors(scene, views, background, BOUND_BATCH, False):
        sums, seen = sums + batch, seen + count
        full, obj, _ = sums.tolist()
        psnr = mse_to_psnr(full / pixels)
        bound = min(psnr, mse_to_psnr(obj / object_pixels) if object_pixels else psnr)
        if seen < pixels and (bound < below or (settled is not None and settled(bound))):
            return bound
    return bound
