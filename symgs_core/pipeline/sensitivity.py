"""How much the fitting renders' error grows with an error in each stored attribute: a diagonal Gauss-Newton model.

For a small change d of the stored attributes the rendered images change by J d, J the Jacobian of every pixel with
respect to every attribute, so the squared error grows by |J d|^2. Quantisation errors of different Gaussians and
attributes are independent and of zero mean, so the cross terms average out and the growth is sum_i w_i d_i^2 with
w = diag(J^T J): one weight per stored attribute component. ``sensitivity`` estimates w without forming J (Hutchinson's
estimator): for a random sign image v, E[(J^T v)_i^2] = (J^T J)_ii, and J^T v is one backward pass of the renderer.

The weights are in units of mean squared error over the fitting views, summed over the full frame and the object's
own pixels (``views``): an upper bound of the larger of the two, which is what a floor holds. With them the error of
any quantiser, palette, dropped SH band or removed Gaussian is predicted in one pass over the Gaussians, no render;
the few renders that follow calibrate the prediction (measured against real renders: within a factor of 2, and
mostly 0.8-1.0 of the measured error, on the fox and playbot captures).

Opacity weights are kept per unit of alpha (what quantisers and removal change), not of its logit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from ..devices import HOST
from ..mirror import expand
from ..render import render
from ..scene import GaussianScene
from ..views import View
from .state import LevelState

# Step classes 0..3 (steps up to 8 times the section's): on the trained kacytran scene, at the fitting cameras'
# PSNR, 18% fewer bytes than one step per section with classes 0..1, 34% with 0..2, 39% with 0..3, 40% with 0..4
# and 39% with 0..5; at 0..6 the renders fell 16 dB below the model's prediction (a log-scale off by 4 is a small
# Gaussian turned large: the model is linear, the renders are not).
STEP_CLASSES = 4


@dataclass(frozen=True)
class Sensitivity:
    """Weights [N, ...] per stored attribute (as ``GaussianScene.tensors()`` names them), float64 on the CPU."""

    weights: dict[str, Tensor]

    def error(self, section: str, original: np.ndarray, decoded: np.ndarray) -> float:
        """Predicted growth of the mean squared error when ``section`` decodes to ``decoded`` instead of
        ``original`` (both as the stored set holds them; opacities as logits)."""
        if section == "opacities":
            original, decoded = _alpha(original), _alpha(decoded)
        elif section == "quats":
            original = original / np.maximum(np.linalg.norm(original, axis=1, keepdims=True), 1e-12)
        return _weighted_squares(self.weights[section].numpy(), decoded, original)

    def grouped(self, section: str, original: np.ndarray, index: np.ndarray) -> GroupedError:
        """``error`` for values that decode a group at a time (``Estimate.index`` [N]: each value's group), priced
        per group: a palette's rungs then cost its entries, not its rows."""
        if section in ("opacities", "quats"):
            raise ValueError(f"{section} is not priced by group (its error is not of the stored values)")
        n = len(original)
        w = self.weights[section].reshape(n, -1)
        x = torch.from_numpy(original.reshape(n, -1).astype(np.float64))
        groups = torch.from_numpy(index.astype(np.int64))  # a copy: the index may be read-only (a kept fit)
        count = int(groups.max()) + 1 if n else 0
        weight = w.new_zeros(count, w.shape[1]).index_add_(0, groups, w)
        mean = w.new_zeros(count, w.shape[1]).index_add_(0, groups, w * x) / weight.clamp_min(1e-300)
        spread = float((w * (x - mean[groups]) ** 2).sum())
        return GroupedError(weight.numpy(), mean.numpy(), spread)

    def per_gaussian(self, section: str) -> Tensor:
        """The weights of ``section`` summed over each Gaussian's components [N]."""
        w = self.weights[section]
        return w.reshape(len(w), -1).sum(dim=1)

    def removal(self, opacities: Tensor) -> Tensor:
        """Predicted error growth [N] of removing each Gaussian: its alpha going to zero."""
        alpha = torch.sigmoid(opacities.detach().to(HOST, torch.float64))
        return self.weights["opacities"] * alpha * alpha

    def select(self, index: Tensor) -> Sensitivity:
        return Sensitivity({k: v[index.to(HOST)] for k, v in self.weights.items()})

    def step_classes(self, count: int = STEP_CLASSES) -> Tensor:
        """Each Gaussian's step class [N] int64 in 0..count-1 (``codec.classes``): the step that spends equal error
        per unit of weight grows as weight^-1/2, so a Gaussian whose weight is 4^c times below the 90th percentile's
        takes steps 2^c times coarser, c the mean over the attributes the renders respond to."""
        exponents = []
        for w in self.weights.values():
            per = w.reshape(len(w), -1).sum(dim=1)
            reference = float(np.quantile(per.numpy(), 0.9)) if len(per) else 0.0
            if reference > 0:
                exponents.append(0.5 * torch.log2(reference / per.clamp_min(reference * 4.0**-count)))
        if not exponents:
            return torch.zeros(len(next(iter(self.weights.values()))), dtype=torch.int64)
        return torch.stack(exponents).mean(dim=0).round().clamp(0, count - 1).to(torch.int64)


@dataclass(frozen=True)
class GroupedError:
    """The error of values decoded by group: per group its weight [G, C] and the weighted mean [G, C] of its values,
    and their error about those means (``spread``). Decoding group g to r_g errs by sum_g weight_g (r_g - mean_g)^2
    plus the spread: about the weighted mean the cross term vanishes, so no large terms cancel."""

    weight: np.ndarray
    mean: np.ndarray
    spread: float

    def error(self, rows: np.ndarray) -> float:
        """The error when group g decodes to ``rows[g]`` [G, ...]."""
        return _weighted_squares(self.weight, rows.reshape(len(rows), -1), self.mean) + self.spread


def _weighted_squares(weights: np.ndarray, values: np.ndarray, reference: np.ndarray) -> float:
    """sum(weights * (values - reference)^2) in float64 (float32 values widen exactly), in the order w * d * d and in
    place where it can be: a million SH rows are 190 MB a float64 copy."""
    diff = values.astype(np.float64)
    diff -= reference
    weighted = weights * diff
    weighted *= diff
    return float(weighted.sum())


def _alpha(logits: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))


