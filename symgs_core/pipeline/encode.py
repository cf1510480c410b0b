"""From a state to its archive: the codec fitted to the floor, checked against real renders, and its accounting.

``fit_codec`` predicts (``budget.RateDistortion`` over ``sensitivity``), encodes, decodes and renders the decoded
archive on the fitting views; where the measured error differs from the prediction, the allowed error is rescaled by
their ratio and the choice made again. The archive kept is the smallest whose decode holds the floor. Quantised
archives store each rotation in its canonical frame (``codec.frames``). Preset ``lossless`` stores float32.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera, scene_bounds
from ..codec import ArchiveContents, coding_order, decode_archive, encode_archive, expand_archive
from ..codec.classes import CLASSES, unwrapped
from ..codec.frames import canonical_frames
from ..codec.masks import MASKS
from ..codec.order import grid_cells
from ..codec.registry import ATTRIBUTE_NAMES, ArchiveCodec, archive_codec
from ..codec.steps import QuantSteps
from ..devices import HOST
from ..metrics import mse_to_psnr, psnr_to_mse
from ..report import CodecReport, Fidelity, StageReport
from ..views import View, evaluate, viewer_cameras
from .budget import Choice, RateDistortion, extent_of
from .sensitivity import sensitivity
from .state import LevelState

_LOSSLESS = CodecReport("lossless", None, None, 0)
MAX_CHECKS = 4  # renders of a decoded archive per fit
PRUNE_SHARES = (1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4)  # shares of the stored set pruning tries, rendered
_AIM = 0.9  # of the allowed error the first choice aims at: the model errs by tens of percent either way
FitProgress = Callable[[float, str], None]  # (share of the fit done, what it is doing)
_CLOSE = 0.8  # a passing archive that measures at least this share of the allowed error is kept without retrying
_SAME = 0.03  # targets this close (relatively) give about one choice: aiming again at one is no new try


# Cameras of the sensitivity's coverage: 32 at 96 px add a sixth to the fitting views' pixels. On the lego scene
# trained from its photographs (32k Gaussians) the fitting cameras alone left Gaussians unseen that the evaluation
# cameras see: pruned, they cost 9-10 dB there (37.7 dB where the fitting cameras measured 47.1); with the coverage,
# with step classes too, 47.2 dB (46.7 on the fitting cameras) in 19% fewer bytes. On kacytran bytes stay within 1%.
COVERAGE_VIEWS, COVERAGE_RESOLUTION = 32, 96
COVERAGE_SEED = 4  # the job's rigs use 1..3 (``views``)


def coverage_cameras(state: LevelState) -> list[Camera]:
    """Low-resolution cameras all around the state's scene, from directions no rig of the job uses: the sensitivity
    counts what they see, so Gaussians the fitting cameras miss are neither pruned nor coarsened for that alone."""
    center, radius = scene_bounds(state.stored.means.detach(), state.stored.scales.detach())
    return viewer_cameras(center, radius, COVERAGE_VIEWS, COVERAGE_RESOLUTION, seed=COVERAGE_SEED, name="coverage")


def write_archive(
    state: LevelState, meta: dict, codec: str | ArchiveCodec = "lossless", classes: Tensor | None = None
) -> bytes:
    """The archive of ``state`` in coding order, written by ``codec`` (an archive codec or a registered name), each
    stored Gaussian in its step class (``classes`` [|S|] int64; None: class 0)."""
    stored, bits = state.stored.detach().to(HOST), state.bits.to(HOST)  # the entropy coders run on the host
    codec = archive_codec(codec)
    if not any(unwrapped(c)[1] for name, c in codec.sections.items() if name in ATTRIBUTE_NAMES):
        # No section takes the classes: they would only cost their order (``coding_order`` sorts by them first).
        codec, classes = replace(codec, sections={k: unwrapped(c)[0] for k, c in codec.sections.items()}), None
    classes = None if classes is None else classes.to(HOST)
    means, classed = unwrapped(codec.sections["means"])
    cells = grid_cells(means, stored.means.numpy(),
                       None if classes is None or not classed else classes.numpy().astype(np.uint8))  # fmt: skip
    perm = coding_order(stored, bits, cells, classes)
    ordered = None if classes is None else classes[perm]
    return encode_archive(ArchiveContents(stored.select(perm), state.planes, bits[perm], meta, ordered), codec=codec)


def canonical(state: LevelState) -> LevelState:
    """``state`` with each stored rotation in its frame closest to the identity (``codec.frames``)."""
    return LevelState(canonical_frames(state.stored.detach()), state.normals, state.offsets, state.bits)


@dataclass
class Fitted:
    """A state's archive: the state as stored (after reductions), the bytes, and how they were found."""

    state: LevelState
    archive: bytes
    psnr: float  # measured on the fitting views, the worse of full frame and object pixels
    codec: CodecReport
    steps: QuantSteps | None = None  # None: float32
    writer: ArchiveCodec | None = None
    choice: Choice | None = None
    unreduced: LevelState | None = None  # the state before pruning and SH reduction (canonical frames)
    kept: Tensor | None = None  # [M] indices of ``unreduced`` that pruning kept
    pruned: float = 0.0  # the measured growth of the fitting MSE from the Gaussians left out
    removed: int = 0  # Gaussians left out
    dropped_bands: int = 0  # SH bands left out, over every Gaussian
    tries: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    rd: RateDistortion | None = None  # the rate model the codec was chosen by (``rate_model``); see ``release``
    classes: Tensor | None = None  # [|unreduced|] int64 step classes the codec chose (None: class 0)
    allowed: float = 0.0  # the growth of the fitting MSE the floor left the codec
    fitting: Fidelity | None = None  # the archive's decode on the fitting views, SSIM too (None: not rendered)

    def classes_of(self, kept: Tensor | None = None) -> Tensor | None:
        """Step classes of ``unreduced``'s Gaussians (those of ``kept`` [M] indices, or all), as the codec chose."""
        if self.classes is None:
            return None
        return self.classes if kept is None else self.classes[kept.to(self.classes.device)]

    def release(self) -> None:
        """Let the rate model go once no level is left to judge: after the levels only its step classes are asked
        for, and it is the largest thing a fit holds (a sorted copy of the scene, float64 weights, the SH palette's
        keys: about 1 GB at 1M Gaussians with SH 3), held until the report's own archives are written."""
        self.rd = None


