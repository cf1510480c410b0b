"""The level loop: detect a mirror in the working set, drop its right side, fine-tune what it changed, and keep it only
if the archive with it is smaller than the best archive so far at the same fidelity.

Each level is judged by bytes: the state after the fine-tune must hold the floor on the fitting views, and then its
whole archive (``judge``: the codec fitted to what the floor leaves, quantisation, pruning, SH bands) must be smaller
than the best prefix of levels so far, the plain codec's to begin with. A level that is not smaller is rolled back and
the next candidate tried; the search stops at the first level none of whose candidates pays. The scene decides how
many levels it gets, and a scene without symmetry keeps the plain codec's archive.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ..cameras import Focus, focus, scene_bounds
from ..codec.steps import QuantSteps
from ..config import CompressConfig
from ..devices import HOST
from ..mirror import Plane, reflect
from ..report import LevelReport
from ..scene import GaussianScene
from ..views import ViewSet, evaluate, worst_psnr
from .checkpoint import Checkpoint, load_checkpoint, save_checkpoint, scene_fingerprint
from .encode import FitProgress, Fitted, Rate, rate_model
from .gating import colour_mismatch, gated
from .job import TUNE_SHARE, Job, Reporter, grown, level_share
from .optimize import halo, optimize_level
from .pace import Pace, Stretches
from .refine import Refined
from .state import LevelState

# Colour-agreement gates (largest RGB channel difference) tried after the geometric membership, loosest first.
GATES = (0.3, 0.2, 0.1)
# A level must drop at least this share of its working set to be worth its plane, mask and fine-tune.
MIN_SAVING = 0.02
# dB a fine-tune is credited with, against the upload's own renders, when deciding whether to run one: a membership
# that would not pay even this much better than it starts is not tried. Forced, fine-tunes recover more against the
# real scans' own renders, yet what this leaves out there paid at most 0.2% (BENCHMARKS, "Real scenes"). Against
# photographs nothing is credited: each membership's own fine-tune is measured stretch by stretch (``Pace``). On the
# lego trained from its photographs, the detected membership starts 3.4 dB under the floor and gains 3.6 dB in its
# first stretch, 4.2 dB in all: the credit had left out the membership that paid most.
TUNE_GAIN = 3.0
# Fine-tunes tried per level before the level is given up.
MAX_ATTEMPTS = 2
# Neighbours within this many local spacings of a mirror's two sides move with them in its fine-tune.
HALO_SPACINGS = 3.0
# Against renders of the input, a membership that, as it starts, costs the codec less than this share of its bytes (by
# the rate model) is judged without a fine-tune: bringing it all the way back could save no more, and on near-exact
# twins a fine-tune only burns minutes before it is rolled back. Against photographs a fine-tune may gain beyond the
# input itself, so there every membership is fine-tuned, for as long as its pace says it may pay (``Pace``).
SETTLED_COST = 0.005
# A mirror whose reflection would stand in for at least this share of the scene, found but not kept against the
# upload's own renders, is worth telling the user about: their photographs might make it pay.
NOTABLE_SHARE = 0.05


@dataclass(frozen=True)
class Membership:
    """One way to apply a detected mirror: the plane, the Gaussians reflected (left) and dropped (right), and the
    colour-agreement gate that produced it (None: geometry alone)."""

    plane: Plane
    left: torch.Tensor  # [L] indices into the working set
    right: torch.Tensor  # [R]
    votes: float
    coverage: float
    gate: float | None
    found_in: str = "scene"  # ``detect.Mirror.found_in``


def consistent_bits(state: LevelState, plane: Plane, left: torch.Tensor,
                    right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """``left`` and ``right`` with the pairs whose earlier-level bits differ taken out.

    A dropped (right) Gaussian is replaced at decode by the reflection of the left one covering it, and that
    reflection inherits its source's bits: where the two disagree on an earlier level, the decode would lose a copy
    the dropped Gaussian had, or make one it never had. So a right Gaussian is dropped only when the left Gaussian
    whose reflection lands nearest carries the same earlier bits, and a left Gaussian is reflected only when the
    right one nearest its reflection is dropped."""
    if state.bits.shape[1] == 0 or left.numel() == 0 or right.numel() == 0:
        return left, right
    with torch.no_grad():
        normal, _ = plane.tensor(HOST)
        mirrored = reflect(state.stored.select(left).detach().to(HOST), normal, plane.offset).means.numpy()
    dropped = state.stored.means.detach()[right.to(state.stored.device)].cpu().numpy()
    _, nearest_left = cKDTree(mirrored).query(dropped, k=1)
    _, nearest_right = cKDTree(dropped).query(mirrored, k=1)
    bits = state.bits.cpu()
    agree = (bits[right.cpu()] == bits[left.cpu()][torch.from_numpy(nearest_left)]).all(dim=1)
    return gated(left, right, ~agree * 1.0, torch.from_numpy(nearest_right).reshape(-1), 0.5)


def apply_mirror(
    state: LevelState, plane: Plane, left: torch.Tensor, right: torch.Tensor
) -> LevelState:
    """The next level's state: ``right`` members dropped, ``left`` marked in a new bit column, the plane appended.

    ``left`` and ``right`` index the current stored set.
    """
    n = len(state.stored)
    device = state.stored.device
    keep = torch.ones(n, dtype=torch.bool, device=device)
    keep[right.to(device)] = False
    is_left = torch.zeros(n, dtype=torch.bool, device=device)
    is_left[left.to(device)] = True
    if bool((is_left & ~keep).any()):
        raise ValueError("a Gaussian cannot be both left and right of one mirror")
    dtype = state.normals.dtype
    return LevelState(
        stored=state.stored.select(keep),
        normals=torch.cat([state.normals, plane.tensor(device)[0].to(dtype).reshape(1, 3)]),
        offsets=torch.cat([state.offsets, torch.tensor([plane.offset], device=device, dtype=dtype)]),
        bits=torch.cat([state.bits[keep], is_left[keep][:, None]], dim=1),
    )


def memberships(state: LevelState, mirror) -> list[Membership]:  # noqa: ANN001 - detect.Mirror
    """The detected membership, then ever stricter colour-agreement gates of it (``GATES``), loosest first; every
    one with its earlier-level bits made consistent (``consistent_bits``)."""
    plane = mirror.plane
    left, right = consistent_bits(state, plane, mirror.left, mirror.right)
    coverage = (left.numel() + right.numel()) / max(len(state.stored), 1)
    base = Membership(plane, left, right, float(mirror.votes), coverage, None, mirror.found_in)
    mismatch, nearest = colour_mismatch(state.stored, plane, left, right)
    out = [base]
    for gate in GATES:
        gated_left, gated_right = gated(left, right, mismatch, nearest, gate)
        if gated_right.numel() == out[-1].right.numel():  # the gate changed nothing (twins agree everywhere)
            continue
        coverage = (gated_left.numel() + gated_right.numel()) / max(len(state.stored), 1)
        out.append(Membership(plane, gated_left, gated_right, base.votes, coverage, gate, mirror.found_in))
    return out


def _spacing(means: torch.Tensor) -> float:
    """Median distance to the nearest neighbour over a sample of at most 20,000 points."""
    points = means.detach().cpu().numpy()
    if len(points) < 2:
        return math.inf
    sample = points[:: max(1, len(points) // 20_000)]
    distances, _ = cKDTree(points).query(sample, k=2)
    return float(max(float(torch.from_numpy(distances[:, 1]).median()), 1e-12))


@dataclass(frozen=True)
class Attempt:
    """A membership to try: its PSNR before the fine-tune and, with a rate model, the bytes its archive is
    predicted at should the fine-tune gain ``TUNE_GAIN`` dB (None: no model), and whether it is ``settled``: it costs
    the codec so little as it starts (``SETTLED_COST``) that no fine-tune could pay for its minutes. A ``probed``
    one (against photographs, where a fine-tune may gain beyond the input itself) is fine-tuned whatever it starts
    at, and its fine-tune stops once its own pace says it cannot pay (``Pace``)."""

    membership: Membership
    psnr_before: float  # with ``bounded``, a bound: the PSNR is at most this
    predicted: float | None
    settled: bool = False
    bounded: bool = False
    probed: bool = False

    def pays(self, floor: float, best_bytes: int) -> bool:
        if self.probed:
            return True
        if self.predicted is not None:
            return self.predicted < best_bytes
        return not hopeless(self.psnr_before, floor)


def plan_attempts(
    state: LevelState, psnr: float, options: list[Membership], views: ViewSet, *, floor: float, rate: Rate | None,
    best_bytes: int, photographs: bool = False,
) -> list[Attempt]:
    """The memberships to consider (at most ``MAX_ATTEMPTS``), those that may pay first, the smallest predicted
    archive first (without a rate model, the loosest). Against ``photographs`` every membership may pay: those that
    drop the most Gaussians go first, each probed by its own fine-tune (``Attempt.probed``).

    A membership must drop enough Gaussians to pay for a level (``MIN_SAVING`` of the working set). One that
    cannot pay is listed but not fine-tuned: with a rate model (``rate``), when even ``TUNE_GAIN`` dB more than it
    starts at would leave the codec too little of the budget to make the archive smaller than ``best_bytes`` (a
    mirror spends the same error the quantiser needs); without, when it starts more than ``TUNE_GAIN`` dB below the
    floor. Nor is one already ``settled`` (``SETTLED_COST``; never against ``photographs``): it is judged as it
    starts. A fine-tune costs minutes on a large scene, and the rate model a few encodes.
    """
    worth = [m for m in options if m.right.numel() >= MIN_SAVING * len(state.stored)]
    # Below this start no fine-tune can pay (``hopeless``, or no room left under the floor even TUNE_GAIN dB up):
    # rendering stops once the fitting views seen so far put a membership there.
    lowest = floor if rate is None else rate.no_room if psnr > rate.no_room else -math.inf
    attempts = []
    for m in worth:
        candidate = apply_mirror(state, m.plane, m.left, m.right)
        if photographs:
            before = evaluate(candidate.expanded(), views.fit, views.background, with_ssim=False).worst
            attempts.append(Attempt(m, before, None, probed=True))
            continue
        share = len(candidate.stored) / max(len(state.stored), 1)
        predict = None if rate is None else functools.partial(_predicted, rate, psnr, best_bytes * share)
        before, bounded = _start(candidate, views, lowest - TUNE_GAIN, predict, best_bytes)
        predicted = None if predict is None else predict(before)
        settled = rate is not None and not photographs and rate(psnr, min(before, psnr)) <= 1.0 + SETTLED_COST
        attempts.append(Attempt(m, before, predicted, settled, bounded=bounded))

    def rank(a: Attempt) -> tuple[bool, float, float]:  # stable: loosest first where no model ranks them
        if a.probed:
            return False, -float(a.membership.right.numel()), -a.psnr_before
        if a.predicted is None:
            return not a.pays(floor, best_bytes), 0.0, 0.0
        return not a.pays(floor, best_bytes), a.predicted, -a.psnr_before  # then the closest to the floor first

    return sorted(attempts, key=rank)[:MAX_ATTEMPTS]


def _predicted(rate: Rate, psnr: float, now: float, before: float) -> float:
    """The bytes of a membership's archive (``now`` at the state's PSNR ``psnr``) should its fine-tune take it
    ``TUNE_GAIN`` dB above ``before``, where it starts."""
    return now * rate(psnr, min(before + TUNE_GAIN, psnr))


def _start(
    candidate: LevelState, views: ViewSet, below: float, predict: Callable[[float], float] | None, best_bytes: int
) -> tuple[float, bool]:
    """A membership's fitting PSNR as it starts, and whether that is a bound: its renders stop once the views so far
    put it below ``below`` or, with a rate model (``predict``), once a start no higher than they allow cannot pay
    (the prediction only grows as the start falls): most memberships of a scene that keeps no level."""
    cut: list[float] = []

    def unpaid(bound: float) -> bool:
        assert predict is not None
        if predict(bound) < best_bytes:
            return False
        cut.append(bound)
        return True

    before = worst_psnr(candidate.expanded(), views.fit, views.background, below=below,
                        settled=None if predict is None else unpaid)  # fmt: skip
    return before, before < below or bool(cut)


def hopeless(psnr_before: float, floor: float) -> bool:
    """Whether a membership starts too far below the floor for a fine-tune to bring it back (``TUNE_GAIN``)."""
    return psnr_before < floor - TUNE_GAIN


Judge = Callable[[LevelState, float, FitProgress | None], Fitted]  # (state, its fitting PSNR, progress) -> archive


def tune(
    state: LevelState,
    candidate: LevelState,
    membership: Membership,
    views: ViewSet,
    *,
    start: float,
    level: int,
    config: CompressConfig,
    extent: float,
    spacing: float,
    steps: QuantSteps | None,
    report: Reporter,
    pace: Pace | None = None,
    span: tuple[float, float] = (0.0, 1.0),
) -> tuple[LevelState, float, int, bool]:
    """Fine-tune what ``membership`` changed in ``candidate`` (its left side and the neighbours of both sides, and
    the new plane) in stretches while they gain and, with ``pace``, while it says the level may still pay; returns
    the tuned state, its fitting PSNR, the steps run and whether ``pace`` stopped it. ``start``: ``candidate``'s
    fitting PSNR, as the plan rendered it (``Attempt.psnr_before``, exact for every membership it lets run);
    ``span``: the part of the levels' share of the bar its steps move across."""
    region = torch.cat([membership.left, membership.right])
    trainable = halo(state.stored, region, candidate.stored, radius=HALO_SPACINGS * spacing)
    stretches = Stretches(views, start, config.iterations, pace)
    lo, hi = span

    def on_step(step: int, loss: Tensor) -> None:
        if step % 10 == 0:
            report("levels", lo + (hi - lo) * step / max(config.iterations, 1),
                   f"level {level}: step {step}/{config.iterations} loss {float(loss):.4f}", level)  # fmt: skip

    torch.manual_seed(config.seed + 1000 * (level + 1))
    tuned, run = optimize_level(
        candidate, views.train, views.background, iterations=config.iterations, extent=extent, trainable=trainable,
        steps=steps, seed=config.seed + level, check_every=stretches.every, keep_going=stretches,
        should_stop=report.should_stop, on_step=on_step,
    )  # fmt: skip
    psnr = stretches.fitting_psnr(tuned, run)
    if psnr < start:  # the fine-tune must pay for itself too: exact twins need none
        return candidate.detach(), start, run, stretches.cut
    return tuned, psnr, run, stretches.cut


