"""One PSNR budget shared by every lossy stage, and the search for the quantisation steps that spend the rest of it.

Errors of independent stages add in mean squared error, not in dB. The budget is the excess MSE between the
reference (the input's own PSNR, or +inf against renders of the input) and the floor; the stages get cumulative
shares of it, in the order they run: mirrors up to 60%, pruning up to 70%, SH reduction up to 80%, quantisation up
to 100%. A stage's floor is the PSNR at its cumulative share, so what an earlier stage leaves unspent passes on to
the next, and quantisation, which always runs last, takes whatever remains.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .cameras import Camera
from .codec.steps import QuantSteps
from .optimize import LevelState, evaluate
from .scene import GaussianScene

# Mirrors lead: on playbot (125k) a 60% share kept a level that 40% refused, and the archive came out 9% smaller.
SHARES = {"mirrors": 0.6, "pruning": 0.7, "sh_reduction": 0.8, "quantization": 1.0}


def psnr_to_mse(psnr: float) -> float:
    return 0.0 if math.isinf(psnr) and psnr > 0 else 10.0 ** (-psnr / 10.0)


def mse_to_psnr(mse: float) -> float:
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


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


def quantized(stored: GaussianScene, steps: QuantSteps) -> GaussianScene:
    """``stored`` as a reader of its quantised archive decodes it (every section encoded, then decoded)."""
    codecs = steps.codecs(extent_of(stored))
    out = {}
    for name, value in stored.tensors().items():
        array = value.detach().cpu().contiguous().numpy()
        coded = codecs[name].encode(array)
        out[name] = torch.from_numpy(codecs[name].decode(coded.payload, array.shape, coded.params, coded.raw_length))
    return GaussianScene(**out).to(stored.device)


@dataclass
class QuantFit:
    steps: QuantSteps
    factor: float
    psnr: float
    tries: list[dict]


def fit_quantization(
    state: LevelState,
    test: list[tuple[Camera, Tensor]],
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
        decoded = LevelState(quantized(state.stored, steps), state.normals, state.offsets, state.bits)
        value, _ = evaluate(decoded.expanded(), test, background)
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
