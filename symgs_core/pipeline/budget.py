"""One PSNR budget shared by every lossy stage, and the search for the quantisation steps that spend the rest of it.

Errors of independent stages add in mean squared error, not in dB. The budget is the excess MSE between the
reference (the input's own PSNR, or +inf against renders of the input) and the floor; the stages get cumulative
shares of it, in the order they run: mirrors up to 60%, pruning up to 70%, SH reduction up to 80%, quantisation up
to 100%. A stage's floor is the PSNR at its cumulative share, so what an earlier stage leaves unspent passes on to
the next, and quantisation, which always runs last, takes whatever remains.

Quantisation spends its share in three moves (``fit_steps``): the preset's steps are balanced on the scene's own
renders so that every coded component carries the same error (``balance_steps``), their common factor is fitted to
the floor (``fit_quantization``), and what that leaves is spent one attribute at a time (``coarsen_one_by_one``).
On the plant capture (113k, SH 0) at the 60.36 dB of `.spz` v3: 1,363,603 bytes with one factor for the preset's
steps, 1,184,853 after all three (BENCHMARKS.md, Codec: ``benchmarks/bench_steps.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from ..codec.order import coding_order, grid_cells
from ..codec.quantize import band_slices
from ..codec.steps import QuantSteps
from ..metrics import mse_to_psnr, psnr_to_mse
from ..scene import GaussianScene
from ..views import View, evaluate
from .state import LevelState

# Mirrors lead: on playbot (125k) a 60% share kept a level that 40% refused, and the archive came out 9% smaller.
SHARES = {"mirrors": 0.6, "pruning": 0.7, "sh_reduction": 0.8, "quantization": 1.0}


def split_budget(floor: float, reference: float) -> dict[str, float]:
    """The floor (dB) of each stage in ``SHARES`` for an overall ``floor`` below the ``reference`` PSNR."""
    if math.isinf(floor) or floor >= reference:
        return {stage: floor for stage in SHARES}
    base = psnr_to_mse(reference)
    excess = psnr_to_mse(floor) - base
    return {stage: mse_to_psnr(base + share * excess) for stage, share in SHARES.items()}


def extent_of(stored: GaussianScene) -> float:
    """Longest side of the stored set's bounding box (the position grid is relative to it)."""
    if len(stored) == 0:
        return 1.0
    means = stored.means.detach()
    return float((means.max(dim=0).values - means.min(dim=0).values).max())


def held_out_psnr(
    state: LevelState, stored: GaussianScene, test: Sequence[View], background: Tensor
) -> float:
    """PSNR (the worse of full frame and object pixels) on the fitting views of ``state``'s levels with ``stored``
    (a decoded copy) in place of its stored set."""
    return evaluate(LevelState(stored, state.normals, state.offsets, state.bits).expanded(), test, background).worst


def quantized(stored: GaussianScene, steps: QuantSteps, sections: tuple[str, ...] | None = None) -> GaussianScene:
    """``stored`` as a reader of its quantised archive decodes it (every section encoded, then decoded); only the
    attributes named in ``sections`` when given, the others exact."""
    codecs = steps.codecs(extent_of(stored))
    out = {}
    for name, value in stored.tensors().items():
        if sections is not None and name not in sections:
            out[name] = value.detach().cpu()
            continue
        array = value.detach().cpu().contiguous().numpy()
        coded = codecs[name].encode(array)
        out[name] = torch.from_numpy(codecs[name].decode(coded.payload, array.shape, coded.params, coded.raw_length))
    return GaussianScene(**out).to(stored.device)


# Attributes whose steps are balanced, with their section and coded components per Gaussian (rotations: three).
_ATTRIBUTES = {"position": ("means", 3), "rotation": ("quats", 3), "scale": ("scales", 3),
               "opacity": ("opacities", 1), "dc": ("sh_dc", 3)}  # fmt: skip