def _unpaid(attempt: Attempt, floor: float, best_bytes: int) -> str:
    """Why ``attempt`` was not fine-tuned."""
    start = f"not fine-tuned: it starts {'no higher than' if attempt.bounded else 'at'} {attempt.psnr_before:.2f} dB"
    if attempt.predicted is None:
        return f"{start}, more than {TUNE_GAIN:g} dB below the floor {floor:.2f} dB"
    if not math.isfinite(attempt.predicted):
        return f"{start}; even {TUNE_GAIN:g} dB more would leave the codec no room under the floor {floor:.2f} dB"
    return (f"{start}; even {TUNE_GAIN:g} dB more would leave the codec so little of the budget that the archive "
            f"is predicted at {'no less than ' if attempt.bounded else ''}{attempt.predicted:,.0f} bytes, not below "
            f"{best_bytes:,}")


def level_notes(records: list[LevelReport], gaussians: int, *, photographs: bool) -> tuple[str, ...]:
    """What a user can do about the mirrors of ``records`` (the levels tried on a scene of ``gaussians``).

    Without photographs the reference is the upload's own renders, where a reflected half must match the half it
    replaces; halves that are two reconstructions of one symmetric object do not, though against photographs of it
    the reflection may render as well as the half it replaces (BENCHMARKS, "Against the truth")."""
    if photographs or not records or any(r.accepted for r in records):
        return ()
    largest = max(r.right for r in records)
    if largest < NOTABLE_SHARE * gaussians:
        return ()
    return (
        f"A mirror was found whose reflection would stand in for {largest:,} of the {gaussians:,} Gaussians, but no "
        "mirror level paid against renders of the upload, the reference when no photographs come with it: there a "
        "reflected half must match the half it replaces, and two reconstructions of one symmetric object seldom do. "
        "With the photographs the scene was trained from (symgs compress --images, or images in the API), a "
        "reflection only has to match them, and the mirror may pay.",
    )


