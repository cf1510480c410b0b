"""Every benchmark of BENCHMARKS.md, run at the checked-out commit by one command, and its tables rewritten.

    make bench              # everything (hours on 2 cores); rewrites BENCHMARKS.md
    make bench QUICK=1      # a short subset, written to bench-out/BENCHMARKS.quick.md
    .venv/bin/python benchmarks/run_all.py --only codec --scenes kacytran,fox

BENCHMARKS.md holds generated blocks between ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``; everything
outside them (the prose) is kept as it is. Each entry of ``BENCHES`` runs one command, takes the Markdown tables it
prints (with the notes that follow a table, for entries that ask for them) and writes table i into the block named
by its ``tables[i]``, with a line under it saying the commit, date, machine (cores, CPU, load before and after),
tool versions, the command and how long it took. Adding a benchmark is one entry here and its markers in
BENCHMARKS.md (``tests/unit/test_run_all.py`` checks that the two agree).

A benchmark whose data is missing (the real scenes in ``../shared/data``) is skipped and its blocks left as they
were; one that fails leaves its blocks too, and the run ends with a non-zero status.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from symgs_core.bench import splat_transform, stamp  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "bench-out"
DOC = ROOT / "BENCHMARKS.md"
TIMES = ROOT / "benchmarks" / "times.json"  # the last measured wall time of each entry, full and quick
CLI = ("-m", "service.cli.parser")
PASSIVE = {"OMP_WAIT_POLICY": "PASSIVE"}  # waiting OpenMP threads sleep instead of spinning on a shared machine

KACYTRAN = "kacytran_try_iter7000/point_cloud.ply"
PLAYBOT_31K = "playbot_cc_by_sa3d/playbot_lod3_31k_sh2.ply"
PLAYBOT_125K = "playbot_cc_by_sa3d/playbot_lod2_125k_sh2.ply"
DONUT = "donut_mipsplatting/donut_graphdeco_sh0.ply"
FOX = "fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply"
PLANT = "padilla_captures_cc_by/plant_113k_sh0.ply"
TAROT = "padilla_captures_cc_by/academic_tarot_cards_115k_sh0.ply"
SNOWMIKU = "snowmiku_plush_capture_mit"  # photographs and a COLMAP model, no trained scene
LEGO = "nerf_synthetic_lego_400px"  # NeRF-Synthetic photographs, no points, no trained scene
REAL = (KACYTRAN, PLAYBOT_31K, DONUT, FOX, PLANT, TAROT, PLAYBOT_125K)  # smallest first
FOX_CAPTURE = "instant_ngp_fox_capture"  # phone photographs with a distorted camera, no trained scene
CAPTURES = tuple("{data}/" + c for c in (LEGO, SNOWMIKU, FOX_CAPTURE))

# The settings of every run of ours in the codec bench: the presets' own camera sets (8 fitting, 8 evaluation at
# 256 px) and a shorter fine-tune than a job's default (24 training views, 50 steps, at most 2 levels), so the
# whole bench fits in hours on 2 cores.
CODEC = ("--train-views", "24", "--iterations", "50", "--device", "cpu")


@dataclass(frozen=True)
class Bench:
    """One benchmark command and where its tables go.

    full, quick  the arguments after the Python interpreter; quick None: not part of the quick subset. ``{scenes}``
                 stands for the entry's scenes (absolute paths), ``{out}`` for its output folder, ``{data}`` for the
                 data folder
    tables       the block names its printed tables go to, in order
    scenes       data files (relative to the data folder) for ``{scenes}``; ``quick_scenes`` in the quick subset
    notes        take the text lines that follow each table into its block
    copies       (file under ``{out}``, path in the repository) copied after a full run: charts, bench.json
    cuda         runs only where torch sees a CUDA device (``make gpu-check`` runs the same command)
    estimate     how long a full run takes, until one has been timed (``TIMES`` then holds the measured time)
    """

    name: str
    full: tuple[str, ...]
    quick: tuple[str, ...] | None
    tables: tuple[str, ...]
    scenes: tuple[str, ...] = ()
    quick_scenes: tuple[str, ...] = ()
    data: bool = False  # needs the data folder even without {scenes}
    cuda: bool = False  # needs an NVIDIA GPU (and gsplat): skipped elsewhere, its blocks left as they were
    notes: bool = False
    env: dict[str, str] = field(default_factory=dict)
    copies: tuple[tuple[str, str], ...] = ()
    estimate: str = ""


BENCHES: tuple[Bench, ...] = (
    Bench("service", ("benchmarks/bench_api.py", "--clients", "50", "--requests", "10", "--jobs", "6"),
          ("benchmarks/bench_api.py", "--clients", "10", "--requests", "3", "--jobs", "2", "--samples", "2"),
          ("service",)),
    Bench("faults", ("tests/tools/fault_jobs.py", "--jobs", "100", "--workers", "2", "--kills", "10", "--restarts",
                     "10", "--every", "8", "--pace", "1.5"),
          ("tests/tools/fault_jobs.py", "--jobs", "4", "--workers", "1", "--kills", "1", "--restarts", "2", "--every",
           "6", "--pace", "1"),
          ("faults",), notes=True),
    Bench("fuzz", ("tests/tools/fuzz_archive.py", "--mutants", "100000", "--workers", "2"),
          ("tests/tools/fuzz_archive.py", "--mutants", "2000", "--workers", "2"), ("fuzz",), notes=True),
    Bench("renderer", ("benchmarks/bench_render.py", "--repeats", "7", "--view", "4", "--scene", "{scenes}"),
          ("benchmarks/bench_render.py", "--repeats", "2", "--counts", "10000", "50000", "--sizes", "256"),
          ("renderer",), scenes=(PLAYBOT_125K,), notes=True, env=PASSIVE),
    Bench("pipeline-synthetic",
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "nested", "local", "asymmetric", "--capture",
           "independent", "--n", "20000"),
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "asymmetric", "--capture", "independent", "--n",
           "2000", "--iterations", "20", "--max-levels", "1"),
          ("pipeline-synthetic",), env=PASSIVE),
    Bench("pipeline-noise",
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "--capture", "twins", "--noise", "0", "0.001",
           "0.002", "0.004", "0.008", "0.016", "--clutter", "0.3", "--n", "20000"),
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "--capture", "twins", "--noise", "0", "0.004",
           "--clutter", "0.3", "--n", "2000", "--iterations", "20", "--max-levels", "1"),
          ("pipeline-noise",), env=PASSIVE, estimate="about 15 minutes"),
    Bench("pipeline-noise-clutter",
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "--capture", "twins", "--noise", "0.002",
           "--clutter", "1.0", "--n", "20000"),
          None, ("pipeline-noise-clutter",), env=PASSIVE, estimate="about 15 minutes"),
    Bench("pipeline-noise-forced",
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "--capture", "twins", "--noise", "0.004", "0.008",
           "--clutter", "0.3", "--n", "20000", "--tune-gain", "100"),
          None, ("pipeline-noise-forced",), env=PASSIVE, estimate="about 12 minutes"),
    Bench("pipeline-photos",
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "nested", "local", "asymmetric", "--capture",
           "independent", "--n", "20000", "--photos", "64", "--work", "{out}"),
          ("benchmarks/bench_pipeline.py", "--synthetic", "global", "asymmetric", "--capture", "independent", "--n",
           "2000", "--photos", "16", "--photo-resolution", "64", "--iterations", "20", "--max-levels", "1",
           "--work", "{out}"),
          ("pipeline-photos",), env=PASSIVE, estimate="about 20 minutes"),
    Bench("pipeline-real", ("benchmarks/bench_pipeline.py", "--scenes", "{scenes}"), None, ("pipeline-real",),
          scenes=REAL, env=PASSIVE, estimate="about 2 hours"),
    Bench("pipeline-real-small", ("benchmarks/bench_pipeline.py", "--preset", "small", "--scenes", "{scenes}"), None,
          ("pipeline-real-small",), scenes=REAL, env=PASSIVE, estimate="about 10 minutes"),
    Bench("pipeline-real-forced", ("benchmarks/bench_pipeline.py", "--tune-gain", "100", "--scenes", "{scenes}"), None,
          ("pipeline-real-forced",), scenes=(KACYTRAN, PLAYBOT_31K, DONUT, FOX), env=PASSIVE,
          estimate="about 40 minutes"),
    Bench("twins", ("benchmarks/bench_twins.py", "{scenes}", "--synthetic"), None, ("twins",), scenes=REAL,
          env=PASSIVE),
    # The lego scene trained for pipeline-capture: one scene scored by both (trained here when absent).
    Bench("twins-truth", ("benchmarks/bench_twins.py", "--truth", "--captures", "{data}/" + LEGO, "--work",
                          "bench-out/pipeline-capture"),
          None, ("twins-truth",), data=True, env=PASSIVE, estimate="about 30 minutes the first time"),
    Bench("pipeline-capture", ("benchmarks/bench_pipeline.py", "--captures", "{data}/" + LEGO, "{data}/" + SNOWMIKU,
                               "{data}/" + FOX_CAPTURE, "--work", "bench-out/pipeline-capture"),
          None, ("pipeline-capture",), data=True, env=PASSIVE, estimate="about 2 hours the first time (training)"),
    # Where the photographs look: the same trained captures, and a generated object on a slab where the answer is known.
    Bench("focus", ("benchmarks/bench_focus.py", "--generated", "--captures", "{data}/" + LEGO, "{data}/" + SNOWMIKU,
                    "{data}/" + FOX_CAPTURE, "--work", "bench-out/pipeline-capture"),
          ("benchmarks/bench_focus.py", "--generated", "--directions", "50", "--work", "{out}"), ("focus",),
          data=True, env=PASSIVE, estimate="about 10 minutes"),
    Bench("paper", ("benchmarks/bench_paper.py", "--capture", "{data}/" + LEGO, "--work", "bench-out/pipeline-capture"),
          None, ("paper",), data=True, notes=True, env=PASSIVE,
          estimate="hours on 2 cores (two jobs with the photographs at 400 px); minutes on a GPU"),
    Bench("photo-check", ("benchmarks/bench_photo_check.py", "--data", "{data}", "--captures",
                          "bench-out/pipeline-capture"),
          ("benchmarks/bench_photo_check.py", "--n", "1000"), ("photo-check",), data=True, env=PASSIVE),
    # The lego, plush and fox captures trained here (as pipeline-capture trains them, and read from its folder once
    # trained), then the shared scenes, each told trained or decoded from a container by its values.
    Bench("codec", ("benchmarks/bench_codec.py", "--captures", *CAPTURES, "--scenes", "{scenes}", "--work",
                    "bench-out/pipeline-capture", "--out", "{out}", "--", *CODEC, "--max-levels", "2"),
          ("-m", "service.cli.parser", "bench", "{scenes}", "--out", "{out}", "--presets", "balanced", "--sweep", "2",
           "--no-sog", *CODEC, "--max-levels", "1", "--fit-views", "4", "--eval-views", "4", "--eval-resolution",
           "128", "--other-views", "4"),
          ("codec-summary", "codec-equal", "codec-rows", "codec-sections"), scenes=REAL, quick_scenes=(KACYTRAN,),
          data=True, env=PASSIVE, estimate="about 3 hours the first time (training the captures), 1.5 after",
          copies=(("bench.json", "benchmarks/codec/bench.json"),
                  ("charts/rate_distortion.png", "benchmarks/codec/rate_distortion.png"),
                  ("charts/speed_accuracy.png", "benchmarks/codec/speed_accuracy.png"))),
    Bench("budget", ("benchmarks/bench_budget.py", "{scenes}", "--preset", "high"),
          ("benchmarks/bench_budget.py", "{scenes}", "--budgets", "0.3,0.01"), ("budget",),
          scenes=(KACYTRAN, FOX, PLANT), quick_scenes=(KACYTRAN,), env=PASSIVE, estimate="about 10 minutes"),
    Bench("stages", ("benchmarks/bench_stages.py", "{scenes}", "--preset", "balanced", "--train-views", "24",
                     "--iterations", "50", "--max-levels", "2"),
          ("benchmarks/bench_stages.py", "{scenes}", "--train-views", "4", "--iterations", "5", "--max-levels", "1",
           "--fit-views", "2", "--eval-views", "2", "--resolution", "64", "--eval-resolution", "64"),
          ("stages", "stages-levels"), scenes=(PLAYBOT_125K,), quick_scenes=(KACYTRAN,), notes=True, env=PASSIVE),
    Bench("scale", ("benchmarks/bench_scale.py", "--work", "{out}", "--keep-going", "--sizes",
                    "125k,250k,500k,1M,2M"), None, ("scale",), data=True, env=PASSIVE, estimate="about an hour"),
    Bench("scale-fast", ("benchmarks/bench_scale.py", "--work", "{out}", "--preset", "fast", "--sizes", "250k,1M",
                         "--chart", "{out}/scale.png"),
          None, ("scale-fast",), data=True, env=PASSIVE, estimate="about 5 minutes"),
    Bench("scale-trainer", ("benchmarks/bench_scale.py", "--work", "{out}", "--trainer", "--sizes", "1M",
                            "--chart", "{out}/scale.png"),
          None, ("scale-trainer",), data=True, env=PASSIVE, estimate="about 15 minutes"),
    Bench("scale-large", ("benchmarks/bench_scale.py", "--work", "{out}", "--keep-going", "--sizes", "4M,6M",
                          "--time-limit", "3600", "--no-equal", "--chart", "{out}/scale.png"),
          None, ("scale-large",), data=True, env=PASSIVE, estimate="about 40 minutes"),
    Bench("upload", ("benchmarks/bench_upload.py", "--gigabytes", "2"), ("benchmarks/bench_upload.py", "--gigabytes",
          "0.2"), ("upload",)),
    Bench("exports", ("benchmarks/bench_export.py", "{scenes}", "--archives", "{out}"), None, ("exports",),
          scenes=(DONUT, KACYTRAN, PLAYBOT_31K), env=PASSIVE),
    Bench("fuzz-real", ("tests/tools/fuzz_archive.py", "--mutants", "5000", "--workers", "2", "--only-archives",
                        "--archive", "bench-out/exports/donut_graphdeco_sh0.symgs", "--archive",
                        "bench-out/exports/point_cloud.symgs"),
          None, ("fuzz-real",), data=True, notes=True),
    Bench("web-exports", ("benchmarks/bench_web_exports.py", "{scenes}"), None, ("web-exports",),
          scenes=(PLAYBOT_125K, PLANT, KACYTRAN), env=PASSIVE),
    Bench("decode", ("benchmarks/bench_decode.py", "--threads", "2"), ("benchmarks/bench_decode.py", "--repeats", "2"),
          ("decode",)),
    Bench("decode-10m", ("benchmarks/bench_decode.py", "--threads", "2", "--copies", "80", "--repeats", "1",
                         "--detect"),
          None, ("decode-10m",), notes=True),
    Bench("detect-synthetic", ("benchmarks/bench_detect.py", "--sizes", "100000,1000000", "--repeats", "3",
                               "--all-pairs", "1000000"),
          ("benchmarks/bench_detect.py", "--sizes", "100000", "--repeats", "1", "--all-pairs", "100000"),
          ("detect-synthetic",), notes=True),
    Bench("detect-one-thread", ("benchmarks/bench_detect.py", "--sizes", "1000000", "--repeats", "3"), None,
          ("detect-one-thread",), notes=True, env={"OMP_NUM_THREADS": "1"}),
    Bench("detect-10m", ("benchmarks/bench_detect.py", "--sizes", "10000000", "--repeats", "1"), None,
          ("detect-10m",), notes=True),
    Bench("detect-real", ("benchmarks/bench_detect.py", "--sizes", "", "--real", "{data}"),
          ("benchmarks/bench_detect.py", "--sizes", "", "--real", "{data}/kacytran_try_iter7000", "--max-mirrors", "1"),
          ("detect-real",), data=True),
    Bench("gpu", ("benchmarks/gpu_check.py", "--real", "{scenes}", "--base", f"{{data}}/{PLAYBOT_125K}",
                  "--out", "{out}"),
          None, ("gpu-steps", "gpu-timing", "gpu-real"), scenes=REAL, notes=True, cuda=True,
          estimate="about 8 minutes on one H100 or H200"),
)  # fmt: skip


def tables_of(output: str, notes: bool) -> list[str]:
    """The Markdown tables in ``output``, in order; with ``notes``, each followed by the text lines printed after it
    up to the next table (one paragraph each; indented command lines left out)."""
    blocks: list[list[str]] = []
    in_table = False
    for line in output.splitlines():
        if line.startswith("|"):
            if not in_table:
                blocks.append([])
            blocks[-1].append(line.rstrip())
            in_table = True
            continue
        in_table = False
        if notes and blocks and line.strip() and not line.startswith("    "):
            blocks[-1] += ["", line.strip()]
    return ["\n".join(lines) for lines in blocks]


BLOCK = re.compile(r"<!-- bench:(?P<name>[\w.-]+) -->\n.*?<!-- /bench:(?P=name) -->", re.S)


def block_names(text: str) -> list[str]:
    return [m.group("name") for m in BLOCK.finditer(text)]


def _cuda() -> bool:
    """Whether torch sees a CUDA device, asked in a child process (this one never imports torch)."""
    done = subprocess.run([sys.executable, "-c", "import torch; print(torch.cuda.is_available())"],
                          capture_output=True, text=True)  # fmt: skip
    return done.stdout.strip() == "True"


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with block ``name``'s content replaced by ``body``; KeyError when it has no such block."""
    pattern = re.compile(rf"(<!-- bench:{re.escape(name)} -->\n).*?(<!-- /bench:{re.escape(name)} -->)", re.S)
    if not pattern.search(text):
        raise KeyError(f"BENCHMARKS.md has no block {name!r}")
    return pattern.sub(lambda m: m.group(1) + body.rstrip() + "\n" + m.group(2), text, count=1)


