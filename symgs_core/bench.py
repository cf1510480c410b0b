"""Benchmark: the presets with and without mirrors against the peers' formats, on size, PSNR and time.

For every scene, every entry is judged the same way: decode it, render it from the held-out cameras of
``views.self_supervised_views`` (never trained on) and take the PSNR against renders of the uncompressed scene.
Peers: `.spz` v3 from our exporter, and, when PlayCanvas ``splat-transform`` is installed, its `.spz` v3,
compressed PLY and SOG (each decoded back by splat-transform itself). The ``matched`` entry compresses with the
budget whose floor is the PSNR of splat-transform's `.spz` v3 (ours when it is absent): the archive at equal or
better PSNR, the comparison the goals are stated in.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from .config import PRESETS, CompressConfig, budget_for_floor
from .scene import GaussianScene
from .views import ViewSet, evaluate, self_supervised_views

COLUMNS = ["scene", "entry", "preset", "mirrors", "bytes", "ratio_to_ply", "psnr", "encode_s", "decode_s", "gaussians"]


@dataclass
class BenchRow:
    scene: str
    entry: str  # "symgs", "symgs matched", "spz v3 (symgs)", "spz v3 (splat-transform)", ...
    preset: str
    mirrors: bool | None
    bytes: int
    ratio_to_ply: float
    psnr: float  # +inf: renders exactly as the input
    encode_s: float
    decode_s: float
    gaussians: int


def find_splat_transform() -> str | None:
    """The ``splat-transform`` executable: ``SPLAT_TRANSFORM``, then PATH, then the test suite's npm cache."""
    given = os.environ.get("SPLAT_TRANSFORM")
    if given:
        return given
    found = shutil.which("splat-transform")
    if found:
        return found
    cache = Path(os.environ.get("SYMGS_NPM_CACHE", Path.home() / ".cache" / "symgs" / "npm"))
    exe = cache / "node_modules" / ".bin" / "splat-transform"
    return str(exe) if exe.exists() else None


def _psnr(scene: GaussianScene, views: ViewSet) -> float:
    return evaluate(scene, views.eval, views.background).psnr


def _run(args: list[str], timeout: float) -> None:
    done = subprocess.run(args, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:2])} failed: {done.stderr.strip()[-500:]}")


def _peers(
    ply: Path, name: str, source: GaussianScene, views: ViewSet, exe: str | None, work: Path, timeout: float, say
) -> list[BenchRow]:  # noqa: ANN001 - say: Callable[[str], None]
    from .export import read_spz, write_spz
    from .ply import load_scene

    ply_bytes = ply.stat().st_size
    rows = []
    t0 = time.perf_counter()
    data = write_spz(source, version=3)
    encode = time.perf_counter() - t0
    t0 = time.perf_counter()
    decoded = read_spz(data)
    decode = time.perf_counter() - t0
    rows.append(BenchRow(name, "spz v3 (symgs)", "-", None, len(data), ply_bytes / len(data), _psnr(decoded, views),
                         encode, decode, len(decoded)))  # fmt: skip
    if exe is None:
        return rows
    for entry, target, extra in (
        ("spz v3 (splat-transform)", "peer.spz", ["--spz-version", "3"]),
        ("compressed ply (splat-transform)", "peer.compressed.ply", []),
        ("sog (splat-transform)", "peer.sog", ["-g", "cpu"]),
    ):
        out, back = work / target, work / f"{target}.ply"
        try:
            t0 = time.perf_counter()
            _run([exe, "-w", "-q", str(ply), str(out), *extra], timeout)
            encode = time.perf_counter() - t0
            t0 = time.perf_counter()
            _run([exe, "-w", "-q", str(out), str(back)], timeout)
            decode = time.perf_counter() - t0
        except (RuntimeError, subprocess.TimeoutExpired) as exc:  # one peer failing leaves the others standing
            say(f"  {entry}: skipped ({str(exc)[:200]})")
            continue
        decoded = load_scene(back)
        rows.append(BenchRow(name, entry, "-", None, out.stat().st_size, ply_bytes / out.stat().st_size,
                             _psnr(decoded, views), encode, decode, len(decoded)))  # fmt: skip
    return rows