@dataclass(frozen=True)
class LevelSearch:
    """What the level loop starts from: the input, its camera sets, the ``floor`` every level holds on the fitting
    views, the ``reference`` (the input's own fitting PSNR: +inf against renders of it, finite against
    photographs), its ``extent`` (radius), the plain codec's ``plain_bytes`` and ``steps`` (which the fine-tunes
    round to, straight-through, so that what they learn survives the codec; None: float32), its ``rate`` model
    (None: none), ``detect_from``: where ``source`` holds no mirror, the scene the first level's is sought in,
    Gaussian for Gaussian ``source``'s (the upload, whose halves the whole fine-tune of ``refine`` trained apart: on
    the CPU-trained lego detection finds no mirror in the fine-tuned scene and one in the upload), and ``focus``:
    what the photographs' cameras look at, searched on its own (``detect``; None: no photographs)."""

    source: GaussianScene
    views: ViewSet
    floor: float
    reference: float
    extent: float
    plain_bytes: int
    steps: QuantSteps | None
    rate: Rate | None = None
    detect_from: GaussianScene | None = None
    focus: Focus | None = None


@dataclass(frozen=True)
class LevelOutcome:
    """The state the levels end on, its fitting PSNR, a record of every level tried, the judged archive of the
    last level accepted in this run (None: no level accepted, or the state was resumed from a checkpoint), and the
    fitting PSNR every level held (``held_floor``)."""

    state: LevelState
    psnr: float
    records: list[LevelReport]
    fitted: Fitted | None
    floor: float