def command(bench: Bench, quick: bool, out: Path, only_scenes: list[str] | None) -> list[str] | None:
    """The argv of ``bench``; None when it does not run (not in the quick subset, or its scenes filtered out)."""
    args = bench.quick if quick else bench.full
    if args is None:
        return None
    scenes = bench.quick_scenes if quick and bench.quick_scenes else bench.scenes
    if only_scenes:
        scenes = tuple(s for s in scenes if any(f in s for f in only_scenes))
        if bench.scenes and not scenes:
            return None
    argv = [sys.executable]
    for arg in args:
        if arg == "{scenes}":
            argv += [str(DATA / s) for s in scenes]
        else:
            argv.append(arg.replace("{out}", str(out)).replace("{data}", str(DATA)))
    return argv


def _shown(argv: list[str], env: dict[str, str]) -> str:
    """The command as a reader would type it from the repository's root."""
    shown = [".venv/bin/python" if a == sys.executable else a for a in argv]
    shown = [a.replace(str(DATA), "../shared/data").replace(str(ROOT) + "/", "") for a in shown]
    return " ".join([*(f"{k}={v}" for k, v in env.items()), *map(shlex.quote, shown)])


def _stamp_line(info: dict, end_load: list[float] | None, argv: list[str], env: dict[str, str], seconds: float,
                quick: bool) -> str:  # fmt: skip
    subset = "the quick subset of " if quick else ""
    return (f"<sub>Generated by {subset}`make bench` ({seconds:,.0f} s): {stamp.describe(info, end_load)}. "
            f"Command: `{_shown(argv, env)}`</sub>")  # fmt: skip


