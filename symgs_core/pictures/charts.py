"""Rate-distortion and speed-accuracy charts of a compression job, from its report.

The points follow the job: the input, each mirror level (its PSNR as applied and after fine-tuning), each later
stage the report accounts for (``Report.stages``: pruning, SH reduction, quantisation, ...), and the final archive,
on the fitting cameras the decisions saw and on the evaluation cameras that fitted nothing. PSNR is in dB against
the report's reference (renders of the input, or photographs); ``None`` stands for an infinite PSNR (a result
identical to its reference) and is drawn above the finite range.

With ``peers`` (other formats run on the same upload and scored on the same evaluation cameras), both charts
also show where each peer lands: its file's size and PSNR, and its encoding time.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, cast

from matplotlib.axes import Axes
from matplotlib.ticker import EngFormatter, LogLocator, NullFormatter
from matplotlib.transforms import blended_transform_factory

from ..report import Report
from ._png import new_figure, png_bytes
from .axes import psnr_axis
from .palette import NEUTRAL, level_colour, method_style

YMap = Callable[[float | None], float]

PointKind = Literal["input", "applied", "level", "rolled_back", "stage", "final", "evaluated"]
# Stages whose point is drawn elsewhere: the mirror stage is the levels, entropy coding is the final archive.
_FOLDED_STAGES = {"mirrors", "entropy_coding"}


@dataclass(frozen=True)
class ChartPoint:
    """One point of a job's path, in the order the job reached them.

    kind     input: the input scene (its lossless archive); applied: a mirror just applied, before fine-tuning;
             level: an accepted level after fine-tuning; rolled_back: a level that cost too much; stage: a
             reduction stage after the levels (``label`` names it); final: the archive the job wrote
    bytes    archive size after this point; estimated (``estimated``) for levels, None where nothing was written
    seconds  pipeline time since the job started when this point was reached
    psnr     dB; None when infinite
    """

    kind: PointKind
    label: str
    level: int | None
    bytes: float | None
    seconds: float
    psnr: float | None
    estimated: bool = False


@dataclass(frozen=True)
class PeerPoint:
    """Another format on the job's upload: its file's bytes, PSNR (dB, None when infinite) on the job's
    evaluation cameras (the worst of full frame and object, as the job's own evaluated point) and encode seconds."""

    method: str
    bytes: int
    psnr: float | None
    seconds: float


def _draw_peers(ax: Axes, peers: Sequence[PeerPoint], ymap: YMap, x: Callable[[PeerPoint], float]) -> None:
    for p in peers:
        colour, marker = method_style(p.method)
        ax.plot([x(p)], [ymap(p.psnr)], linestyle="none", marker=marker, markersize=8, color=colour,
                markeredgecolor="#222222", zorder=4, label=p.method)  # fmt: skip


def _db(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def _lossless_span(report: Report) -> tuple[tuple[int, float], tuple[int, float]]:
    """(Gaussians stored, lossless archive bytes) of the input and after the accepted levels.

    With stage accounting the report measures both; without it, the plain archive of the input (the baseline) and
    the final archive are the two measured ends."""
    mirrors = next((s for s in report.stages if s.stage == "mirrors"), None)
    n_in = report.gaussians.input
    accepted = report.accepted_levels
    n_levels = accepted[-1].stored_after if accepted else n_in
    if mirrors is not None:
        return (n_in, float(mirrors.bytes_before)), (n_levels, float(mirrors.bytes_after))
    return (n_in, float(report.baseline_bytes)), (report.gaussians.stored, float(report.output_bytes))


def _bytes_for(stored: int, span: tuple[tuple[int, float], tuple[int, float]]) -> float:
    """Lossless archive bytes of a level storing ``stored`` Gaussians: on the line through the two measured ends
    (exact at both; the codec's cost is close to linear in the count between them)."""
    (n0, b0), (n1, b1) = span
    if n0 == n1:
        return b1 if stored == n1 else b0
    return b0 + (b1 - b0) * (n0 - stored) / (n0 - n1)


def job_points(report: Report) -> list[ChartPoint]:
    """Every point of the job's path, in time order.

    Detection time is reported for all levels together, so each level gets an equal share of it, before its
    fine-tuning."""
    seconds, records = report.seconds, report.levels
    span = _lossless_span(report)
    t = seconds.get("load", 0.0) + seconds.get("views", 0.0)
    input_label = "input (lossless archive)" if span[0][1] != report.baseline_bytes else "baseline (plain codec)"
    points = [ChartPoint("input", input_label, None, span[0][1], t, _db(report.psnr_input))]
    detect_share = seconds.get("detect", 0.0) / max(len(records), 1)
    for r in records:
        t += detect_share
        points.append(ChartPoint("applied", f"level {r.level} applied", r.level, None, t, _db(r.psnr_before)))
        t += r.seconds
        estimated = r.stored_after != span[1][0]
        size = _bytes_for(r.stored_after, span)
        kind: PointKind = "level" if r.accepted else "rolled_back"
        label = f"level {r.level}" + ("" if r.accepted else " (rolled back)")
        points.append(ChartPoint(kind, label, r.level, size, t, _db(r.psnr_after), estimated))
    for s in report.stages:
        t += s.seconds
        if s.stage not in _FOLDED_STAGES:
            label = s.stage.replace("_", " ")
            points.append(ChartPoint("stage", label, None, float(s.bytes_after), t, _db(s.psnr_after)))
    if not report.stages:
        t += seconds.get("encode", 0.0)
    t += seconds.get("evaluate", 0.0)
    size = float(report.output_bytes)
    points.append(ChartPoint("final", "final archive", None, size, t, _db(report.fitting.worst)))
    points.append(ChartPoint("evaluated", "final, evaluation cameras", None, size, t, _db(report.fidelity.worst)))
    return points


def _psnr_axis(ax: Axes, points: Sequence[ChartPoint], floor: float | None, peers: Sequence[PeerPoint] = ()) -> YMap:
    """The y range over the finite PSNRs and the floor (``axes.psnr_axis``); lossless points in a band above it."""
    return psnr_axis(ax, [p.psnr for p in points] + [p.psnr for p in peers], floor)


def _y(point: ChartPoint, ymap: YMap) -> float:
    return ymap(point.psnr)


_STAGE_MARKERS = "DPhp<>"


def _style(point: ChartPoint, rolled_back: set[int | None], stage_index: int) -> dict:
    if point.kind == "input":
        return {"marker": "s", "color": "#222222"}
    if point.kind == "final":
        return {"marker": "*", "color": "#222222", "markersize": 15, "zorder": 3}
    if point.kind == "evaluated":
        return {"marker": "*", "color": "#E07A1F", "markersize": 12, "zorder": 5}
    if point.kind == "stage":
        return {"marker": _STAGE_MARKERS[stage_index % len(_STAGE_MARKERS)], "color": "#3D5A80"}
    if point.kind == "rolled_back" or point.level in rolled_back:
        return {"marker": "X" if point.kind == "rolled_back" else "v", "color": NEUTRAL}
    return {"marker": "v" if point.kind == "applied" else "o", "color": level_colour(point.level or 0)}


def _draw(ax: Axes, points: Sequence[ChartPoint], top: YMap, x: Callable[[ChartPoint], float], hollow: bool) -> None:
    """The job's path (solid), a dashed grey branch to each rolled-back level, and a marker per point; hollow
    markers for estimated sizes when ``hollow``. Applied points carry no legend entry (the title explains them)."""
    grey = {p.level for p in points if p.kind == "rolled_back"}
    kept = [p for p in points if p.level not in grey]
    ax.plot([x(p) for p in kept], [_y(p, top) for p in kept], color="#444444", linewidth=1, zorder=2)
    last = points[0]
    for i, p in enumerate(points):
        if p.level in grey and (i + 1 == len(points) or points[i + 1].level != p.level):
            branch = [last, *[q for q in points if q.level == p.level]]
            ax.plot([x(q) for q in branch], [_y(q, top) for q in branch], color=NEUTRAL, linewidth=1, linestyle="--")
        elif p.level not in grey:
            last = p
    stage_index = 0
    for p in points:
        style = {"markersize": 9, "zorder": 4, **_style(p, grey, stage_index)}  # levels stay visible on the star
        stage_index += p.kind == "stage"
        ax.plot(
            [x(p)], [_y(p, top)], linestyle="none", markeredgecolor="#222222",
            markerfacecolor="white" if hollow and p.estimated else style["color"],
            label=None if p.kind == "applied" else p.label, **style,
        )  # fmt: skip


def _finish(ax: Axes, report: Report, floor: float | None, title: str) -> None:
    if floor is not None:
        ax.axhline(floor, color="#B22222", linestyle="--", linewidth=1, label="PSNR floor (budget)")
    ax.set_ylabel(f"PSNR (dB) against {report.cameras.evaluation.source}")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.figure.legend(fontsize=8, loc="outside right upper")


def rate_distortion_png(
    report: Report, width: int = 820, height: int = 420, peers: Sequence[PeerPoint] = ()
) -> bytes:
    """PSNR against archive bytes along the job's path; hollow markers are sizes estimated from the Gaussians stored.
    A vertical line marks the baseline (the codec alone on the input) when it is not the input point. With
    ``peers``, their files too, on a logarithmic size axis (they may be several times larger)."""
    points = [p for p in job_points(report) if p.bytes is not None]
    floor = _db(report.psnr_floor)
    fig = new_figure(width, height)
    ax = fig.add_subplot()
    top = _psnr_axis(ax, points, floor, peers)
    _draw(ax, points, top, lambda p: cast(float, p.bytes), hollow=True)  # points without bytes are left out above
    if peers:
        _draw_peers(ax, peers, top, lambda p: p.bytes)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    if points[0].label != "baseline (plain codec)":
        ax.axvline(report.baseline_bytes, color="#222222", linestyle=":", label="baseline: the codec on the input")
    ax.xaxis.set_major_formatter(EngFormatter(unit="B"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("archive size (hollow markers: estimated from the Gaussians stored)")
    ax.margins(x=0.12)
    _finish(ax, report, floor, "Rate and distortion, level by level and stage by stage")
    return png_bytes(fig)


def _stage_bands(ax: Axes, report: Report) -> None:
    seconds = report.seconds
    bands = [("load", seconds.get("load", 0.0)), ("views", seconds.get("views", 0.0))]
    bands.append(("levels", seconds.get("detect", 0.0) + seconds.get("optimize", 0.0)))
    bands += [(s.stage, s.seconds) for s in report.stages] or [
        ("encode", seconds.get("encode", 0.0))
    ]
    bands.append(("evaluate", seconds.get("evaluate", 0.0)))
    total = sum(width for _, width in bands)
    label_at = blended_transform_factory(ax.transData, ax.transAxes)
    t = 0.0
    for i, (name, width) in enumerate(bands):
        if width <= 0:
            continue
        ax.axvspan(t, t + width, color=NEUTRAL, alpha=0.08 if i % 2 else 0.16, linewidth=0, zorder=0)
        if width >= 0.06 * total:  # narrower bands would print their names over each other
            ax.text(
                t + width / 2, 0.01, name.replace("_", " "), transform=label_at, ha="center", va="bottom", fontsize=7
            )
        t += width


def speed_accuracy_png(
    report: Report, width: int = 820, height: int = 420, peers: Sequence[PeerPoint] = ()
) -> bytes:
    """PSNR against the job's cumulative seconds, over shaded stage bands: each level's drop when its mirror is
    applied and its recovery by fine-tuning, then each later stage; with ``peers``, each at its encoding time."""
    points = job_points(report)
    floor = _db(report.psnr_floor)
    fig = new_figure(width, height)
    ax = fig.add_subplot()
    top = _psnr_axis(ax, points, floor, peers)
    _stage_bands(ax, report)
    _draw(ax, points, top, lambda p: p.seconds, hollow=False)
    _draw_peers(ax, peers, top, lambda p: p.seconds)
    ax.set_xlabel("seconds since the job started")
    ax.set_xlim(left=0)
    _finish(ax, report, floor, "Speed and accuracy (\u25bc mirror applied, \u25cf fine-tuned)")
    return png_bytes(fig)