def run_levels(
    search: LevelSearch, *, config: CompressConfig, judge: Judge, report: Reporter, checkpoint: Checkpoint | None
) -> LevelOutcome:
    """Accept mirror levels while each makes the archive smaller (``judge``) at the floor than the best so far, the
    plain codec's to begin with, skipping the fine-tune of memberships that the rate model predicts cannot pay
    (``plan_attempts``); resume from ``checkpoint`` when its fingerprint (the job's inputs) matches."""
    from ..detect import DetectConfig, detect

    source, views, floor, reference = search.source, search.views, search.floor, search.reference
    records: list[LevelReport] = []
    state, psnr, done, best_bytes = LevelState.plain(source), reference, False, search.plain_bytes
    best_fit: Fitted | None = None
    resumed = load_checkpoint(checkpoint, source.device) if checkpoint is not None else None
    if resumed is not None:
        state, records, done, best_bytes = resumed
        if state.normals.shape[0]:
            psnr = evaluate(state.expanded(), views.fit, views.background, with_ssim=False).worst
    detect_config = replace(DetectConfig(), **{**config.detect, "max_mirrors": 1})
    spacing = _spacing(source.means) if config.max_levels else math.inf
    while not done and state.normals.shape[0] < config.max_levels:
        level = state.normals.shape[0]
        report("levels", level_share(level, 0.0), f"level {level}: detecting mirrors", level)
        done = True
        # With photographs, the ball their cameras look at is searched first; where the mirror found there does not
        # pay, the whole scene's (the object's with its surroundings, or a table's, a room's) is tried before the
        # level is given up.
        for aimed in [search.focus, None] if search.focus is not None else [None]:
            t0 = time.perf_counter()
            mirrors = detect(state.stored, detect_config, exclude=state.planes, focus=aimed)
            if not mirrors and level == 0 and search.detect_from is not None:
                mirrors = detect(search.detect_from, detect_config, focus=aimed)
            report.timed("detect", time.perf_counter() - t0)
            options = memberships(state, mirrors[0]) if mirrors else []
            attempts = plan_attempts(state, psnr, options, views, floor=floor, rate=search.rate,
                                     best_bytes=best_bytes, photographs=math.isfinite(reference))  # fmt: skip
            for trial, attempt in enumerate(attempts):
                span = (level_share(level, trial / len(attempts)), level_share(level, (trial + 1) / len(attempts)))
                record, tuned, judged = _try(attempt, state, psnr, best_bytes, search=search, config=config,
                                             judge=judge, report=report, level=level, span=span,
                                             spacing=spacing)  # fmt: skip
                records.append(record)
                if record.accepted:
                    assert record.archive_bytes is not None  # only a judged level is accepted
                    state, psnr, best_bytes, best_fit = tuned, record.psnr_after, record.archive_bytes, judged
                    done = False
                    break
            if not done or not mirrors or mirrors[0].found_in != "focus":
                break
        if checkpoint is not None:
            save_checkpoint(checkpoint, state, records, done, best_bytes)
    report("levels", 1.0, f"{state.normals.shape[0]} mirror level(s) accepted")
    return LevelOutcome(state, psnr, records, best_fit, floor)