def _ours(ply: Path, name: str, config: CompressConfig, views: ViewSet, entry: str) -> BenchRow:
    from .pipeline import compress, decompress

    t0 = time.perf_counter()
    result = compress(ply, config=config)
    encode = time.perf_counter() - t0
    t0 = time.perf_counter()
    decoded = decompress(result.archive)
    decode = time.perf_counter() - t0
    size = len(result.archive)
    return BenchRow(name, entry, config.preset, config.use_mirrors, size, ply.stat().st_size / size,
                    _psnr(decoded, views), encode, decode, len(decoded))  # fmt: skip


def bench_scene(
    ply: Path,
    *,
    presets: list[str],
    config: CompressConfig,
    mirrors: tuple[bool, ...] = (True, False),
    peers: bool = True,
    match: bool = True,
    peer_cache: Path | None = None,
    peer_timeout: float = 1800.0,
    progress=None,  # noqa: ANN001 - Callable[[str], None]
) -> list[BenchRow]:
    """Every entry for one scene; ``config`` gives the views, iterations and levels every run of ours shares.

    ``peer_cache``: a folder where the peers' rows are kept per scene file and view settings, and reused (SOG's
    k-means alone takes many minutes on a CPU). A peer that fails or runs past ``peer_timeout`` seconds is left out.
    """
    from .ply import load_scene

    say = progress or (lambda message: None)
    # Trainers name their output point_cloud.ply or fused.ply: the folder then names the scene.
    name = ply.parent.name if ply.stem in ("point_cloud", "fused", "scene") else ply.stem
    source = load_scene(ply)
    views = self_supervised_views(
        source, train=config.train_views, fit=config.fit_views, eval=config.eval_views, resolution=config.resolution,
        eval_resolution=config.eval_resolution, background=torch.zeros(3), seed=config.seed,
    )  # fmt: skip
    rows: list[BenchRow] = []
    with tempfile.TemporaryDirectory(prefix="symgs-bench-") as tmp:
        if peers:
            say(f"{name}: peers")
            cached = _cache_file(peer_cache, ply, config) if peer_cache is not None else None
            if cached is not None and cached.exists():
                found = [BenchRow(**r) for r in json.loads(cached.read_text())]
            else:
                found = _peers(ply, name, source, views, find_splat_transform(), Path(tmp), peer_timeout, say)
                if cached is not None:
                    cached.parent.mkdir(parents=True, exist_ok=True)
                    cached.write_text(json.dumps([asdict(r) for r in found]))
            for row in found:
                rows.append(row)
                say(_line(row))
    for preset in presets:
        for use_mirrors in mirrors:
            say(f"{name}: {preset}, mirrors {'on' if use_mirrors else 'off'}")
            run = replace(config, preset=preset, use_mirrors=use_mirrors, psnr_budget=PRESETS[preset].budget)
            rows.append(_ours(ply, name, run, views, "symgs"))
            say(_line(rows[-1]))
    if match and peers:
        reference = next((r for r in rows if r.entry == "spz v3 (splat-transform)"), None)
        reference = reference or next(r for r in rows if r.entry == "spz v3 (symgs)")
        if math.isfinite(reference.psnr):
            say(f"{name}: matched to {reference.entry} at {reference.psnr:.2f} dB")
            budget = budget_for_floor(reference.psnr, config.nominal_psnr)
            run = replace(config, preset="balanced", use_mirrors=True, psnr_budget=min(budget, 60.0))
            rows.append(_ours(ply, name, run, views, f"symgs matched to {reference.entry}"))
            say(_line(rows[-1]))
    return rows


