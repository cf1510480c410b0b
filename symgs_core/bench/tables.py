"""The bench as Markdown: equal fidelity per peer over all scenes, per scene and peer, then every row."""

from __future__ import annotations

import math
import statistics

from .rows import TOLERANCE_DB, BenchRow


def _db(value: float | None) -> str:
    if value is None:
        return "-"
    return "lossless" if math.isinf(value) else f"{value:.2f}"


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def _times(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}x"


def _held(value: bool | None) -> str:
    return {None: "-", True: "yes", False: "**no**"}[value]


KINDS = {True: "trained", False: "decoded from a container", None: "all"}


def summary_table(rows: list[BenchRow]) -> str:
    """Per peer, and per kind of scene where the rows say (trained first, then decoded from quantised containers):
    how many scenes our curve spans its PSNR, and our size at its PSNR over the peer's (median, range); how many of
    the claims hold on the other rig."""
    lines = [
        "| peer | scenes | compared | peer / ours at equal PSNR: median | min | max | "
        "claims that hold on other cameras |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    peers = list(dict.fromkeys(r.method for r in rows if r.role == "peer"))
    kinds = [kind for kind in (True, False, None) if any(r.trained is kind for r in rows)]
    for peer in peers:
        for kind in kinds:
            theirs = [r for r in rows if r.method == peer and r.trained is kind]
            mine = [r for r in theirs if r.equal_psnr_ratio is not None]
            ratios = [r.equal_psnr_ratio for r in mine if r.equal_psnr_ratio is not None]
            claimed = [r for r in mine if r.claim_holds_other is not None]
            held = sum(bool(r.claim_holds_other) for r in claimed)
            scenes = len({r.scene for r in theirs})
            if not ratios:
                lines.append(f"| {peer} | {KINDS[kind]} | 0 of {scenes} | - | - | - | - |")
                continue
            lines.append(f"| {peer} | {KINDS[kind]} | {len(ratios)} of {scenes} | {statistics.median(ratios):.2f}x | "
                         f"{min(ratios):.2f}x | {max(ratios):.2f}x | {held} of {len(claimed)} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def equal_table(rows: list[BenchRow]) -> str:
    """One line per scene and peer: the peer's file, our size at its PSNR, and the check on the other cameras."""
    lines = [
        "| scene | kind | peer | peer bytes | peer PSNR (dB) | ours at that PSNR (bytes) | peer / ours | "
        "peer / ours, object pixels | peer PSNR, other cameras | peer / ours, other cameras | holds on other cameras |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        if r.role != "peer":
            continue
        kind = "-" if r.trained is None else KINDS[r.trained]
        if not r.ok:
            lines.append(f"| {r.scene} | {kind} | {r.method} | {r.status.replace('_', ' ')} | - | - | - | - | - | - | "
                         "- |")  # fmt: skip
            continue
        ratio = "not spanned" if r.equal_psnr_ratio is None else _times(r.equal_psnr_ratio)
        lines.append(f"| {r.scene} | {kind} | {r.method} | {r.bytes:,} | {_db(r.psnr_db)} | "
                     f"{_num(r.equal_psnr_bytes, ',.0f')} | {ratio} | {_times(r.equal_psnr_object_ratio)} | "
                     f"{_db(r.psnr_other_db)} | {_times(r.equal_psnr_other_ratio)} | "
                     f"{_held(r.claim_holds_other)} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def rows_table(rows: list[BenchRow]) -> str:
    lines = [
        "| scene | method | preset | budget (dB) | bytes | x smaller than PLY | PSNR (dB) | object PSNR | "
        "PSNR, other cameras | SSIM | encode (s) | decode (s) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if not r.ok:
            lines.append(f"| {r.scene} | {r.method} | - | - | {r.status.replace('_', ' ')} | - | - | - | - | - | - "
                         "| - |")  # fmt: skip
            continue
        budget = "-" if r.budget_db is None else f"{r.budget_db:.3g}" + (" (sweep)" if r.role == "sweep" else "")
        lines.append(f"| {r.scene} | {r.method} | {r.preset or '-'} | {budget} | {r.bytes:,} | {r.ratio:.1f} | "
                     f"{_db(r.psnr_db)} | {_db(r.psnr_object_db)} | {_db(r.psnr_other_db)} | {r.ssim:.4f} | "
                     f"{r.encode_s:.1f} | {r.decode_s:.2f} |")  # fmt: skip
    return "\n".join(lines) + "\n"


SECTION_COLUMNS = ("means", "quats", "scales", "opacities", "sh_dc", "sh_degrees|sh_index", "sh_band_1", "sh_band_2",
                   "sh_band_3", "header|bits|classes")  # fmt: skip


def sections_table(rows: list[BenchRow], preset: str = "balanced") -> str:
    """Where our archive's bytes go, per scene, at ``preset`` (mirrors on where they ran): bytes per decoded Gaussian
    and each part's share of the archive (the higher SH's index and each band apart)."""
    names = [c.replace("|", " / ") for c in SECTION_COLUMNS]
    lines = ["| scene | bytes | bytes per decoded Gaussian | " + " | ".join(names) + " |",
             "|---|---:|---:|" + "---:|" * len(names)]  # fmt: skip
    runs = [r for r in rows if r.ours and r.ok and r.role == "preset" and r.preset == preset and r.sections]
    for scene in dict.fromkeys(r.scene for r in runs):
        r = max((r for r in runs if r.scene == scene), key=lambda r: bool(r.mirrors))
        sections = r.sections or {}
        size = r.bytes or sum(sections.values())
        shares = [sum(sections.get(part, 0) for part in column.split("|")) / size for column in SECTION_COLUMNS]
        cells = " | ".join(f"{share:.0%}" if share else "-" for share in shares)
        per = f"{size / r.gaussians:.2f}" if r.gaussians else "-"
        lines.append(f"| {r.scene} | {size:,} | {per} | {cells} |")
    return "\n".join(lines) + "\n"


def markdown(rows: list[BenchRow]) -> str:
    """The four tables, in that order, separated by blank lines (the order ``benchmarks/run_all.py`` reads)."""
    note = (f"A claim holds on other cameras when our curve there reaches the peer's PSNR (less {TOLERANCE_DB} dB) "
            "in fewer bytes than the peer's file.")  # fmt: skip
    return "\n".join([summary_table(rows), equal_table(rows), rows_table(rows), sections_table(rows), note]) + "\n"