def _try(
    attempt: Attempt,
    state: LevelState,
    psnr: float,
    best_bytes: int,
    *,
    search: LevelSearch,
    config: CompressConfig,
    judge: Judge,
    report: Reporter,
    level: int,
    span: tuple[float, float],
    spacing: float,
) -> tuple[LevelReport, LevelState, Fitted | None]:
    """One membership applied to ``state`` (fitting PSNR ``psnr``), fine-tuned unless the plan says it cannot pay or
    need not, and judged by its archive against ``best_bytes``: its record, the state it leaves and its archive (None
    where not judged). ``span``: its part of the levels' share of the bar, most of it the fine-tune's."""
    floor, views = search.floor, search.views
    membership, psnr_before = attempt.membership, attempt.psnr_before
    tuning = (span[0], span[0] + TUNE_SHARE * (span[1] - span[0]))
    t0 = time.perf_counter()
    candidate = apply_mirror(state, membership.plane, membership.left, membership.right)
    skipped, cut = not attempt.pays(floor, best_bytes), False
    if skipped or attempt.settled:
        tuned, psnr_after, run = candidate.detach(), psnr_before, 0
    else:
        pace = None
        if attempt.probed:
            share = len(candidate.stored) / max(len(state.stored), 1)
            pace = Pace(floor, search.rate, psnr, best_bytes * share, best_bytes)
        tuned, psnr_after, run, cut = tune(state, candidate, membership, views, start=psnr_before, level=level,
                                           config=config, extent=search.extent, spacing=spacing,
                                           steps=search.steps, report=report, pace=pace, span=tuning)  # fmt: skip
    report.timed("optimize", time.perf_counter() - t0)
    archive_bytes, judged = None, None
    if skipped:
        accepted, reason = False, _unpaid(attempt, floor, best_bytes)
    elif cut:
        accepted = False
        reason = (f"fine-tuned {run} steps to {psnr_after:.2f} dB, then stopped: at its last stretch's pace "
                  f"it could not {'hold the floor' if psnr_after < floor else 'pay'} "
                  f"(floor {floor:.2f} dB, {best_bytes:,} bytes to beat)")  # fmt: skip
    elif psnr_after < floor:
        accepted, reason = False, f"fitting PSNR {psnr_after:.2f} dB below the floor {floor:.2f} dB"
    else:
        t1 = time.perf_counter()
        encoding = report.part("levels", tuning[1], span[1], f"level {level}: encoding to compare", level)
        judged = judge(tuned, psnr_after, encoding)
        archive_bytes = len(judged.archive)
        report.timed("judge", time.perf_counter() - t1)
        accepted = archive_bytes < best_bytes
        reason = (f"the archive shrinks from {best_bytes:,} to {archive_bytes:,} bytes" if accepted else
                  f"within the floor, but the archive ({archive_bytes:,} bytes) is not smaller than without "
                  f"this level ({best_bytes:,} bytes)")  # fmt: skip
    if attempt.settled and not skipped:
        reason += f"; not fine-tuned: as it starts it costs the codec under {SETTLED_COST:.1%} of its bytes"
    record = LevelReport(
        level=level, normal=(float(tuned.normals[-1, 0]), float(tuned.normals[-1, 1]), float(tuned.normals[-1, 2])),
        offset=float(tuned.offsets[-1]), votes=membership.votes, left=int(membership.left.numel()),
        right=int(membership.right.numel()), coverage=membership.coverage, psnr_before=psnr_before,
        psnr_after=psnr_after, stored_after=len(tuned.stored), seconds=time.perf_counter() - t0,
        accepted=accepted, reason=reason, gate=membership.gate, iterations=run, archive_bytes=archive_bytes,
        found_in=membership.found_in,
    )  # fmt: skip
    return record, tuned, judged