_PROBE = 2.0  # steps are probed at twice the start, so attributes already on a grid that fine still show an error
_MAX_SHIFT = 8.0  # how far balancing may move one attribute's step from the start, either way
_EXACT = 0.01  # an error per component below this share of the mean counts as none
_EXACT_PALETTE = 1 << 16  # distinct SH rows below which the palette starts exact
_PALETTE = 1 << 14  # the k-means palette size tried first otherwise
# Palette SH steps start this much finer again; benchmarks/bench_steps.py at the .spz floors: playbot 31k 379,026 ->
# 375,194 B, kacytran 88,335 -> 83,195 B (symgs bench: playbot 125k unchanged within 0.1%).
_PALETTE_SH = 0.8


@dataclass
class Balanced:
    """Balanced steps, and per attribute the excess MSE measured at the probe and the coded components per Gaussian."""

    steps: QuantSteps
    errors: dict[str, float]
    components: dict[str, float]

    @property
    def order(self) -> list[str]:
        """Attributes with coded components, the most first: where a coarser step saves the most bytes."""
        return sorted((k for k, c in self.components.items() if c > 0), key=lambda k: -self.components[k])


def _times(steps: QuantSteps, attribute: str, factor: float) -> QuantSteps:
    """``steps`` with one attribute's step (a key of ``_ATTRIBUTES``, or ``sh1``..``sh3``) times ``factor``; for
    ``sh_palette`` the palette shrinks as a step growing by ``factor`` would cut the error (size / factor^4)."""
    if attribute == "sh_palette":
        return replace(steps, sh_palette=max(2, round(steps.sh_palette / factor**4)))
    if attribute.startswith("sh"):
        band = int(attribute[2:]) - 1
        return replace(steps, sh=tuple(s * factor if i == band else s for i, s in enumerate(steps.sh)))
    value = getattr(steps, attribute) * factor
    return replace(steps, **{attribute: min(value, 0.5) if attribute == "opacity" else value})


def balance_steps(
    state: LevelState, test: Sequence[View], background: Tensor, *, start: QuantSteps, psnr_before: float
) -> Balanced:
    """Steps that give every coded component the same share of the error, measured on this scene's renders.

    With entropy-coded uniform quantisers each halving of a step costs one bit per coded component and quarters that
    attribute's error, so a given total error is cheapest when every component carries the same share of it (the
    slopes of rate against error are then equal). The shares depend on the scene (how anisotropic its Gaussians
    are, how much of its colour is view-dependent, which attributes a previous codec already rounded), so each
    attribute, and each SH band, is quantised alone at twice the ``start`` steps, its excess error over
    ``psnr_before`` measured on the held-out views, and its step rescaled (error grows as the step squared) to the
    mean error per component, within a factor of 8 either way.
    """
    base = psnr_to_mse(psnr_before)
    probe = start.scaled(_PROBE)
    stored = state.stored.detach()

    def excess(scene: GaussianScene) -> float:
        return max(psnr_to_mse(held_out_psnr(state, scene, test, background)) - base, 0.0)

    errors, components = {}, {}
    for name, (section, count) in _ATTRIBUTES.items():
        errors[name], components[name] = excess(quantized(stored, probe, (section,))), float(count)
    rounded = quantized(stored, probe, ("sh_rest",)).sh_rest if stored.sh_degree else None
    for lvl, rows in enumerate(band_slices(stored.sh_degree), start=1):
        mixed = stored.sh_rest.clone()
        mixed[:, rows] = rounded[:, rows]
        kept = float((stored.sh_rest[:, rows].abs().amax(dim=(1, 2)) > 0).double().mean())
        errors[f"sh{lvl}"] = excess(stored.with_(sh_rest=mixed))
        components[f"sh{lvl}"] = (rows.stop - rows.start) * 3 * kept
    coded = [k for k in errors if components[k] > 0]
    mean_error = sum(errors[k] for k in coded) / max(sum(components[k] for k in coded), 1e-12)
    # An attribute exact at the probe (already on a grid that fine) shows no slope to balance: its step stays.
    measured = [k for k in coded if errors[k] > _EXACT * mean_error * components[k]]
    if not measured:
        return Balanced(start, errors, components)
    per_component = sum(errors[k] for k in measured) / sum(components[k] for k in measured)
    ratio = {k: 1.0 for k in errors}
    for k in measured:
        ratio[k] = float(np.clip(math.sqrt(per_component * components[k] / errors[k]), 1 / _MAX_SHIFT, _MAX_SHIFT))
    steps = start
    for k, r in ratio.items():
        steps = _times(steps, k, r)
    return Balanced(steps, errors, components)


