"""One bench: our presets with and without mirrors, a sweep of our budget across the peers' fidelity, and the peers.

Every output is written to the bench's folder, decoded as its users would decode it (ours by ``decompress``, the
peers by their own tool) and rendered from two camera rigs that fitted nothing: the pipeline's evaluation cameras
(the same seed, count and resolution as the runs' config, so a row's PSNR is the one its report states) and an
independent rig (another seed: other directions over the same distances). Our runs fit only on their own fitting
cameras, which neither rig contains.

Equal fidelity: the sweep adds runs of ours (mirrors on, the preset nearest to each floor) at budgets chosen from
the peers' PSNRs until our curve spans every peer's PSNR, a run of ours reaches on the other rig the PSNR each
peer we claim to beat has there, and every peer's PSNR has a point of our curve near it, or the sweep's runs are
spent; each peer row then carries our size at its PSNR
(``curve.size_at``) and whether that claim still holds on the other rig.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..config import PRESETS, CompressConfig, budget_for_floor, floor_for_budget
from ..metrics import LOSSLESS_DB
from ..report import Fidelity
from ..scene import GaussianScene
from ..views import ViewSet, evaluate, self_supervised_views
from . import curve
from .peers import PEERS, Peer, PeerOutput, run_peers
from .rows import TOLERANCE_DB, BenchRow, Role

OURS = "symgs"  # mirrors on (the product's default): our curve whenever mirrors run
OURS_PLAIN = "symgs no mirrors"
Say = Callable[[str], None]
AIM_PAST_DB = 0.5  # a sweep run meant to span a PSNR aims this far past it
NEAR_DB = 1.5  # a peer's PSNR farther than this from every point of our curve gets a run of its own
MIN_FLOOR_GAP_DB = 0.5  # two runs' floors closer than this say nothing of the slope between them
SLOPE_RANGE = (0.25, 2.0)  # dB of PSNR per dB of floor the aim assumes, at least and at most
SLOPE_NEAR_DB = 3.0  # two runs say the slope where the next should land when both landed this near it


@dataclass(frozen=True)
class BenchSettings:
    """What a bench runs. ``overrides`` are CompressConfig settings every run of ours shares (views, iterations,
    levels, device, seed); the preset and budget vary per run."""

    presets: tuple[str, ...] = tuple(PRESETS)
    mirrors: tuple[bool, ...] = (True, False)
    overrides: dict[str, Any] = field(default_factory=dict)
    peers: tuple[Peer, ...] = PEERS
    splat_transform: str | None = None  # the executable; None: its peers are reported unavailable
    unavailable: str = "splat-transform is not installed"
    peer_timeout: float = 300.0  # seconds per peer (writing its file and decoding it back)
    slow_timeout: float = 900.0  # the same for a slow peer (SOG on a CPU)
    sweep: int = 8  # at most this many runs of ours added to span and meet the peers' PSNRs
    other_seed: int = 1  # the second rig's seed (the runs' own seed is overrides["seed"], default 0)
    other_views: int = 8

    @property
    def curve_method(self) -> str:
        """The method whose runs form our curve and whose budget the sweep varies: with mirrors when they run."""
        return OURS if True in self.mirrors else OURS_PLAIN

    def config(self, preset: str, **changes: Any) -> CompressConfig:
        return CompressConfig.for_preset(preset, **{**self.overrides, "pictures": False, **changes})


def scene_name(ply: Path) -> str:
    """Trainers name their output point_cloud.ply or fused.ply: the folder then names the scene."""
    return ply.parent.name if ply.stem in ("point_cloud", "fused", "scene") else ply.stem


@dataclass
class _Scene:
    name: str
    ply: Path
    source: GaussianScene
    rig: ViewSet
    other: ViewSet
    folder: Path  # where its outputs go
    out: Path  # the bench's folder (rows name files relative to it)

    def fidelity(self, decoded: GaussianScene) -> tuple[Fidelity, Fidelity]:
        decoded = decoded.to(self.source.device)
        return (evaluate(decoded, self.rig.eval, self.rig.background),
                evaluate(decoded, self.other.eval, self.other.background))  # fmt: skip

    def relative(self, path: Path) -> str:
        return path.relative_to(self.out).as_posix()


def _figures(row: BenchRow, main: Fidelity, other: Fidelity, ply_bytes: int) -> BenchRow:
    row.ratio = ply_bytes / row.bytes if row.bytes else None
    row.psnr_db, row.psnr_object_db, row.ssim = main.psnr, main.psnr_object, main.ssim
    row.psnr_other_db, row.psnr_object_other_db, row.ssim_other = other.psnr, other.psnr_object, other.ssim
    return row


def _ours(scene: _Scene, config: CompressConfig, role: Role, say: Say) -> BenchRow:
    from ..pipeline import compress, decompress
    from ..ply import ply_bytes

    method = OURS if config.use_mirrors else OURS_PLAIN
    label = f"{config.preset}, mirrors {'on' if config.use_mirrors else 'off'}, budget {config.budget:.4g} dB"
    say(f"{scene.name}: {method} ({label})")
    t0 = time.perf_counter()
    result = compress(scene.ply, config=config)
    encode = time.perf_counter() - t0
    stem = f"symgs-{config.preset}-{'mirrors' if config.use_mirrors else 'no-mirrors'}"
    path = scene.folder / (f"{stem}.symgs" if role == "preset" else f"{stem}-budget-{config.budget:.4g}.symgs")
    path.write_bytes(result.archive)
    t0 = time.perf_counter()
    decoded = decompress(path.read_bytes())
    ply_bytes(decoded)
    decode = time.perf_counter() - t0
    row = BenchRow(
        scene.name, method, role, "ok", scene.relative(path), preset=config.preset, mirrors=config.use_mirrors,
        budget_db=config.budget, floor_db=result.report.psnr_floor, bytes=len(result.archive),
        gaussians=len(decoded), encode_s=encode, decode_s=decode,
        sections={part.name: part.bytes for part in result.report.sections},
    )  # fmt: skip
    return _figures(row, *scene.fidelity(decoded), scene.ply.stat().st_size)


def _peer_row(scene: _Scene, found: PeerOutput) -> BenchRow:
    row = BenchRow(scene.name, found.peer.method, "peer", found.status, None, reason=found.reason)
    if found.status != "ok" or found.decoded is None or found.path is None:
        return row
    row.file, row.bytes, row.gaussians = scene.relative(found.path), found.bytes, len(found.decoded)
    row.encode_s, row.decode_s = found.encode_s, found.decode_s
    return _figures(row, *scene.fidelity(found.decoded), scene.ply.stat().st_size)


def _line(row: BenchRow) -> str:
    if not row.ok:
        return f"  {row.method}: {row.status} ({row.reason})"
    db = lambda v: "lossless" if v is None or math.isinf(v) else f"{v:.2f} dB"  # noqa: E731
    return (f"  {row.method} [{row.preset or '-'}]: {row.bytes:,} B ({row.ratio:.1f}x), {db(row.psnr_db)} "
            f"(object {db(row.psnr_object_db)}; other cameras {db(row.psnr_other_db)}), encode {row.encode_s:.1f} s, "
            f"decode {row.decode_s:.2f} s")  # fmt: skip


def curve_points(rows: list[BenchRow], scene: str, method: str = OURS, field: str = "psnr_db") -> list[curve.Point]:
    """(bytes, PSNR) of ``method``'s runs on ``scene``; ``field`` names the PSNR: the evaluation rig's (full frame or
    object), or the other rig's. A run that stores float32 (preset ``lossless``) is lossless whatever its renders'
    rounding measures (73 dB on one scene, 142 on another): it reaches every PSNR and is no point to interpolate
    along (``curve``), so a peer between our finest lossy run and it is met by the sweep, not by interpolation."""

    def psnr(r: BenchRow) -> float | None:
        value = getattr(r, field)
        stored_float32 = r.preset in PRESETS and not PRESETS[r.preset].step_scale > 0
        return math.inf if stored_float32 and value is not None else value

    return [(float(r.bytes), psnr(r)) for r in rows
            if r.scene == scene and r.method == method and r.ok and r.bytes]  # fmt: skip


def _nearest_preset(floor: float, nominal: float) -> str:
    lossy = [name for name, spec in PRESETS.items() if spec.step_scale > 0 and spec.fitted]  # a budget it can hold
    return min(lossy, key=lambda name: abs(floor_for_budget(PRESETS[name].budget, nominal) - floor))


def next_floor(
    rows: list[BenchRow],
    scene: str,
    targets: list[float],
    tried: list[float],
    method: str = OURS,
    other: list[float] | None = None,
) -> float | None:
    """The fitting floor for our next sweep run, or None when every target is met. Aimed, in this order: past the
    first target PSNR our curve does not span (a peer's evaluation PSNR); past the first ``other`` PSNR no lossy run
    of ours reaches on the other rig (where a claim is checked); at the first target with no point of our curve
    within ``NEAR_DB`` of it (our size there would be interpolated across a wide gap, a guess)."""
    main = curve_points(rows, scene, method)
    missing = [("psnr_db", t, AIM_PAST_DB) for t in targets if t < LOSSLESS_DB and not curve.spans(main, t)]
    if not missing and other:
        reached = curve.front(curve_points(rows, scene, method, "psnr_other_db"))
        missing = [("psnr_other_db", t, AIM_PAST_DB) for t in other
                   if t < LOSSLESS_DB and (not reached or reached[-1][1] < t)]  # fmt: skip
    if not missing:
        ahead = curve.front(main)
        missing = [("psnr_db", t, 0.0) for t in targets
                   if t < LOSSLESS_DB and ahead and min(abs(p - t) for _, p in ahead) > NEAR_DB]  # fmt: skip
    if not missing:
        return None
    field, target, past = missing[0]
    # Only runs that held their floor say where a floor lands: a preset that fits nothing (fixed steps) does not.
    ours = [r for r in rows if r.scene == scene and r.method == method and r.ok
            and (r.preset not in PRESETS or PRESETS[r.preset].fitted)]  # fmt: skip
    figures = [(getattr(r, field), r.floor_db, r.preset) for r in ours]
    landed = [(p, f, preset) for p, f, preset in figures
              if p is not None and f is not None and math.isfinite(p) and math.isfinite(f)]  # fmt: skip
    front = curve.front(curve_points(rows, scene, method, field))
    up = not front or target > front[-1][1]
    floor = _aim(landed, target + (past if up else -past))
    while any(abs(floor - t) < 0.25 for t in tried):
        floor += 1.0 if up else -1.0
    return floor


def _aim(landed: list[tuple[float, float, str | None]], psnr: float) -> float:
    """The floor at which a run should land at ``psnr``, from the (PSNR, floor, preset) of the runs that held their
    floor: from the run that landed nearest it (runs far from it, at other steps, land differently), one dB of floor
    a dB of PSNR, or along the slope between it and another run of its preset when both landed within
    ``SLOPE_NEAR_DB`` of it. Near the lossless end a higher floor buys less PSNR on the cameras that fitted nothing
    (0.3 dB a dB on the lego), so one dB a dB aimed short run after run there; a slope between presets, or across
    many dB, says little (the lego's balanced and high presets: 0.27 dB a dB, which sent a run 13 dB past its
    target), and the slope is bounded so that two runs close together cannot send the next far off. Without runs,
    the floor is the PSNR itself."""
    if not landed:
        return psnr
    nearest = sorted(landed, key=lambda run: abs(run[0] - psnr))
    p0, f0, preset = nearest[0]
    near = [(p, f) for p, f, other in nearest[1:] if other == preset and abs(f - f0) >= MIN_FLOOR_GAP_DB]
    slope = 1.0
    if abs(p0 - psnr) <= SLOPE_NEAR_DB and near and abs(near[0][0] - psnr) <= SLOPE_NEAR_DB:
        slope = min(max((near[0][0] - p0) / (near[0][1] - f0), SLOPE_RANGE[0]), SLOPE_RANGE[1])
    return f0 + (psnr - p0) / slope


def other_targets(rows: list[BenchRow], scene: str, method: str) -> list[float]:
    """The other rig's PSNR, less the tolerance, of each peer our curve claims to beat: what a run of ours must
    reach there for the claim to be checked."""
    main = curve_points(rows, scene, method)
    return [r.psnr_other_db - TOLERANCE_DB for r in rows
            if r.scene == scene and r.role == "peer" and r.ok and r.bytes and r.psnr_db and r.psnr_other_db
            and (ours := curve.size_at(main, r.psnr_db)) is not None and ours < r.bytes]  # fmt: skip


def _sweep(scene: _Scene, rows: list[BenchRow], settings: BenchSettings, say: Say) -> None:
    nominal = settings.config("balanced").nominal_psnr
    targets = [r.psnr_db for r in rows if r.scene == scene.name and r.role == "peer" and r.ok and r.psnr_db]
    tried: list[float] = []
    for _ in range(settings.sweep):
        other = other_targets(rows, scene.name, settings.curve_method)
        floor = next_floor(rows, scene.name, targets, tried, settings.curve_method, other)
        if floor is None:
            return
        tried.append(floor)
        budget = min(max(budget_for_floor(floor, nominal), 1e-6), 59.0)
        preset = _nearest_preset(floor, nominal)
        config = settings.config(preset, psnr_budget=budget, use_mirrors=settings.curve_method == OURS)
        rows.append(_ours(scene, config, "sweep", say))
        say(_line(rows[-1]))


def equal_fidelity(rows: list[BenchRow], scene: str, method: str = OURS) -> None:
    """Fill each ok peer row of ``scene`` with our size at its PSNR on ``method``'s curve, and the check of that
    claim on the other rig."""
    main, other = curve_points(rows, scene, method), curve_points(rows, scene, method, "psnr_other_db")
    objects = curve_points(rows, scene, method, "psnr_object_db")

    def ratio(points: list[curve.Point], nbytes: int, psnr: float | None) -> float | None:
        ours = curve.size_at(points, psnr) if psnr is not None else None
        return nbytes / ours if ours else None

    for r in rows:
        if r.scene != scene or r.role != "peer" or not r.ok or r.bytes is None or r.psnr_db is None:
            continue
        r.equal_psnr_bytes = curve.size_at(main, r.psnr_db)
        r.equal_psnr_ratio = r.bytes / r.equal_psnr_bytes if r.equal_psnr_bytes else None
        r.equal_psnr_other_ratio = ratio(other, r.bytes, r.psnr_other_db)
        r.equal_psnr_object_ratio = ratio(objects, r.bytes, r.psnr_object_db)
        r.claim_holds_other = None
        if r.equal_psnr_ratio is not None and r.equal_psnr_ratio > 1 and r.psnr_other_db is not None:
            needed = curve.smallest_reaching(other, r.psnr_other_db - TOLERANCE_DB)
            r.claim_holds_other = needed is not None and needed < r.bytes


def bench_scene(ply: Path, out: Path, settings: BenchSettings, say: Say | None = None, name: str | None = None,
                trained: bool | None = None) -> list[BenchRow]:  # fmt: skip
    """Every row for one scene; outputs go to ``out/files/<scene>/``. ``trained``: whether the scene is as a trainer
    wrote it, or decoded from a quantised container (None: not said); every row carries it."""
    from ..devices import resolve_device
    from ..ply import load_scene

    say = say or (lambda message: None)
    base = settings.config("balanced")
    device = resolve_device(base.device)
    source = load_scene(ply).to(device)
    name = name or scene_name(ply)
    background = torch.zeros(3, device=device)

    def rig(seed: int, count: int) -> ViewSet:
        return self_supervised_views(
            source, train=1, fit=1, eval=count, resolution=16, eval_resolution=base.eval_resolution,
            background=background, seed=seed,
        )  # fmt: skip

    if settings.other_seed == base.seed:
        raise ValueError(f"the other rig's seed must differ from the runs' seed ({base.seed})")
    folder = out / "files" / name
    folder.mkdir(parents=True, exist_ok=True)
    scene = _Scene(name, ply, source, rig(base.seed, base.eval_views), rig(settings.other_seed, settings.other_views),
                   folder, out)  # fmt: skip
    rows: list[BenchRow] = []
    if settings.peers:
        say(f"{name}: peers")
        found = run_peers(ply, source.to("cpu"), folder, exe=settings.splat_transform, timeout=settings.peer_timeout,
                          slow_timeout=settings.slow_timeout, peers=settings.peers,
                          unavailable=settings.unavailable)  # fmt: skip
        for output in found:
            rows.append(_peer_row(scene, output))
            say(_line(rows[-1]))
    for preset in settings.presets:
        for mirrors in settings.mirrors:
            rows.append(_ours(scene, settings.config(preset, use_mirrors=mirrors), "preset", say))
            say(_line(rows[-1]))
    _sweep(scene, rows, settings, say)
    equal_fidelity(rows, name, settings.curve_method)
    for row in rows:
        row.trained = trained
    return rows