def _without(state: LevelState, keep: Tensor) -> LevelState:
    keep = keep.to(state.stored.device)
    return LevelState(state.stored.select(keep), state.normals, state.offsets, state.bits[keep.to(state.bits.device)])


def _excess(state: LevelState, fit: Sequence[View], background: Tensor, psnr_before: float) -> float:
    """Growth of the fitting MSE from ``psnr_before`` to ``state``'s renders."""
    return psnr_to_mse(evaluate(state.expanded(), fit, background, with_ssim=False).worst) - psnr_to_mse(psnr_before)


# Training views that also judge pruning (at most this many, spread over the set). The order picks the Gaussians the
# fitting and coverage cameras see least: the views that chose them cannot tell what their absence costs elsewhere.
# On the lego trained from its photographs (32k Gaussians), `--preset high --psnr-budget 0.00194`: pruning judged on
# the fitting views alone left out 1,015 Gaussians and scored 53.9-64.1 dB on four evaluation rigs (fitting views:
# 67.6 dB); without pruning, 1.9% more bytes, 67.3-68.3 dB.
CHECK_VIEWS = 16


def check_views(train: Sequence[View], count: int = CHECK_VIEWS) -> list[View]:
    """At most ``count`` of ``train``, evenly spread over it."""
    step = len(train) / max(min(count, len(train)), 1)
    return [train[int(i * step)] for i in range(min(count, len(train)))]


def prune(
    state: LevelState, rd: RateDistortion, fit: Sequence[View], background: Tensor, *, allowed: float,
    psnr_before: float, check: Sequence[View] = (), should_stop=None,  # noqa: ANN001
) -> tuple[Tensor, float]:
    """How many of the Gaussians the renders miss least to leave out: for shares 1/4 .. 1/64 of the stored set,
    the error of their absence is rendered (their errors add up coherently, so no model predicts it), the codec
    priced on what is left of the budget, and the share with the fewest predicted bits kept. Returns the keep mask
    [N] and the measured error.

    The error is the larger of the fitting views' and the ``check`` views' (which played no part in the order), and
    of the coverage cameras' prediction. The largest share first: a share is rendered only when the codec, given the
    whole budget as if its absence cost nothing, would still price it below the best so far (fewer bits never need
    more error). A share whose absence takes half the budget or more is not kept: the quantiser needs the rest."""
    n = len(state.stored)
    order = rd.prune_order()
    keep_all = torch.ones(n, dtype=torch.bool, device=HOST)  # masks over the rate model's set, which lives there
    best = (rd.choose(_AIM * allowed).bits, keep_all, 0.0)
    predicted = rd.sens.removal(rd.stored.opacities)  # [N] in the rate model's order
    # The state's own PSNR on ``check``, rendered once a share needs it; where the fitting views are its own renders
    # (``psnr_before`` infinite: targets rendered from the input), so are the check views' targets.
    checked: float | None = psnr_before if math.isinf(psnr_before) else None
    for share in reversed(PRUNE_SHARES):
        if should_stop is not None and should_stop():
            break
        keep = keep_all.clone()
        keep[order[: int(share * n)]] = False
        if rd.choose(_AIM * allowed, keep=keep).bits >= best[0]:
            continue  # even free, this share would not pay
        without = _without(state, keep)
        removed = max(_excess(without, fit, background, psnr_before), float(predicted[~keep[rd.order]].sum()))
        if check and removed < 0.5 * allowed:
            if checked is None:
                checked = evaluate(state.expanded(), check, background, with_ssim=False).worst
            removed = max(removed, _excess(without, check, background, checked))
        if removed >= 0.5 * allowed:
            continue
        bits = rd.choose(_AIM * allowed - removed, keep=keep).bits
        if bits < best[0]:
            best = (bits, keep, removed)
    return best[1], best[2]