@dataclass(frozen=True)
class Levelled(Refined):
    """``levels``: the state the levels end on (no plane: the plain scene), its fitting PSNR, every level tried, and
    its judged archive (None: the plain codec's, or a state resumed from a checkpoint, not judged in this run)."""

    levels: LevelOutcome


def held_floor(floor: float, plain: Fitted, *, photographs: bool) -> float:
    """The fitting PSNR every mirror level holds: the job's ``floor`` or, against ``photographs``, the plain
    archive's own where that is higher.

    Against photographs the upload's own fine-tune (``refine``) leaves the scene above the floor, on the generated
    captures by several dB, and where the plain codec's coarsest steps cannot spend that its archive stays above the
    floor: a mirror judged at the floor alone could be smaller only for being worse, on photographs its reflection
    never fitted. There levels are judged at the plain archive's fidelity. Against the upload's own renders both
    archives are fitted to the same floor and land above it by the same search's margin (``encode._CLOSE``): holding
    a mirror to the plain archive's landing as well would charge it that margin twice (a planted near-twin mirror
    with as much clutter, BENCHMARKS "Twins with noise": 1.20x at the floor, 1.16x held). A float32 plain archive
    (preset ``lossless``) is exact: there the floor is the budget mirrors may spend."""
    return max(floor, plain.psnr) if photographs and plain.rd is not None else floor