def _cache_file(folder: Path, ply: Path, config: CompressConfig) -> Path:
    stat = ply.stat()
    key = f"{ply.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{config.resolution}|{config.train_views}|" \
          f"{config.eval_views}|{config.seed}"  # fmt: skip
    return folder / f"{ply.stem}-{hashlib.sha256(key.encode()).hexdigest()[:16]}.json"


def _line(row: BenchRow) -> str:
    return (f"  {row.entry} [{row.preset}]: {row.bytes:,} bytes ({row.ratio_to_ply:.1f}x), {row.psnr:.2f} dB, "
            f"encode {row.encode_s:.1f} s, decode {row.decode_s:.2f} s")  # fmt: skip


def to_csv(rows: list[BenchRow]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("inf" if isinstance(v, float) and math.isinf(v) else v) for k, v in asdict(row).items()})
    return out.getvalue()


def to_markdown(rows: list[BenchRow]) -> str:
    lines = [
        "| scene | entry | preset | mirrors | bytes | x smaller than PLY | PSNR (dB) | encode (s) | decode (s) |",
        "|---|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        mirrors = "-" if r.mirrors is None else ("on" if r.mirrors else "off")
        psnr = "lossless" if math.isinf(r.psnr) else f"{r.psnr:.2f}"
        lines.append(f"| {r.scene} | {r.entry} | {r.preset} | {mirrors} | {r.bytes:,} | {r.ratio_to_ply:.1f} | "
                     f"{psnr} | {r.encode_s:.1f} | {r.decode_s:.2f} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def _short(value: float) -> str:
    """Tick labels: 200k, 1.5M, 0.5 (bytes or seconds)."""
    for unit, scale in (("M", 1e6), ("k", 1e3)):
        if value >= scale:
            return f"{value / scale:g}{unit}"
    return f"{value:g}"


def _chart(rows: list[BenchRow], x: str, xlabel: str, title: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    scenes = sorted({r.scene for r in rows})
    cols = min(3, len(scenes))
    fig, axes = plt.subplots(-(-len(scenes) // cols), cols, figsize=(5 * cols, 4 * -(-len(scenes) // cols)),
                             squeeze=False)  # fmt: skip
    finite = [r.psnr for r in rows if math.isfinite(r.psnr)]
    top = (max(finite) + 5.0) if finite else 60.0
    def label(r: BenchRow) -> str:
        return r.entry if r.entry != "symgs" else f"symgs {r.preset} mirrors {'on' if r.mirrors else 'off'}"

    labels = sorted({label(r) for r in rows})
    colours = {name: plt.get_cmap("tab20")(i % 20) for i, name in enumerate(labels)}  # one colour per entry
    for ax, scene in zip(axes.flat, scenes):
        for r in (r for r in rows if r.scene == scene):
            marker = "o" if r.entry.startswith("symgs") else "s"
            ax.scatter(getattr(r, x), r.psnr if math.isfinite(r.psnr) else top, marker=marker, label=label(r),
                       color=colours[label(r)])  # fmt: skip
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: _short(v)))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(scene)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR vs uncompressed (dB; top row: lossless)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6)
    for ax in list(axes.flat)[len(scenes) :]:
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def write_outputs(rows: list[BenchRow], out: Path) -> dict[str, Path]:
    """bench.csv, bench.md, rate_distortion.png (PSNR vs bytes), speed_accuracy.png (PSNR vs encode seconds)."""
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "csv": out / "bench.csv",
        "markdown": out / "bench.md",
        "rate_distortion": out / "rate_distortion.png",
        "speed_accuracy": out / "speed_accuracy.png",
    }
    files["csv"].write_text(to_csv(rows))
    files["markdown"].write_text(to_markdown(rows))
    files["rate_distortion"].write_bytes(_chart(rows, "bytes", "bytes (log)", "Rate-distortion"))
    files["speed_accuracy"].write_bytes(_chart(rows, "encode_s", "encode seconds (log)", "Speed-accuracy"))
    return files