def run(bench: Bench, argv: list[str], out: Path, quick: bool) -> tuple[dict[str, str], float, dict]:
    """Run one benchmark; returns its blocks' new content, its wall seconds and the stamp taken as it started.
    RuntimeError when it fails."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **bench.env, "PYTHONPATH": str(ROOT)}
    tool = splat_transform.find()
    info = stamp.stamp(splat_transform.version(tool) if tool and bench.name == "codec" else None)
    t0 = time.perf_counter()
    # Written as it runs, so a long benchmark can be followed (tail -f bench-out/<entry>/stdout.txt).
    with open(out / "stdout.txt", "w") as stdout, open(out / "stderr.txt", "w") as stderr:
        done = subprocess.run(argv, cwd=ROOT, env=env, stdout=stdout, stderr=stderr, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"exit status {done.returncode}: {(out / 'stderr.txt').read_text().strip()[-1500:]}")
    tables = tables_of((out / "stdout.txt").read_text(), bench.notes)
    if len(tables) < len(bench.tables):
        raise RuntimeError(f"printed {len(tables)} tables, {len(bench.tables)} expected; see {out / 'stdout.txt'}")
    line = _stamp_line(info, stamp.machine()["load"], argv, bench.env, seconds, quick)  # type: ignore[arg-type]
    return {name: f"{table}\n\n{line}\n" for name, table in zip(bench.tables, tables)}, seconds, info


def record_time(times: dict, bench: str, quick: bool, seconds: float, info: dict, scenes: list[str] | None) -> None:
    times.setdefault("quick" if quick else "full", {})[bench] = {
        "seconds": round(seconds, 1), "commit": info["commit"], "date": info["date"], "scenes": scenes or "all",
    }  # fmt: skip


def durations_table(times: dict) -> str:
    """The durations block: each entry's last measured full and quick times, and what a full run is expected to
    take where none has been timed whole."""
    lines = ["| entry | full run (s) | measured at | quick subset (s) | expected for a full run |",
             "|---|---:|---|---:|---|"]  # fmt: skip
    total_full = total_quick = 0.0
    for bench in BENCHES:
        full, quick = times.get("full", {}).get(bench.name), times.get("quick", {}).get(bench.name)
        whole = full is not None and full["scenes"] == "all"
        when = "-"
        if full is not None:
            subset = "" if whole else f" (scenes: {', '.join(full['scenes'])})"
            when = f"{full['commit']}, {full['date']}{subset}"
            total_full += full["seconds"] if whole else 0.0
        total_quick += quick["seconds"] if quick else 0.0
        full_s = f"{full['seconds']:,.0f}" if full else "-"
        quick_s = f"{quick['seconds']:,.0f}" if quick else "-"
        lines.append(f"| {bench.name} | {full_s} | {when} | {quick_s} | {'-' if whole else bench.estimate or '-'} |")
    lines.append(f"| all, as measured | {total_full:,.0f} | | {total_quick:,.0f} | |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the short subset; writes bench-out/BENCHMARKS.quick.md")
    parser.add_argument("--only", default="", help="comma-separated entries (default: all)")
    parser.add_argument("--scenes", default="", help="comma-separated parts of scene paths: run only those scenes")
    parser.add_argument("--file", type=Path, help="the Markdown file to rewrite (default: BENCHMARKS.md, or the "
                                                  "quick copy)")  # fmt: skip
    parser.add_argument("--list", action="store_true", help="print the entries and their commands, run nothing")
    parser.add_argument("--durations", action="store_true", help="only rewrite the durations block from "
                                                                 "benchmarks/times.json")  # fmt: skip
    args = parser.parse_args(argv)
    only = [n.strip() for n in args.only.split(",") if n.strip()]
    unknown = sorted(set(only) - {b.name for b in BENCHES})
    if unknown:
        parser.error(f"unknown entries {unknown}; known: {', '.join(b.name for b in BENCHES)}")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()] or None
    target = args.file or (OUT / "BENCHMARKS.quick.md" if args.quick else DOC)
    if args.quick and args.file is None and not args.list:
        OUT.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(DOC, target)
    names = block_names(target.read_text())
    missing = [t for b in BENCHES for t in (*b.tables, "durations") if t not in names]
    if missing:
        parser.error(f"{target} lacks the blocks {', '.join(sorted(set(missing)))}")
    times = json.loads(TIMES.read_text()) if TIMES.exists() else {}
    failed, ran = [], 0.0
    for bench in BENCHES:
        if args.durations or (only and bench.name not in only):
            continue
        out = OUT / bench.name
        argv_ = command(bench, args.quick, out, scenes)
        if argv_ is None:
            continue
        if args.list:
            print(f"{bench.name}: {_shown(argv_, bench.env)}")
            continue
        if (bench.data or bench.scenes) and not DATA.is_dir():
            print(f"{bench.name}: skipped, no data folder at {DATA}", flush=True)
            continue
        if bench.cuda and not _cuda():
            print(f"{bench.name}: skipped, no CUDA device on this machine", flush=True)
            continue
        print(f"{bench.name}: {_shown(argv_, bench.env)}", flush=True)
        try:
            blocks, seconds, info = run(bench, argv_, out, args.quick)
        except RuntimeError as exc:
            print(f"{bench.name}: FAILED, its blocks are left as they were: {exc}", flush=True)
            failed.append(bench.name)
            continue
        ran += seconds
        record_time(times, bench.name, args.quick, seconds, info, scenes if bench.scenes else None)
        TIMES.write_text(json.dumps(times, indent=1) + "\n")
        text = target.read_text()
        for name, body in blocks.items():
            text = replace_block(text, name, body)
        target.write_text(text)
        if not args.quick:
            for source, dest in bench.copies:
                shutil.copyfile(out / source, ROOT / dest)
        print(f"{bench.name}: {seconds:,.0f} s, {len(blocks)} table(s) written to {target}", flush=True)
    if args.list:
        return 0
    target.write_text(replace_block(target.read_text(), "durations", durations_table(times)))
    if not args.durations:
        print(f"done: {ran:,.0f} s" + (f"; FAILED: {', '.join(failed)}" if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
