"""The level loop: detect a mirror in the working set, drop its right side, fine-tune, and keep it only if the
held-out PSNR stays above the floor; otherwise roll back and stop. The scene decides how many levels it gets."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from ..config import CompressConfig
from ..mirror import Plane
from ..report import LevelReport
from ..scene import GaussianScene
from ..views import ViewSet, evaluate
from .gating import colour_mismatch, gated
from .optimize import optimize_level
from .state import LevelState

# Colour-agreement gates (largest RGB channel difference) tried after the geometric membership, loosest first.
GATES = (0.3, 0.2, 0.1)
# A level must drop at least this share of its working set to be worth its plane, mask and fine-tune.
MIN_SAVING = 0.02
# dB a fine-tune typically recovers on a real capture; memberships starting further below the floor are not tried.
TUNE_GAIN = 3.0
# Fine-tunes tried per level before the level is given up.
MAX_ATTEMPTS = 2


def apply_mirror(
    state: LevelState, normal: torch.Tensor, offset: float, left: torch.Tensor, right: torch.Tensor
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
        normals=torch.cat([state.normals, normal.to(device, dtype).reshape(1, 3)]),
        offsets=torch.cat([state.offsets, torch.tensor([float(offset)], device=device, dtype=dtype)]),
        bits=torch.cat([state.bits[keep], is_left[keep][:, None]], dim=1),
    )


@dataclass(frozen=True)
class Membership:
    """One way to apply a detected mirror: the plane, the Gaussians reflected (left) and dropped (right), and the
    colour-agreement gate that produced it (None: geometry alone)."""

    normal: torch.Tensor  # [3]
    offset: float
    left: torch.Tensor  # [L] indices into the working set
    right: torch.Tensor  # [R]
    votes: float
    coverage: float
    gate: float | None


def memberships(state: LevelState, mirror) -> list[Membership]:  # noqa: ANN001 - detect.Mirror
    """The detected membership, then ever stricter colour-agreement gates of it (``GATES``), loosest first."""
    normal = torch.tensor(mirror.plane.normal, dtype=torch.float32)
    offset = float(mirror.plane.offset)
    base = Membership(normal, offset, mirror.left, mirror.right, float(mirror.votes), float(mirror.coverage), None)
    mismatch, nearest = colour_mismatch(state.stored, normal, offset, mirror.left, mirror.right)
    out = [base]
    for gate in GATES:
        left, right = gated(mirror.left, mirror.right, mismatch, nearest, gate)
        if right.numel() == out[-1].right.numel():  # the gate changed nothing (twins agree everywhere)
            continue
        coverage = (left.numel() + right.numel()) / max(len(state.stored), 1)
        out.append(Membership(normal, offset, left, right, base.votes, coverage, gate))
    return out


def try_level(
    state: LevelState,
    membership: Membership,
    views: ViewSet,
    *,
    level: int,
    config: CompressConfig,
    floor: float,
    extent: float,
    report,  # noqa: ANN001 - pipeline._Reporter
    psnr_before: float | None = None,
) -> tuple[LevelState, LevelReport]:
    """Apply one membership of a mirror, fine-tune and judge it. Returns the candidate state and its record."""
    t0 = time.perf_counter()
    candidate = apply_mirror(state, membership.normal, membership.offset, membership.left, membership.right)
    if psnr_before is None:
        psnr_before = evaluate(candidate.expanded(), views.fit, views.background).worst

    def on_step(step: int, loss: float) -> None:
        if step % 10 == 0:
            report(
                "levels",
                (level + step / max(config.iterations, 1)) / max(config.max_levels, 1),
                f"level {level}: step {step}/{config.iterations} loss {loss:.4f}",
                level,
            )

    torch.manual_seed(config.seed + 1000 * (level + 1))
    tuned = optimize_level(
        candidate,
        views.train,
        views.background,
        iterations=config.iterations,
        extent=extent,
        seed=config.seed + level,
        should_stop=report.should_stop,
        on_step=on_step,
    )
    after = evaluate(tuned.expanded(), views.fit, views.background)
    if after.worst < psnr_before:  # the fine-tune must pay for itself too: exact twins need none
        tuned = candidate.detach()
        after = evaluate(tuned.expanded(), views.fit, views.background)
    psnr_after, ssim_after = after.worst, after.ssim
    accepted = psnr_after >= floor
    record = LevelReport(
        level=level,
        normal=(float(tuned.normals[-1, 0]), float(tuned.normals[-1, 1]), float(tuned.normals[-1, 2])),
        offset=float(tuned.offsets[-1]),
        votes=membership.votes,
        left=int(membership.left.numel()),
        right=int(membership.right.numel()),
        coverage=membership.coverage,
        gate=membership.gate,
        psnr_before=psnr_before,
        psnr_after=psnr_after,
        ssim=ssim_after,
        stored_after=len(tuned.stored),
        seconds=time.perf_counter() - t0,
        accepted=accepted,
        reason="within budget" if accepted else f"held-out PSNR {psnr_after:.2f} dB below the floor {floor:.2f} dB",
    )
    return tuned, record


def plan_attempts(
    state: LevelState, options: list[Membership], views: ViewSet, *, floor: float
) -> list[tuple[Membership, float]]:
    """The memberships worth fine-tuning, loosest first, with their PSNR before the fine-tune.

    A membership must drop enough Gaussians to pay for a level (``MIN_SAVING`` of the working set) and start
    within ``TUNE_GAIN`` dB of the floor (what a fine-tune typically recovers); at most ``MAX_ATTEMPTS`` are tried.
    """
    worth = [m for m in options if m.right.numel() >= MIN_SAVING * len(state.stored)]
    scored = []
    for m in worth:
        candidate = apply_mirror(state, m.normal, m.offset, m.left, m.right)
        scored.append((m, evaluate(candidate.expanded(), views.fit, views.background).worst))
    hopeful = [(m, p) for m, p in scored if p >= floor - TUNE_GAIN]
    if not hopeful and scored:  # none close enough: the strictest still gets its chance
        hopeful = scored[-1:]
    return hopeful[:MAX_ATTEMPTS]


def _save_checkpoint(path: Path, fingerprint: str, state: LevelState, records: list[LevelReport], done: bool) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "fingerprint": fingerprint,
        "stored": {k: v.detach().cpu() for k, v in state.stored.tensors().items()},
        "normals": state.normals.detach().cpu(),
        "offsets": state.offsets.detach().cpu(),
        "bits": state.bits.cpu(),
        "records": [asdict(r) for r in records],
        "done": done,
    }
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)  # atomic: a worker killed mid-write leaves the previous checkpoint intact


def _load_checkpoint(path: Path, fingerprint: str, device: torch.device):  # noqa: ANN202
    if not path.exists():
        return None
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception:  # noqa: BLE001 - an unreadable checkpoint is recomputed, never trusted
        return None
    if payload.get("fingerprint") != fingerprint:
        return None
    state = LevelState(GaussianScene(**payload["stored"]), payload["normals"], payload["offsets"], payload["bits"])
    records = [LevelReport(**{**r, "normal": tuple(r["normal"])}) for r in payload["records"]]
    return state, records, bool(payload["done"])


def run_levels(
    source: GaussianScene,
    views: ViewSet,
    *,
    config: CompressConfig,
    floor: float,
    extent: float,
    report,  # noqa: ANN001 - pipeline._Reporter
    checkpoint: Path | None,
    fingerprint: str,
    size_of: Callable[[LevelState], int] | None = None,
) -> tuple[LevelState, list[LevelReport]]:
    """Accept mirror levels while they pay for themselves; resume from ``checkpoint`` when it matches.

    ``size_of`` measures a state's archive where fewer Gaussians need not mean fewer bytes (a lossless archive of
    a scene whose values sit on a grid: fine-tuned values leave it); a level must then also shrink it.
    """
    from ..detect import DetectConfig, detect

    state, records, done = LevelState.plain(source), [], False
    if checkpoint is not None:
        resumed = _load_checkpoint(checkpoint, fingerprint, source.device)
        if resumed is not None:
            state, records, done = resumed
    detect_config = replace(DetectConfig(), **{**config.detect, "max_mirrors": 1})
    while not done and state.normals.shape[0] < config.max_levels:
        level = state.normals.shape[0]
        t0 = time.perf_counter()
        report("levels", level / config.max_levels, f"level {level}: detecting mirrors", level)
        accepted = [Plane.from_tensor(n, g) for n, g in zip(state.normals, state.offsets)]
        mirrors = detect(state.stored, detect_config, exclude=accepted)
        report.timed("detect", time.perf_counter() - t0)
        attempts = plan_attempts(state, memberships(state, mirrors[0]), views, floor=floor) if mirrors else []
        done = True
        for membership, psnr_before in attempts:
            t0 = time.perf_counter()
            candidate, record = try_level(
                state,
                membership,
                views,
                level=level,
                config=config,
                floor=floor,
                extent=extent,
                report=report,
                psnr_before=psnr_before,
            )
            report.timed("optimize", time.perf_counter() - t0)
            if record.accepted and size_of is not None and size_of(candidate) >= size_of(state):
                record = replace(record, accepted=False, reason="within budget, but the archive would not shrink")
            records.append(record)
            if record.accepted:
                state, done = candidate, False
                break
        if checkpoint is not None:
            _save_checkpoint(checkpoint, fingerprint, state, records, done)
    report("levels", 1.0, f"{state.normals.shape[0]} mirror level(s) accepted")
    return state, records