def levels(fitted: Refined, job: Job) -> Levelled:
    config, plain = job.config, fitted.plain
    # Levels are judged by fitted archives: a preset that fits nothing keeps none.
    max_levels = config.max_levels if config.use_mirrors and job.preset.fitted else 0
    _, radius = scene_bounds(fitted.source.means.detach().cpu(), fitted.source.scales)
    floor = held_floor(fitted.floor, plain, photographs=job.photographs)
    search = LevelSearch(
        fitted.source, fitted.views, floor, fitted.reference, radius, len(plain.archive), plain.steps,
        rate_model(plain, floor) if plain.rd is not None else None,
        fitted.upload if fitted.upload is not fitted.source else None,
        # Photographs were taken by someone pointing at what they meant: their cameras frame the object.
        focus([view.camera for view in fitted.views.train]) if math.isfinite(fitted.reference) else None,
    )
    checkpoint = None
    if job.checkpoint_dir is not None:
        checkpoint = Checkpoint(job.checkpoint_dir / "levels.pt", scene_fingerprint(fitted.source, job.settings_digest))
    t0 = time.perf_counter()
    outcome = run_levels(search, config=replace(config, max_levels=max_levels),
                         judge=replace(fitted.codec, floor=floor), report=job.reporter,
                         checkpoint=checkpoint)  # fmt: skip
    job.reporter.timed("levels", time.perf_counter() - t0)
    return grown(fitted, Levelled, levels=outcome)