def _identity(choice: Choice) -> tuple:
    """What makes two choices one archive: each section's codec (its steps) and each Gaussian's SH degree."""
    degrees = None if choice.degrees is None else choice.degrees.cpu().numpy().tobytes()
    return tuple(sorted((section, repr(codec)) for section, codec in choice.codecs.items())), degrees


def fit_codec(
    state: LevelState,
    fit: Sequence[View],
    background: Tensor,
    *,
    floor: float,
    psnr_before: float,
    start: QuantSteps | None,
    meta: dict,
    name: str,
    check: Sequence[View] = (),
    should_stop=None,  # noqa: ANN001 - Callable[[], bool], checked between renders
    progress: FitProgress | None = None,
) -> Fitted:
    """The smallest archive of ``state`` whose decode keeps ``floor`` on ``fit``; ``psnr_before`` is ``state``'s
    own. ``check``: views that also judge what pruning leaves out (``prune``). ``start`` None, or no room under the
    floor: float32 (lossless)."""
    t0 = time.perf_counter()
    allowed = psnr_to_mse(floor) - psnr_to_mse(psnr_before)
    if start is None or not math.isfinite(floor) or allowed <= 0:
        return Fitted(state, write_archive(state, meta), psnr_before, _LOSSLESS, seconds=time.perf_counter() - t0)
    # Parts of the fit's progress as its steps took its time at 250k and 1M on 2 cores: the sensitivity a third, the
    # pruning's choices (the rate model's first pricing of every ladder) two fifths, then the checks.
    tell = progress or (lambda within, message: None)
    state = canonical(state)
    tell(0.0, "measuring how the renders respond to each attribute")
    sens = sensitivity(state, fit, background, coverage=coverage_cameras(state))
    tell(0.35, "rate of each quantiser")
    rd = RateDistortion(state.stored, sens, start)
    del sens  # the rate model holds its own, in coding order: at 1M Gaussians with SH 3 each copy is 450 MB
    tell(0.4, "how many Gaussians the renders miss least")
    keep, pruned = prune(state, rd, fit, background, allowed=allowed, psnr_before=psnr_before, check=check,
                         should_stop=should_stop)  # fmt: skip
    best: Fitted | None = None
    tries: list[dict]
    target, tries = _AIM * allowed - pruned, []
    # Each choice's decode on the fitting views (the model may give a choice again for a new target), SSIM too: the
    # report's fitting scores are then the kept archive's, not 16 more renders.
    measured: dict[tuple, Fidelity] = {}
    held, missed = 0.0, math.inf  # the largest target whose archive held the floor, the smallest whose did not
    for round_ in range(MAX_CHECKS):
        if should_stop is not None and should_stop():
            break
        choice = rd.choose(target, keep=keep)
        if choice.error > target:
            break  # nothing quantised fits: float32 below
        key, improved = _identity(choice), False
        if key not in measured:
            tell(0.8 + 0.2 * round_ / MAX_CHECKS, f"encoding and checking against renders ({len(tries) + 1})")
            kept, stored = rd.apply(choice)
            candidate = LevelState(stored, state.normals, state.offsets, state.bits[kept.to(state.bits.device)])
            codec = ArchiveCodec(name, {**choice.codecs, "bits": MASKS, "classes": CLASSES})
            archive = write_archive(candidate, meta, codec, rd.classes[kept])
            decoded = expand_archive(decode_archive(archive)).to(state.stored.device)
            measured[key] = evaluate(decoded, fit, background)
            del decoded  # each check's scenes go before the next is made: at 1M Gaussians with SH 3, 220 MB each
            tries.append({"predicted_psnr": mse_to_psnr(psnr_to_mse(psnr_before) + pruned + choice.error),
                          "psnr": measured[key].worst, "bytes": len(archive)})  # fmt: skip
            if measured[key].worst >= floor and (best is None or len(archive) < len(best.archive)):
                dropped = 0
                if choice.degrees is not None:
                    dropped = int((stored.sh_degree - choice.degrees[choice.keep]).clamp_min(0).sum())
                steps = rd.steps(choice)
                best = Fitted(candidate, archive, measured[key].worst, CodecReport(name, steps.report(), floor, 0),
                              steps, codec, choice, state, kept, pruned=pruned,
                              removed=len(state.stored) - len(stored), dropped_bands=dropped, rd=rd,
                              classes=rd.classes, allowed=allowed, fitting=measured[key])  # fmt: skip
                improved = True
            del candidate, stored
        excess = psnr_to_mse(measured[key].worst) - psnr_to_mse(psnr_before)
        if measured[key].worst >= floor:
            held = max(held, target)
        else:
            missed = min(missed, target)
        if improved and excess >= _CLOSE * allowed:
            break
        # Rescale the codec's model by what the renders measured beyond the pruning, aiming again at ``_AIM``.
        ratio = max(excess - pruned, 1e-30) / max(choice.error, 1e-30)
        aim = min(max((_AIM * allowed - pruned) / ratio, target / 8.0), target * 8.0)
        # Only a target between the two can improve: at or below one that held the floor the steps are finer and the
        # archive larger; at or above one that missed it, it misses again (the ratio drifts where the renders are
        # not linear in the steps: playbot at 2M aimed below its kept archive's target after a miss, one try wasted).
        # (Within ``_SAME`` of either counts as the same target: a rescale that lands on the missed target itself, but
        # for rounding, would render its archive again.)
        if aim <= held * (1.0 + _SAME):
            break
        if aim >= missed * (1.0 - _SAME):
            aim = math.sqrt(missed * max(held, missed / 8.0))
        if abs(aim / target - 1.0) < _SAME:
            break
        target = aim
    if best is None:
        best = Fitted(state, write_archive(state, meta), psnr_before, _LOSSLESS)
    best.tries, best.seconds = tries, time.perf_counter() - t0
    best.codec = CodecReport(best.codec.name, best.codec.steps, best.codec.floor, len(tries))
    return best


