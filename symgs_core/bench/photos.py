"""Generated scenes with photographs: the paper's protocol, where fidelity is measured against images of the object,
not against renders of the upload.

The object is drawn once (``synthetic_scene``'s design) and sampled twice (``sample_seed``): densely as exact twins,
the truth that is photographed (symmetric, as the object is), and as the upload, whose mirrored half is an
independent reconstruction. Reflected, the kept half of the upload renders the photographs about as well as the half
it replaces: the two are samples of one surface.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..cameras import Camera, scene_bounds
from ..datasets import Split, write_nerf_synthetic
from ..render import render
from ..scene import GaussianScene
from ..synthetic import Capture, SceneKind, surroundings_of, synthetic_scene
from ..views import viewer_cameras

TRUTH_DENSITY = 4  # the photographed truth holds this many times the upload's Gaussians


def photographed(
    kind: SceneKind, folder: str | Path, *, n: int, photos: int, tests: int, resolution: int, sh_degree: int = 1,
    capture: Capture = "independent", seed: int = 0, backdrop: tuple[float, float, float] = (0.0, 0.0, 0.0),
    surroundings: float = 0.0,
) -> GaussianScene:  # fmt: skip
    """The upload of a generated ``kind`` scene of about ``n`` Gaussians; ``photos`` training and ``tests`` test
    photographs (``resolution`` px square, on ``backdrop``, without alpha) of its truth written to ``folder`` as
    NeRF-Synthetic. ``surroundings``: the object stands on a slab of ``surroundings * n`` asymmetric Gaussians
    (``synthetic.surroundings_of``), the same in the truth and the upload, as a capture's table is reconstructed
    once; the cameras frame the object."""
    common: dict[str, Any] = {"seed": seed, "sh_degree": sh_degree}
    upload = synthetic_scene(kind, n=n, capture=capture, sample_seed=2 * seed + 1, **common).scene
    truth = synthetic_scene(kind, n=TRUTH_DENSITY * n, capture="twins", sample_seed=2 * seed + 2, **common).scene
    centre, radius = scene_bounds(truth.means, truth.scales)
    if surroundings > 0:
        gen = torch.Generator().manual_seed(2 * seed + 3)
        slab = surroundings_of(truth.means, truth.scales, round(surroundings * n), gen, truth.sh_rest.shape[1])
        upload, truth = GaussianScene.cat([upload, slab]), GaussianScene.cat([truth, slab])
    split: Split
    for split, count, rig in (("train", photos, 11), ("test", tests, 12)):
        cameras = viewer_cameras(centre, radius, count, resolution, seed=1000 * seed + rig, name=split)
        if surroundings > 0:
            cameras = [_above(camera, centre) for camera in cameras]
        with torch.no_grad():
            images = [render(truth, camera, torch.tensor(backdrop)).image for camera in cameras]
        write_nerf_synthetic(folder, split, cameras, images)
    return upload


def _above(camera: Camera, centre: Tensor) -> Camera:
    """``camera``, if it is under ``centre`` [3], moved to its reflection above it, upright: photographs of an object on
    a table are taken from above the table."""
    eye = camera.center.to(torch.float64)
    target = centre.to(eye)
    if eye[2] >= target[2]:
        return camera
    eye = torch.stack([eye[0], eye[1], 2 * target[2] - eye[2]])
    up = (0.0, 0.0, 1.0) if float((eye - target)[:2].norm()) > 1e-9 else (0.0, 1.0, 0.0)  # not straight above
    fov = math.degrees(2 * math.atan(camera.width / (2 * camera.fx)))
    return Camera.look_at(eye, target, up, fov, camera.width, camera.height, camera.name, camera.near)