@dataclass
class QuantFit:
    steps: QuantSteps
    factor: float
    psnr: float
    tries: list[dict]
    probe_errors: dict[str, float] = field(default_factory=dict)  # of ``balance_steps``, when it ran


def fit_quantization(
    state: LevelState,
    test: Sequence[View],
    background: Tensor,
    *,
    floor: float,
    start: QuantSteps,
    psnr_before: float,
    max_tries: int = 6,
    slack_db: float = 0.25,
) -> QuantFit | None:
    """The coarsest multiple of ``start`` whose decoded scene keeps the held-out PSNR at or above ``floor``.

    The quantisation error grows as the square of the step, so each try rescales the steps by the square root of
    (error allowed / error measured), aiming at 95% of what is allowed, and bisects between the coarsest pass and
    the finest failure when that aim falls outside them; it stops at the first pass within ``slack_db`` of the
    floor, when pass and failure lie within 4% of each other, or after ``max_tries`` renders. None when no try
    passes (the caller then stores the attributes losslessly).
    """
    if math.isinf(floor):
        return None
    allowed = psnr_to_mse(floor) - psnr_to_mse(psnr_before)
    if allowed <= 0:
        return None
    factor, best, failed, tries = 1.0, None, math.inf, []
    for _ in range(max_tries):
        steps = start.scaled(factor)
        value = held_out_psnr(state, quantized(state.stored, steps), test, background)
        tries.append({"factor": factor, "psnr": value})
        if value >= floor and (best is None or factor > best.factor):
            best = QuantFit(steps, factor, value, tries)
            if value < floor + slack_db:
                break
        elif value < floor:
            failed = min(failed, factor)
        error = psnr_to_mse(value) - psnr_to_mse(psnr_before)
        proposal = factor * 8.0 if error <= 0 else factor * math.sqrt(0.95 * allowed / error)
        proposal = float(np.clip(proposal, factor / 8.0, factor * 8.0))
        low = best.factor if best is not None else 0.0
        if not low < proposal < failed:  # the model overshot what the renders have bracketed: bisect instead
            proposal = math.sqrt(low * failed) if low > 0 and math.isfinite(failed) else proposal
        if best is not None and (failed / best.factor < 1.04 or proposal <= best.factor * 1.02):
            break
        factor = proposal
    if best is not None:
        best.tries = tries
    return best


def coarsen_one_by_one(
    state: LevelState,
    test: Sequence[View],
    background: Tensor,
    fit: QuantFit,
    *,
    floor: float,
    order: list[str],
    max_tries: int = 16,
    factors: tuple[float, ...] = (math.sqrt(2.0), 2.0**0.25, 2.0**0.125),
) -> QuantFit:
    """Spend what the common factor left of the budget: coarsen one attribute at a time, in ``order`` (the
    attributes most likely to pay first), keeping each change whose renders stay at or above ``floor``.

    One factor for every step lands short of the floor wherever the error jumps instead of growing smoothly (an
    attribute on a grid of its own is exact up to twice that grid's step, then not), and the last try that passed
    can sit a decibel or more above the floor. Each attribute is coarsened by ``factors[0]``; one that fails is
    tried again by the next, smaller factor, and left alone once the last fails.
    """
    candidates = [(attribute, 0) for attribute in order]
    best, tries = fit, list(fit.tries)
    while candidates and len(tries) - len(fit.tries) < max_tries:
        attribute, which = candidates.pop(0)
        steps = _times(best.steps, attribute, factors[which])
        value = held_out_psnr(state, quantized(state.stored, steps), test, background)
        tries.append({"coarsen": attribute, "by": factors[which], "psnr": value})
        if value >= floor:
            best = QuantFit(steps, best.factor, value, tries)
            candidates.append((attribute, which))  # the others get their turn before it comes round again
        elif which + 1 < len(factors):
            candidates.append((attribute, which + 1))
    best.tries = tries
    return best