@dataclass(frozen=True)
class Rate:
    """(``psnr_from``, ``psnr_to``) -> the predicted ratio of archive bytes were a state's fitting PSNR ``psnr_to``
    instead of ``psnr_from`` (``rate_model``). ``no_room``: fitting PSNRs at or below it leave the codec nothing of
    the floor's budget (ratio inf from any ``psnr_from`` above it); -inf where no PSNR is known to."""

    ratio: Callable[[float, float], float]
    no_room: float = -math.inf

    def __call__(self, psnr_from: float, psnr_to: float) -> float:
        return self.ratio(psnr_from, psnr_to)


def rate_model(fitted: Fitted, floor: float) -> Rate:
    """The size ratio of ``fitted``'s state coded to ``floor``, as a function of (``psnr_from``, ``psnr_to``):
    predicted bytes were its own fitting PSNR ``psnr_to`` instead of ``psnr_from``, over its bytes at ``psnr_from``;
    by the rate model it was fitted with, calibrated as it was. Each PSNR's bits are priced once: the level loop asks
    about every membership from the same state.

    What a change to the state costs in budget, it costs in bytes: the codec gets only the MSE the floor leaves.
    ``inf`` where nothing is left."""
    rd, choice = fitted.rd, fitted.choice
    if rd is None or choice is None or fitted.allowed <= 0:
        raise ValueError("the state was not fitted with a rate model (float32 or fixed steps)")
    pruned = fitted.pruned
    calibration = choice.error / max(_AIM * fitted.allowed - pruned, 1e-300)

    @functools.cache
    def bits(psnr: float) -> float:
        target = calibration * (_AIM * (psnr_to_mse(floor) - psnr_to_mse(psnr)) - pruned)
        if target <= 0:
            return math.inf
        at = rd.choose(target, keep=choice.keep)
        return at.bits if at.error <= target else math.inf

    def ratio(psnr_from: float, psnr_to: float) -> float:
        before = bits(psnr_from)
        return bits(psnr_to) / before if math.isfinite(before) and before > 0 else 1.0

    left = psnr_to_mse(floor) - pruned / _AIM  # the MSE at which ``bits``' target reaches 0
    return Rate(ratio, mse_to_psnr(left) if left > 0 else math.inf)


