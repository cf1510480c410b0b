"""Scale: `symgs compress` of a real capture from 125k to 6M Gaussians, seconds per stage and peak memory, against
PlayCanvas splat-transform writing `.spz` of the same file in the same run.

Scenes (SH degree 2): the playbot capture at full detail, 500k Gaussians (the shared SOG decoded by splat-transform);
seeded random subsets of it (125k, 250k); copies of it turned about the vertical axis and set side by side, two
abreast (1M: two, 2M: four, 4M: eight, 6M: twelve; positions, rotations and SH turn with them). Each is written as a
graphdeco `.ply` into ``--work``. With ``--trainer`` each is made as a trainer writes its scenes
(``as_trained``): every value moved off the SOG's grids by a small seeded jitter, and a third SH band added.

Every run is its own process, one after the other: `symgs compress` (preset balanced unless ``--preset``), then
splat-transform writing `.spz` v4 (its default) and v3 from the same `.ply`, then, unless ``--no-fidelity``,
`symgs evaluate` of our archive and of the `.spz` v4 on the same 8 cameras. Where our archive scores below the
`.spz` there, one more `symgs compress` with the budget whose floor is the `.spz`'s PSNR (``equal``) gives our size
at no lower fidelity, as a codec comparison must. Peak RSS is each process's maximum
resident set (the kernel's ``ru_maxrss``; for a run that the time limit kills, its ``VmHWM`` just before). The
kernel counts in ``ru_maxrss`` what the process held before it replaced itself with the command, a copy of this
one: so this process stays small (the scenes are made, and the kernels compiled, in a child of their own) and
records its own resident memory at each start (``parent_rss_mib``), a floor under every peak it reports. A
compression past ``--time-limit`` is recorded as timed out with the last progress line it printed, and the larger
sizes are then skipped unless ``--keep-going``. Results accumulate in ``WORK/scale.json`` (a rerun of a size replaces
it); the table is printed as Markdown and the chart (time and memory against N, log-log, with a linear reference)
written to ``--chart``.

    .venv/bin/python benchmarks/bench_scale.py --work bench-scale --time-limit 1800
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # torch is imported in the child that makes the scenes only
    from symgs_core.scene import GaussianScene

ROOT = Path(__file__).resolve().parents[1]
SOG = ROOT.parent / "shared/data/playbot_cc_by_sa3d/sog_lod0_500k/meta.json"
SIZES = {"125k": 125_000, "250k": 250_000, "500k": 500_000, "1M": 1_000_000, "2M": 2_000_000, "4M": 4_000_000,
         "6M": 6_000_000}
BASE = 500_000
GRID = 1.6  # metres between the copies' centres: the capture spans about 1.4 across
SYMGS = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]


@dataclass
class Child:
    """One measured process."""

    rc: int | None  # None: killed at the time limit
    seconds: float  # wall clock, process start to exit
    cpu_s: float
    peak_bytes: int

    @property
    def timed_out(self) -> bool:
        return self.rc is None


def _vm(pid: int, field: str = "VmHWM:") -> int:
    """A ``/proc/<pid>/status`` memory figure in bytes (0 once the process is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def run_child(cmd: list[str], *, limit_s: float, log: Path, env: dict[str, str] | None = None) -> Child:
    """Run ``cmd`` with stdout and stderr into ``log``; kill its process group past ``limit_s``."""
    t0 = time.perf_counter()
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        elapsed = time.perf_counter() - t0
        if pid:
            proc.returncode = rc = os.waitstatus_to_exitcode(status)
            return Child(rc, elapsed, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024)
        if elapsed > limit_s:
            peak = _vm(proc.pid)
            os.killpg(proc.pid, signal.SIGKILL)
            _, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
            return Child(None, elapsed, usage.ru_utime + usage.ru_stime, max(peak, usage.ru_maxrss * 1024))
        time.sleep(0.25)


def splat_transform() -> str:
    from symgs_core.bench import splat_transform as tool

    try:
        return tool.find() or tool.install()
    except tool.ToolError as exc:
        sys.exit(f"splat-transform: {exc}")


def setup(work: Path, labels: list[str], sog: Path, trainer: bool) -> tuple[str, dict[str, Path]]:
    """splat-transform, the scenes' files and compiled kernels, from a child process (see the module's notes)."""
    argv = [sys.executable, __file__, "--setup", "--work", str(work), "--sizes", ",".join(labels), "--sog", str(sog),
            *(["--trainer"] if trainer else [])]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(argv, check=True, stdout=subprocess.PIPE, text=True, env=env)
    found = json.loads(done.stdout.strip().splitlines()[-1])
    return found["exe"], {label: Path(p) for label, p in found["paths"].items()}


def _rss_mib() -> float:
    return _vm(os.getpid(), "VmRSS:") / 2**20


def warm_up(work: Path) -> None:
    """A tiny compression first, so that no measured run pays numba's first compilation of the kernels."""
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    tiny = work / "warm_up.ply"
    save_scene(synthetic_scene("global", n=2000, seed=0, sh_degree=2).scene, tiny)
    cmd = [*SYMGS, "compress", str(tiny), "-o", str(work / "warm_up.symgs"),
           "--iterations", "2", "--resolution", "32", "--train-views", "2", "--eval-views", "1", "--quiet"]  # fmt: skip
    subprocess.run(cmd, check=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True)


def as_trained(scene: GaussianScene, seed: int) -> GaussianScene:
    """``scene`` as a trainer writes it, float32 on no grid and with SH degree 3: each value moved by a seeded
    jitter small against what it holds (positions by 1e-3 of the scene's extent, rotations by 0.02, log-scales by
    0.05, opacity logits by 0.1, DC colour by 0.01, the SH bands by 0.005), and a third band drawn with 0.6 of the
    second's mean magnitude per Gaussian and channel."""
    import torch

    from symgs_core.scene import GaussianScene

    g = torch.Generator().manual_seed(seed)
    jitter = lambda x, sd: x + sd * torch.randn(x.shape, generator=g)  # noqa: E731
    extent = float((scene.means.max(dim=0).values - scene.means.min(dim=0).values).max())
    rest = scene.sh_rest
    band3 = torch.randn((len(scene), 7, 3), generator=g) * 0.6 * rest[:, 3:8].abs().mean(dim=1, keepdim=True)
    return GaussianScene(
        means=jitter(scene.means, 1e-3 * extent), quats=jitter(scene.quats, 0.02), scales=jitter(scene.scales, 0.05),
        opacities=jitter(scene.opacities, 0.1), sh_dc=jitter(scene.sh_dc, 0.01),
        sh_rest=torch.cat([jitter(rest, 0.005), band3], dim=1),
    )  # fmt: skip


def prepare(work: Path, labels: list[str], exe: str, sog: Path, trainer: bool) -> dict[str, Path]:
    """The scenes' `.ply` files, made once and kept in ``work``."""
    paths = {label: work / f"playbot_{label}{'_trainer' if trainer else ''}.ply" for label in labels}
    if all(p.exists() for p in paths.values()):
        return paths
    import torch

    from symgs_core.export import save_scene
    from symgs_core.ply import load_scene
    from symgs_core.scene import GaussianScene
    from symgs_core.synthetic import Pose, apply_pose

    decoded = work / "playbot_sog_500k.ply"
    if not decoded.exists():
        if not sog.exists():
            sys.exit(f"the shared playbot SOG is missing: {sog}")
        done = subprocess.run([exe, "-w", "-q", str(sog), str(decoded)], capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"splat-transform could not decode {sog}: {done.stderr[-500:]}")
    base = load_scene(decoded)
    assert len(base) == BASE, len(base)
    for label, path in paths.items():
        if path.exists():
            continue
        n = SIZES[label]
        if n <= BASE:
            keep = torch.randperm(BASE, generator=torch.Generator().manual_seed(0))[:n].sort().values
            scene = base.select(keep)
        else:
            copies = []
            for i in range(n // BASE):
                turn = math.pi / 2 * i  # about y, the capture's vertical axis
                pose = Pose((math.cos(turn / 2), 0.0, math.sin(turn / 2), 0.0), (GRID * (i % 2), 0.0, GRID * (i // 2)))
                copies.append(apply_pose(base, pose))
            scene = GaussianScene.cat(copies)
        if trainer:
            scene = as_trained(scene, seed=n)
        save_scene(scene, path)
        print(f"wrote {path} ({len(scene):,} Gaussians)", flush=True)
    return paths


def last_progress(log: Path) -> str:
    lines = [line for line in log.read_text(errors="replace").splitlines() if line.startswith("compress: ")]
    return lines[-1][len("compress: ") :].strip() if lines else ""


def measure(label: str, ply: Path, args: argparse.Namespace, exe: str) -> dict:
    out = args.work / label
    out.mkdir(exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # the children run this checkout's code
    row: dict = {"label": label, "gaussians": SIZES[label], "ply_bytes": ply.stat().st_size, "preset": args.preset,
                 "time_limit_s": args.time_limit, "load_before": os.getloadavg()[0],
                 "parent_rss_mib": _rss_mib()}  # fmt: skip

    archive, report = out / "out.symgs", out / "report.json"
    for stale in (archive, report):
        stale.unlink(missing_ok=True)
    cmd = [*SYMGS, "compress", str(ply), "-o", str(archive), "--report", str(report), "--preset", args.preset,
           *args.compress_args.split()]  # fmt: skip
    print(f"[{label}] symgs {' '.join(cmd[len(SYMGS):])}", flush=True)
    run = run_child(cmd, limit_s=args.time_limit, log=out / "compress.log", env=env)
    row["symgs"] = asdict(run)
    row["load_after"] = os.getloadavg()[0]
    if run.timed_out:
        row["reached"] = last_progress(out / "compress.log")
        print(f"[{label}] timed out after {run.seconds:.0f} s at: {row['reached']}", flush=True)
    elif run.rc != 0:
        row["error"] = (out / "compress.log").read_text(errors="replace")[-1500:]
        print(f"[{label}] failed: {row['error']}", flush=True)
    else:
        r = json.loads(report.read_text())
        row.update(stages=r["seconds"], archive_bytes=r["output_bytes"], psnr_report=r["fidelity"]["psnr"])
        peak = run.peak_bytes / 2**30
        print(f"[{label}] {run.seconds:.1f} s, peak {peak:.2f} GiB, {r['output_bytes']:,} B", flush=True)

    for version in (4, 3):
        spz = out / f"peer_v{version}.spz"
        peer = run_child([exe, "-w", "-q", str(ply), str(spz), "--spz-version", str(version)],
                         limit_s=args.time_limit, log=out / f"spz_v{version}.log")  # fmt: skip
        row[f"spz_v{version}"] = {**asdict(peer), "bytes": spz.stat().st_size if peer.rc == 0 else None}
        print(f"[{label}] splat-transform .spz v{version}: {peer.seconds:.1f} s", flush=True)

    if not args.no_fidelity and "stages" in row:
        # The .spz as splat-transform itself reads it back (its 3.x releases keep .spz in the PLY's axes).
        read_back = out / "peer_v4.ply"
        subprocess.run([exe, "-w", "-q", str(out / "peer_v4.spz"), str(read_back)], capture_output=True, check=False)
        for key, candidate in (("psnr_symgs", archive), ("psnr_spz_v4", read_back)):
            row[key] = evaluated(ply, candidate, env)
        if None not in (row["psnr_symgs"], row["psnr_spz_v4"]) and row["psnr_symgs"] < row["psnr_spz_v4"]:
            skipped = {"skipped": True}
            row["equal"] = skipped if args.no_equal else equal_fidelity(label, ply, row["psnr_spz_v4"], args, env)
    return row


def equal_fidelity(label: str, ply: Path, psnr: float, args: argparse.Namespace, env: dict[str, str]) -> dict:
    """Our archive with the floor raised to ``psnr`` (the `.spz`'s): its bytes, PSNR on the same cameras, time."""
    from symgs_core.config import CompressConfig, budget_for_floor

    out = args.work / label / "equal"
    out.mkdir(exist_ok=True)
    archive, report = out / "out.symgs", out / "report.json"
    budget = budget_for_floor(psnr, CompressConfig.for_preset(args.preset).nominal_psnr)
    cmd = [*SYMGS, "compress", str(ply), "-o", str(archive), "--report", str(report), "--preset", args.preset,
           "--psnr-budget", f"{budget:.6f}", *args.compress_args.split()]  # fmt: skip
    print(f"[{label}] at the .spz's PSNR: symgs {' '.join(cmd[len(SYMGS):])}", flush=True)
    run = run_child(cmd, limit_s=args.time_limit, log=out / "compress.log", env=env)
    if run.rc != 0:
        return {"run": asdict(run), "floor_db": psnr}
    return {"run": asdict(run), "floor_db": psnr, "bytes": archive.stat().st_size,
            "psnr": evaluated(ply, archive, env)}  # fmt: skip


def evaluated(ply: Path, candidate: Path, env: dict[str, str]) -> float | None:
    """`symgs evaluate`'s PSNR of ``candidate`` against ``ply`` (None where it fails)."""
    done = subprocess.run([*SYMGS, "evaluate", str(ply), str(candidate), "--json"], capture_output=True, text=True,
                          env=env)  # fmt: skip
    return json.loads(done.stdout)["psnr"] if done.returncode == 0 else None


# -- table and chart -------------------------------------------------------------------------------------------


def _stages(row: dict) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in row.get("stages", {}).items())


def _equal(row: dict) -> str:
    """The run at the `.spz`'s PSNR: ``-`` where ours already scored no lower (or none was made)."""
    equal = row.get("equal")
    if equal is None:
        return "-"
    if equal.get("skipped"):
        return "not run (`--no-equal`)"
    if "bytes" not in equal:
        return f"failed (exit {equal['run']['rc']})"
    psnr = "-" if equal["psnr"] is None else f"{equal['psnr']:.2f}"
    return f"{equal['bytes']:,}, {psnr} ({equal['run']['seconds']:.0f})"


def table(rows: list[dict]) -> str:
    lines = [
        "| N | seconds per stage | `symgs compress` wall s | CPU s | peak RSS GiB | `.spz` v4 s (peak MiB) "
        "| ratio to `.spz` v4 | `.spz` v3 s | archive B | `.spz` v4 B | PSNR archive / `.spz` v4 dB "
        "| at the `.spz`'s PSNR: archive B, dB (s) | load avg |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|",
    ]
    for row in rows:
        s, v4, v3 = row["symgs"], row["spz_v4"], row["spz_v3"]
        if s["rc"] is None:
            wall = f"> {s['seconds']:.0f} (timed out at: {row.get('reached') or 'start'})"
        elif s["rc"] != 0:
            wall = f"failed (exit {s['rc']})"
        else:
            wall = f"{s['seconds']:.1f}"
        peak = f"{'>= ' if s['rc'] is None else ''}{s['peak_bytes'] / 2**30:.2f}"
        ratio = f"{s['seconds'] / v4['seconds']:.0f}x" if s["rc"] == 0 and v4["rc"] == 0 else "-"
        fmt = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        psnr = f"{fmt(row.get('psnr_symgs'))} / {fmt(row.get('psnr_spz_v4'))}" if "psnr_symgs" in row else "-"
        size = lambda x: "-" if x is None else f"{x:,}"  # noqa: E731
        lines.append(
            f"| {row['gaussians']:,} | {_stages(row) or '-'} | {wall} | {s['cpu_s']:.0f} | {peak} "
            f"| {v4['seconds']:.1f} ({v4['peak_bytes'] / 2**20:.0f}) | {ratio} | {v3['seconds']:.1f} "
            f"| {size(row.get('archive_bytes'))} | {size(v4.get('bytes'))} | {psnr} | {_equal(row)} "
            f"| {row['load_before']:.1f} / {row['load_after']:.1f} |"
        )
    done = {r["label"]: r["symgs"] for r in rows if r["symgs"]["rc"] == 0}
    if "250k" in done and "1M" in done:
        wall, cpu = (done["1M"][k] / done["250k"][k] for k in ("seconds", "cpu_s"))
        lines.append(f"\nFrom 250k to 1M the time grows {wall:.2f}x, the CPU time {cpu:.2f}x (target: at most 4.6x).")
    return "\n".join(lines)


def chart(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(11, 4.4))
    n = [r["gaussians"] for r in rows]
    ok = [r for r in rows if r["symgs"]["rc"] == 0]
    late = [r for r in rows if r["symgs"]["rc"] is None]
    for ax, key, unit, scale in ((ax_t, "seconds", "seconds", 1.0), (ax_m, "peak_bytes", "peak RSS, GiB", 2**-30)):
        ax.plot([r["gaussians"] for r in ok], [r["symgs"][key] * scale for r in ok], "o-", label="symgs compress")
        if late:
            ax.plot([r["gaussians"] for r in late], [r["symgs"][key] * scale for r in late], "^", color="C0",
                    markerfacecolor="none", label="symgs compress, timed out (at least)")  # fmt: skip
        ax.plot(n, [r["spz_v4"][key] * scale for r in rows], "s-", label="splat-transform .spz v4")
        first = (ok or late)[0] if (ok or late) else None
        if first is not None:
            y0 = first["symgs"][key] * scale
            ax.plot(n, [y0 * x / first["gaussians"] for x in n], "k--", lw=0.8, label="linear in N")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("Gaussians")
        ax.set_ylabel(unit)
        ax.grid(True, which="both", alpha=0.3)
    ax_t.plot([r["gaussians"] for r in ok], [r["symgs"]["cpu_s"] for r in ok], "o--", color="C0", alpha=0.5,
              markerfacecolor="none", label="symgs compress, CPU seconds (all threads)")  # fmt: skip
    if ok:
        stages = sorted({k for r in ok for k in r["stages"]}, key=lambda k: -max(r["stages"].get(k, 0) for r in ok))
        for k in stages[:5]:
            ax_t.plot([r["gaussians"] for r in ok], [max(r["stages"].get(k, 0.0), 1e-2) for r in ok], ".:", lw=0.8,
                      label=f"stage {k}")  # fmt: skip
    ax_t.set_title("time")
    ax_m.set_title("peak memory")
    ax_t.legend(fontsize=7)
    ax_m.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(SIZES), help=f"labels among {', '.join(SIZES)}")
    parser.add_argument("--preset", default="balanced")
    parser.add_argument("--compress-args", default="", help="more `symgs compress` options, one string")
    parser.add_argument("--time-limit", type=float, default=1800.0, help="seconds per run")
    parser.add_argument("--sog", type=Path, default=SOG, help="the playbot SOG's meta.json")
    parser.add_argument("--work", type=Path, default=Path("bench-scale"), help="scenes, outputs and scale.json")
    parser.add_argument("--chart", type=Path, default=ROOT / "benchmarks/scale/scale.png")
    parser.add_argument("--keep-going", action="store_true", help="run the larger sizes after a timeout")
    parser.add_argument("--no-fidelity", action="store_true", help="skip `symgs evaluate` of archive and .spz")
    parser.add_argument("--no-equal", action="store_true",
                        help="no second run at the .spz's PSNR where our archive scores below it")
    parser.add_argument("--trainer", action="store_true",
                        help="scenes as a trainer writes them: off the SOG's grids, SH degree 3 (``as_trained``)")
    parser.add_argument("--table-only", action="store_true", help="print the table and chart of scale.json")
    parser.add_argument("--setup", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT))  # this checkout's code, as its children run it
    labels = [s for s in args.sizes.split(",") if s]
    unknown = [s for s in labels if s not in SIZES]
    if unknown:
        parser.error(f"unknown sizes {unknown}; choose among {list(SIZES)}")
    args.work = args.work.resolve()
    args.work.mkdir(parents=True, exist_ok=True)
    results = args.work / "scale.json"
    rows = {r["label"]: r for r in json.loads(results.read_text())} if results.exists() else {}
    if args.setup:
        exe = splat_transform()
        paths = prepare(args.work, labels, exe, args.sog, args.trainer)
        warm_up(args.work)
        print(json.dumps({"exe": exe, "paths": {label: str(p) for label, p in paths.items()}}))
        return
    if not args.table_only:
        exe, paths = setup(args.work, labels, args.sog, args.trainer)
        for label in labels:
            row = measure(label, paths[label], args, exe)
            rows[label] = row
            results.write_text(json.dumps(sorted(rows.values(), key=lambda r: r["gaussians"]), indent=1))
            if row["symgs"]["rc"] is None and not args.keep_going:
                print(f"larger sizes skipped after the timeout at {label} (--keep-going runs them)", flush=True)
                break
    ordered = sorted(rows.values(), key=lambda r: r["gaussians"])
    if ordered:
        chart(ordered, args.chart)
        print(table(ordered))
        print(f"\nchart: {args.chart}")


if __name__ == "__main__":
    main()