def archive_bytes(stored: GaussianScene, steps: QuantSteps) -> int:
    """Bytes of the attribute sections of ``stored`` quantised with ``steps`` (the archive less header and masks)."""
    codecs = steps.codecs(extent_of(stored))
    stored = stored.detach().to("cpu")
    bits = torch.zeros(len(stored), 0, dtype=torch.bool)
    stored = stored.select(coding_order(stored, bits, grid_cells(codecs["means"], stored.means.numpy())))
    return sum(len(codecs[k].encode(v.contiguous().numpy()).payload) for k, v in stored.tensors().items())


def palette_start(sh_rest: Tensor) -> int:
    """The first palette size tried for ``sh_rest`` [N, K, 3]: every distinct row (exact) when they number fewer
    than ``_EXACT_PALETTE``, as in scenes decoded from SOG; else ``_PALETTE``."""
    rows = sh_rest.detach().reshape(len(sh_rest), -1)
    distinct = len(torch.unique(rows[rows.any(dim=1)], dim=0))
    return distinct + 1 if distinct < _EXACT_PALETTE else _PALETTE


def fit_steps(
    state: LevelState,
    test: Sequence[View],
    background: Tensor,
    *,
    floor: float,
    start: QuantSteps,
    psnr_before: float,
) -> QuantFit | None:
    """The quantisation steps for ``floor``: balanced on this scene's renders (``balance_steps``), their common
    factor fitted (``fit_quantization``), then what is left spent one attribute at a time (``coarsen_one_by_one``).
    Scenes with higher SH bands are fitted twice, with those bands per coefficient and as a palette of vectors
    (``codec.palette``, shrunk further while it pays), and the smaller archive wins. None when no quantisation keeps
    the floor."""
    if math.isinf(floor) or psnr_to_mse(floor) <= psnr_to_mse(psnr_before):
        return None
    balanced = balance_steps(state, test, background, start=start, psnr_before=psnr_before)
    fits = []
    variants = [(balanced.steps, balanced.order)]
    if state.stored.sh_degree:
        size = palette_start(state.stored.sh_rest)
        # A palette codes an SH vector per entry, not per Gaussian: fewer coded components than ``balance_steps``
        # counted, so the steps that balance the error are finer by the square root of entries per Gaussian; and
        # finer again (``_PALETTE_SH``) where the entry classes make the entries few renders see cheaper.
        shrink = _PALETTE_SH * math.sqrt(min(1.0, size / max(len(state.stored), 1)))
        palette = replace(balanced.steps, sh_palette=size, sh=tuple(s * shrink for s in balanced.steps.sh))
        variants.append((palette, ["sh_palette"] + balanced.order))
    for steps, order in variants:
        fit = fit_quantization(state, test, background, floor=floor, start=steps, psnr_before=psnr_before)
        if fit is not None:
            fits.append(coarsen_one_by_one(state, test, background, fit, floor=floor, order=order))
    if not fits:
        return None
    best = fits[0] if len(fits) == 1 else min(fits, key=lambda f: archive_bytes(state.stored, f.steps))
    best.probe_errors = balanced.errors
    return best