def fixed_codec(
    state: LevelState, fit: Sequence[View], background: Tensor, *, steps: QuantSteps, meta: dict, name: str
) -> Fitted:
    """``state`` written at ``steps`` as they are: one encode, nothing searched or reduced (a preset that is not
    ``fitted``); the decode's PSNR on ``fit`` is measured for the report, not held to a floor."""
    t0 = time.perf_counter()
    state = canonical(state)
    writer = steps.archive_codec(extent_of(state.stored), name)
    archive = write_archive(state, meta, writer)
    decoded = expand_archive(decode_archive(archive)).to(state.stored.device)
    fitting = evaluate(decoded, fit, background)
    return Fitted(state, archive, fitting.worst, CodecReport(name, steps.report(), None, 0), steps, writer,
                  seconds=time.perf_counter() - t0, fitting=fitting)  # fmt: skip


def fitted_baseline(plain: LevelState, fitted: Fitted, meta: dict) -> bytes:
    """The codec alone on the input: the plain state written by the archive's own codec, nothing reduced, in the
    step classes the codec chose where it was fitted to that state (else class 0)."""
    if fitted.writer is None:
        return write_archive(plain, meta)
    same = fitted.unreduced is not None and not fitted.unreduced.normals.shape[0]
    return write_archive(canonical(plain), meta, fitted.writer, fitted.classes_of() if same else None)


def stages(
    source: LevelState, mirrored: LevelState, fitted: Fitted, *, reference: float, mirrored_psnr: float, meta: dict,
    seconds: dict[str, float], baseline: bytes,
) -> list[StageReport]:
    """Where the size went, each stage measured on archives: the mirrors on float32 archives, then quantisation,
    pruning and SH reduction with the final codec. The codec chose all three at one price; the PSNR after the
    middle two is the model's prediction (``predicted``), the first and last are rendered. ``baseline``: the plain
    state written by the final codec (``fitted_baseline``), which is the quantisation stage's archive when no mirror
    was kept."""
    lossless_in = len(write_archive(source, meta))
    lossless_mirrored = len(write_archive(mirrored, meta)) if mirrored.normals.shape[0] else lossless_in
    out = [_stage("mirrors", lossless_in, lossless_mirrored, reference, mirrored_psnr, seconds.get("levels", 0.0))]
    final = len(fitted.archive)
    if fitted.choice is None or fitted.unreduced is None or fitted.writer is None or fitted.kept is None:
        out.append(_stage("entropy_coding", lossless_mirrored, final, mirrored_psnr, fitted.psnr, fitted.seconds))
        return out
    base = psnr_to_mse(mirrored_psnr)
    errors = fitted.choice.errors
    errors = {**errors, "pruning": fitted.pruned}
    predicted = lambda *parts: mse_to_psnr(base + sum(errors[p] for p in parts))  # noqa: E731
    unreduced = fitted.unreduced
    pruned = LevelState(unreduced.stored.select(fitted.kept), unreduced.normals, unreduced.offsets,
                        unreduced.bits[fitted.kept.to(unreduced.bits.device)])  # fmt: skip
    quantised = len(baseline) if not mirrored.normals.shape[0] else len(
        write_archive(unreduced, meta, fitted.writer, fitted.classes_of()))
    pruned_bytes = len(write_archive(pruned, meta, fitted.writer, fitted.classes_of(fitted.kept))) if fitted.removed \
        else quantised
    out.append(_stage("quantization", lossless_mirrored, quantised, mirrored_psnr, predicted("codec"),
                      fitted.seconds, predicted=True))  # fmt: skip
    out.append(_stage("pruning", quantised, pruned_bytes, predicted("codec"), predicted("codec", "pruning"), 0.0,
                      removed=fitted.removed, predicted=True))  # the pruning's own error was rendered  # fmt: skip
    out.append(_stage("sh_reduction", pruned_bytes, final, predicted("codec", "pruning"), fitted.psnr, 0.0,
                      removed=fitted.dropped_bands))  # fmt: skip
    return out


def _stage(name: str, before: int, after: int, psnr_before: float, psnr_after: float, seconds: float,
           **extra: int | bool) -> StageReport:  # fmt: skip
    cost = psnr_before - psnr_after if math.isfinite(psnr_before) and math.isfinite(psnr_after) else None
    return StageReport(name, before, after, before - after, psnr_after, cost, seconds, **extra)  # type: ignore[arg-type]