def sensitivity(
    state: LevelState, views: Sequence[View], background: Tensor, *, probes: int = 1, seed: int = 0,
    coverage: Sequence[Camera] = (),
) -> Sensitivity:
    """The weights of ``state``'s stored attributes (every copy the mirrors make contributes to its source's) over
    ``views``: one forward and ``probes`` backward passes per view. ``coverage``: cameras whose full-frame MSE is
    added to the views' (directions the views miss: what no view sees still counts where a viewer may stand)."""
    if not views:
        raise ValueError("sensitivity needs at least one view")
    stored = state.stored.detach()
    params = {k: v.clone().requires_grad_(True) for k, v in stored.tensors().items()}
    total = {k: torch.zeros(v.shape, dtype=torch.float64, device=v.device) for k, v in params.items()}
    # The signs are drawn on the host so that every device estimates from the same probes.
    gen = torch.Generator(HOST).manual_seed(seed)
    object_pixels = sum(int(view.mask.sum()) for view in views)
    all_pixels = sum(view.mask.numel() for view in views)
    scene, _ = expand(GaussianScene(**params), state.normals, state.offsets, state.bits)  # once: every view reuses it
    covered = sum(c.width * c.height for c in coverage)
    rigs = [(view.camera, view.mask) for view in views] + [(camera, None) for camera in coverage]
    for v, (camera, mask) in enumerate(rigs):
        image = render(scene, camera, background).image
        # Per-pixel weight of the squared error: MSE over the object's pixels plus MSE over the frame, each the mean
        # over colour channels and over every fitting view; over the coverage frames, their MSE.
        if mask is None:
            pixel = image.new_full(image.shape[:2], 1.0 / covered)
        else:
            pixel = mask.to(image.dtype) / max(object_pixels, 1) + 1.0 / all_pixels
        scale = (pixel / 3.0).sqrt()[..., None]
        for p in range(probes):
            signs = torch.randint(0, 2, image.shape, generator=gen, device=HOST).to(image) * 2.0 - 1.0
            last = v + 1 == len(rigs) and p + 1 == probes
            grads = torch.autograd.grad((image * signs * scale).sum(), list(params.values()), retain_graph=not last)
            for name, grad in zip(params, grads):
                g = grad.detach().to(torch.float64)
                total[name].addcmul_(g, g, value=1.0 / probes)  # in place: at 1M Gaussians, 38M values a view
    weights = {k: v.to(HOST) for k, v in total.items()}
    alpha = torch.sigmoid(stored.opacities.detach().to(HOST, torch.float64))
    # d image / d alpha = d image / d logit / (alpha (1 - alpha)).
    weights["opacities"] = weights["opacities"] / (alpha * (1.0 - alpha)).clamp_min(1e-12) ** 2
    return Sensitivity(weights)
