"""Charts of a bench (``symgs bench``): rate-distortion (PSNR against bytes) and speed-accuracy (PSNR against
encoding seconds), per scene and over all scenes.

PSNR is on the evaluation cameras, which fitted nothing. Sizes and times are on logarithmic axes; the PSNR axis
covers the finite figures, lossless ones drawn apart above it (``axes.psnr_axis``). On a scene's rate-distortion
chart our curve is drawn through its Pareto front, and each peer that our curve spans is joined, at its PSNR, to our
size there, labelled with how many times smaller ours is (``equal_psnr_ratio``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import cast

from matplotlib.axes import Axes
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from ..pictures._png import new_figure, png_bytes
from ..pictures.axes import psnr_axis
from ..pictures.palette import method_style
from . import curve
from .rows import BenchRow

SCENE_MARKERS = "os^DvP<>hX*p"


def _short(value: float) -> str:
    """Tick labels: 200k, 1.5M, 0.5."""
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if value >= scale:
            return f"{value / scale:g}{unit}"
    return f"{value:g}"


def _log_x(ax: Axes, label: str) -> None:
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: _short(v)))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(label)
    ax.margins(x=0.08)


def _ok(rows: Sequence[BenchRow]) -> list[BenchRow]:
    return [r for r in rows if r.ok and r.bytes and r.encode_s is not None]


def _methods(rows: Sequence[BenchRow]) -> list[str]:
    """Ours first, then the peers, each once, in the order the rows give them."""
    seen = dict.fromkeys(r.method for r in rows if r.ours)
    seen.update(dict.fromkeys(r.method for r in rows if not r.ours))
    return list(seen)


def _finish(ax: Axes, title: str) -> None:
    ax.set_ylabel("PSNR (dB) against renders of the input,\nevaluation cameras")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.figure.legend(fontsize=7, loc="outside right upper")


def _scene_chart(rows: Sequence[BenchRow], scene: str, x: Callable[[BenchRow], float], xlabel: str, title: str,
                 equal: bool, width: int, height: int) -> bytes:  # fmt: skip
    fig = new_figure(width, height)
    ax = fig.add_subplot()
    shown = _ok([r for r in rows if r.scene == scene])
    ymap = psnr_axis(ax, [r.psnr_db for r in shown])
    for method in _methods(shown):
        colour, marker = method_style(method)
        mine = [r for r in shown if r.method == method]
        if mine[0].ours and equal:  # our curve: its Pareto front, then every run on it or off it
            front = curve.front((float(cast(int, r.bytes)), r.psnr_db) for r in mine)  # _ok: rows with bytes
            ax.plot([b for b, _ in front], [ymap(p) for _, p in front], color=colour, linewidth=1.2, zorder=2)
        ax.plot([x(r) for r in mine], [ymap(r.psnr_db) for r in mine], linestyle="none", marker=marker, color=colour,
                markersize=7 if mine[0].ours else 9, markeredgecolor="#222222", zorder=3, label=method)  # fmt: skip
        for r in mine:
            if r.role == "preset":  # a preset run names its preset
                ax.annotate(cast(str, r.preset), (x(r), ymap(r.psnr_db)), textcoords="offset points", xytext=(5, -9),
                            fontsize=6, color=colour)  # fmt: skip
    if equal:
        labelled: list[float] = []
        for r in shown:
            if r.role == "peer" and r.equal_psnr_bytes and r.equal_psnr_ratio:
                y = ymap(r.psnr_db)
                ax.plot([r.equal_psnr_bytes, cast(int, r.bytes)], [y, y], color="#444444", linestyle=":", linewidth=0.9)
                ax.plot([r.equal_psnr_bytes], [y], marker="|", markersize=9, color="#444444")
                stacked = sum(abs(y - other) < 1.5 for other in labelled)  # peers at about the same PSNR
                labelled.append(y)
                ax.annotate(f"ours {r.equal_psnr_ratio:.2f}x smaller", (r.bytes, y), textcoords="offset points",
                            xytext=(8, 2 + 9 * stacked), fontsize=6, color=method_style(r.method)[0])  # fmt: skip
    _log_x(ax, xlabel)
    _finish(ax, title)
    return png_bytes(fig)


def rate_distortion_png(rows: Sequence[BenchRow], scene: str, width: int = 900, height: int = 520) -> bytes:
    """One scene: PSNR against file bytes, our curve, the peers, and our size at each peer's PSNR."""
    return _scene_chart(rows, scene, lambda r: float(r.bytes or 0), "file size (bytes, log)",
                        f"Rate-distortion: {scene}", True, width, height)  # fmt: skip


def speed_accuracy_png(rows: Sequence[BenchRow], scene: str, width: int = 900, height: int = 520) -> bytes:
    """One scene: PSNR against encoding seconds (ours: the whole pipeline; peers: the tool's run)."""
    return _scene_chart(rows, scene, lambda r: float(r.encode_s or 0), "encoding time (seconds, log)",
                        f"Speed-accuracy: {scene}", False, width, height)  # fmt: skip


def _overall(rows: Sequence[BenchRow], x: Callable[[BenchRow], float], xlabel: str, title: str, width: int,
             height: int) -> bytes:  # fmt: skip
    fig = new_figure(width, height)
    ax = fig.add_subplot()
    shown = _ok(rows)
    scenes = list(dict.fromkeys(r.scene for r in shown))
    ymap = psnr_axis(ax, [r.psnr_db for r in shown])
    for method in _methods(shown):
        colour, _ = method_style(method)
        for i, scene in enumerate(scenes):
            mine = sorted((r for r in shown if r.method == method and r.scene == scene), key=x)
            if not mine:
                continue
            if len(mine) > 1:  # the front: a run that another beats in both bytes and PSNR is a marker only
                front = curve.front((x(r), r.psnr_db) for r in mine)
                ax.plot([b for b, _ in front], [ymap(p) for _, p in front], color=colour, linewidth=0.6, alpha=0.6)
            ax.plot([x(r) for r in mine], [ymap(r.psnr_db) for r in mine], linestyle="none", color=colour,
                    marker=SCENE_MARKERS[i % len(SCENE_MARKERS)], markersize=6, markeredgecolor="#222222",
                    label=method if i == 0 else None)  # fmt: skip
    for i, scene in enumerate(scenes):  # the legend's scene entries: grey markers
        ax.plot([], [], linestyle="none", marker=SCENE_MARKERS[i % len(SCENE_MARKERS)], color="#BBBBBB",
                markeredgecolor="#222222", label=scene)  # fmt: skip
    _log_x(ax, xlabel)
    _finish(ax, title)
    return png_bytes(fig)


def rate_distortion_overall_png(rows: Sequence[BenchRow], input_bytes: dict[str, int], width: int = 1000,
                                height: int = 600) -> bytes:  # fmt: skip
    """Every scene: PSNR against the file's size as a fraction of the scene's input PLY (so scenes share an axis);
    colours are methods, markers scenes."""
    return _overall(rows, lambda r: (r.bytes or 0) / input_bytes[r.scene], "file size / input PLY size (log)",
                    "Rate-distortion, all scenes", width, height)  # fmt: skip


def speed_accuracy_overall_png(rows: Sequence[BenchRow], width: int = 1000, height: int = 600) -> bytes:
    """Every scene: PSNR against encoding seconds; colours are methods, markers scenes."""
    return _overall(rows, lambda r: float(r.encode_s or 0), "encoding time (seconds, log)",
                    "Speed-accuracy, all scenes", width, height)  # fmt: skip
