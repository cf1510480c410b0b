"""The prepared GPU check (``make gpu-check``): what a machine with an NVIDIA GPU runs, in one command, offline.

    make gpu-check                                   # everything; writes bench-out/gpu/ (gpu.md, gpu.json, log)
    make bench ONLY=gpu                              # the same, its tables written into BENCHMARKS.md
    .venv/bin/python benchmarks/gpu_check.py --real A.ply B.ply --base SCENE.ply --sizes 125k,1M --budget 480

Steps, each timed and each allowed to fail without stopping the rest (the summary says what failed):
1. gsplat's CUDA kernels built (or found built) and checked against the CPU renderer (``symgs_core.render.gpu``),
   and numba's kernels compiled (``symgs_core.warm``), as a worker image builds both;
2. the CUDA tests (``pytest -m cuda``);
3. one job through the API: Redis, ``symgs serve`` and ``symgs worker --mode gpu`` on this machine, a generated SH
   degree 3 scene with a planted mirror, ``device: cuda``; it must succeed and keep a mirror level;
4. every real scene named by ``--real`` (``.ply`` or zstd-compressed ``.ply.zst``) compressed on CUDA;
5. the timing table: 125k, 500k and 1M Gaussians made of turned copies of ``--base`` (the playbot capture, SH degree
   2, in ``make gpu-check``), preset ``balanced``, each compressed on CUDA and on this machine's CPU in a fresh
   process (``--cpu-sizes``: the sizes whose CPU run fits the budget): seconds per stage, wall time, peak GPU and
   host memory, bytes and evaluation PSNR side by side;
6. where time is left, ``torch.profiler`` over the largest size's CUDA job: where the GPU's and the host's time go.

It prints the three tables that BENCHMARKS.md holds in its blocks ``gpu-steps``, ``gpu-timing`` and ``gpu-real``
(``make bench ONLY=gpu`` writes them there on a machine with a GPU) and writes them to ``--out``; ``--budget``
seconds bound the whole run (steps that would not fit are skipped and say so).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SIZES = {"10k": 10_000, "125k": 125_000, "250k": 250_000, "500k": 500_000, "1M": 1_000_000, "2M": 2_000_000}
TIMING_RESERVE = 120  # seconds the real scenes leave to the timing table that follows them
SYMGS = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]


def timing_scene(base, n: int):  # noqa: ANN001, ANN201 - GaussianScene in and out
    """``n // len(base)`` copies of ``base``, each turned a quarter more about the vertical axis, side by side on a
    grid (as the scale benchmark grows a capture): a real capture's values and density at any size."""
    import torch

    from symgs_core.scene import GaussianScene
    from symgs_core.synthetic import Pose, apply_pose

    copies = max(1, n // len(base))
    if copies == 1:
        return base
    extent = float((base.means.max(dim=0).values - base.means.min(dim=0).values).max())
    grid = 1.15 * extent
    scenes = []
    for i in range(copies):
        turn = math.pi / 2 * i
        pose = Pose((math.cos(turn / 2), 0.0, math.sin(turn / 2), 0.0), (grid * (i % 2), 0.0, grid * (i // 2)))
        scenes.append(apply_pose(base, pose))
    return GaussianScene.cat(scenes).map(lambda t: t.to(torch.float32))


def base_scene(path: Path | None):  # noqa: ANN201 - GaussianScene
    """The timing table's base: the scene at ``path`` (``.ply`` or ``.ply.zst``), or without one a generated SH2
    object of 125k Gaussians (one symmetric object of 40 parts, 30% clutter, 0.2% positional noise)."""
    from symgs_core.ply import load_scene
    from symgs_core.synthetic import synthetic_scene

    if path is None:
        return synthetic_scene("global", n=96_000, seed=0, sh_degree=2, parts=40, clutter=0.3, noise=0.002).scene
    return load_scene(_plain(path, Path(tempfile.mkdtemp(prefix="symgs-base-"))))


def _plain(path: Path, work: Path) -> Path:
    """``path`` itself, or its zstd-compressed content written to ``work``."""
    if path.suffix != ".zst":
        return path
    import zstandard

    out = work / path.name.removesuffix(".zst")
    out.write_bytes(zstandard.ZstdDecompressor().decompress(path.read_bytes(), max_output_size=1 << 31))
    return out


# ---------------------------------------------------------------------------------------------------------------
# One compression in a fresh process (``--child``): its report, peak memory and, optionally, a profile.


def child(args: argparse.Namespace) -> None:
    import torch

    from symgs_core.config import CompressConfig
    from symgs_core.pipeline import compress

    config = CompressConfig.for_preset("balanced", device=args.device, pictures=False)
    cuda = args.device == "cuda"
    profiler = host = None
    if args.profile:  # the device's kernels (torch.profiler) and the host's Python functions (cProfile)
        import cProfile

        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        profiler, host = profile(activities=activities), cProfile.Profile()
        profiler.__enter__()
        host.enable()
    t0 = time.perf_counter()
    result = compress(args.scene, config=config)
    if cuda:
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    if profiler is not None and host is not None:
        import pstats

        host.disable()
        profiler.__exit__(None, None, None)
        averages = profiler.key_averages()
        key = "self_cuda_time_total" if cuda else "self_cpu_time_total"
        print(averages.table(sort_by=key, row_limit=25, max_name_column_width=60), file=sys.stderr)
        print(averages.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60), file=sys.stderr)
        pstats.Stats(host, stream=sys.stderr).sort_stats("cumulative").print_stats(60)
    report = result.report
    print("RESULT " + json.dumps({
        "wall": wall,
        "seconds": report.seconds,
        "bytes": len(result.archive),
        "psnr": report.fidelity.psnr,
        "psnr_object": report.fidelity.psnr_object,
        "levels": len(report.accepted_levels),
        "tried": len(report.levels),
        "gpu_peak": torch.cuda.max_memory_allocated() if cuda else 0,
        "rss_peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "cpu_s": sum(resource.getrusage(resource.RUSAGE_SELF)[:2]),
        "device": report.device,
    }))  # fmt: skip


def _env() -> dict[str, str]:
    """This environment, with the project first on the children's path (before what the caller put there)."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}


def run_child(scene: Path, device: str, *, limit: float, profile: bool = False) -> dict:
    argv = [sys.executable, __file__, "--child", "--scene", str(scene), "--device", device]
    if profile:
        argv.append("--profile")
    t0 = time.perf_counter()
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=max(limit, 1.0), env=_env())
    except subprocess.TimeoutExpired:
        return {"error": f"did not finish within {limit:.0f} s"}
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        return {"error": (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1],
                "log": done.stderr[-4000:]}  # fmt: skip
    row = json.loads(lines[-1][len("RESULT "):])
    row["process_s"] = time.perf_counter() - t0
    if profile:
        row["profile"] = done.stderr
    return row


# ---------------------------------------------------------------------------------------------------------------
# The steps.


class Run:
    """The check's clock, log and findings."""

    def __init__(self, budget: float, out: Path) -> None:
        self.start, self.budget, self.out = time.perf_counter(), budget, out
        self.steps: dict[str, dict] = {}
        self.log = (out / "gpu_check.log").open("w")

    def left(self) -> float:
        return self.budget - (time.perf_counter() - self.start)

    def say(self, text: str) -> None:
        line = f"[{time.perf_counter() - self.start:6.1f} s] {text}"
        print(line, flush=True)
        self.log.write(line + "\n")
        self.log.flush()

    def step(self, name: str, fn, *, needs: float = 0.0) -> None:  # noqa: ANN001 - fn: () -> dict
        if self.left() < needs:
            self.steps[name] = {"ok": False, "skipped": f"needs about {needs:.0f} s, {self.left():.0f} s left"}
            self.say(f"{name}: skipped ({self.steps[name]['skipped']})")
            return
        t0 = time.perf_counter()
        try:
            found = fn() or {}
            found.setdefault("ok", True)
        except Exception as err:  # noqa: BLE001 - one failed step must not hide the others' results
            found = {"ok": False, "error": f"{type(err).__name__}: {err}", "trace": traceback.format_exc()[-3000:]}
        found["seconds"] = time.perf_counter() - t0
        self.steps[name] = found
        self.say(f"{name}: {'ok' if found['ok'] else 'FAILED ' + found.get('error', '')} "
                 f"({found['seconds']:.1f} s)")  # fmt: skip


def kernels() -> dict:
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "symgs_core.render.gpu", "--build"], capture_output=True, text=True,
                          env=_env())  # fmt: skip
    build = time.perf_counter() - t0
    if done.returncode != 0:
        return {"ok": False, "error": done.stderr.strip()[-2000:]}
    check = subprocess.run([sys.executable, "-m", "symgs_core.render.gpu"], capture_output=True, text=True,
                           env=_env())  # fmt: skip
    # numba's kernels too, as a worker image builds them: the timing table then measures jobs, not the compiler.
    t0 = time.perf_counter()
    warm = subprocess.run([sys.executable, "-m", "symgs_core.warm"], capture_output=True, text=True, env=_env())
    found = {"ok": check.returncode == 0 and warm.returncode == 0, "build_s": build,
             "check": (check.stdout + check.stderr).strip(), "numba_s": time.perf_counter() - t0}  # fmt: skip
    if warm.returncode != 0:
        found["error"] = "numba's kernels: " + warm.stderr.strip()[-2000:]
    return found


def cuda_tests(out: Path) -> dict:
    # The files that hold CUDA tests, not the whole suite: collecting it would import the S3 and browser tests'
    # dependencies, which a GPU machine need not have.
    tests = sorted((ROOT / "tests").rglob("test_*.py"))
    files = [str(p.relative_to(ROOT)) for p in tests if "pytest.mark.cuda" in p.read_text()]
    done = subprocess.run([sys.executable, "-m", "pytest", "-m", "cuda", "-q", "-p", "no:cacheprovider", *files],
                          capture_output=True, text=True, cwd=ROOT, env=_env())  # fmt: skip
    (out / "cuda_tests.txt").write_text(done.stdout + done.stderr)
    summary = (done.stdout.strip().splitlines() or ["no output"])[-1]
    return {"ok": done.returncode == 0, "summary": summary}


def api_job(work: Path, mode: str = "gpu") -> dict:
    """A generated SH3 scene with a planted mirror through the API and a worker of ``mode`` (gpu: on CUDA)."""
    from service.cli.stack import LocalStack
    from service.client.http import SymgsClient
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    scene = work / "api_sh3.ply"
    # Twins with a little noise, whose level pays at the default preset (a 20,000-Gaussian one kept no level there).
    save_scene(synthetic_scene("global", n=3000, seed=1, sh_degree=3, noise=0.002).scene, scene)
    stack = LocalStack()
    try:
        stack.start_redis()
        stack.start_api()
        stack.start_worker(mode, timeout=900)
        with SymgsClient(stack.api_url, api_key=stack.api_key) as client:
            t0 = time.perf_counter()
            job = client.submit(scene, params={"device": "cuda" if mode == "gpu" else "cpu", "max_levels": 2})
            final = client.wait(job.id)
            seconds = time.perf_counter() - t0
        found = {"ok": final.state == "succeeded" and bool(final.mirrors), "state": final.state, "job_s": seconds,
                 "mirrors": len(final.mirrors), "queue": final.queue}  # fmt: skip
        if final.error is not None:
            found["error"] = f"{final.error.code}: {final.error.message}"
        elif not final.mirrors:
            found["error"] = "the job kept no mirror level"
        return found
    finally:
        worker_log = "\n".join(w.tail(40) for w in stack.workers)
        (work / "api_worker.log").write_text(worker_log)
        stack.cleanup()


def timing(run: Run, work: Path, labels: list[str], cpu_labels: set[str], profile_label: str | None,
           base_path: Path | None) -> dict:  # fmt: skip
    from symgs_core.export import save_scene

    base = base_scene(base_path)
    rows = []
    for label in labels:
        if run.left() < 60:
            rows.append({"label": label, "skipped": f"{run.left():.0f} s of the check's time left"})
            continue
        path = work / f"timing_{label}.ply"
        scene = timing_scene(base, SIZES[label])
        save_scene(scene, path)
        row: dict = {"label": label, "n": len(scene)}
        row["cuda"] = run_child(path, "cuda", limit=run.left() - 20)
        run.say(f"  {label} cuda: {_brief(row['cuda'])}")
        if label in cpu_labels:
            row["cpu"] = run_child(path, "cpu", limit=run.left() - 20)
            run.say(f"  {label} cpu: {_brief(row['cpu'])}")
        rows.append(row)
        path.unlink()
    found = {"rows": rows}
    if profile_label and run.left() > 90:
        path = work / f"timing_{profile_label}.ply"
        save_scene(timing_scene(base, SIZES[profile_label]), path)
        found["profile"] = run_child(path, "cuda", limit=run.left() - 10, profile=True).get("profile", "")
    found["ok"] = all("error" not in r.get(d, {}) for r in rows for d in ("cuda", "cpu") if d in r)
    if not found["ok"]:
        found["error"] = "a run failed: see its row"
    return found


def real_scenes(run: Run, paths: list[Path], work: Path, reserve: float) -> dict:
    """Each scene on CUDA, leaving ``reserve`` seconds to the steps after."""
    rows = []
    for path in paths:
        if run.left() < 30 + reserve:
            rows.append({"scene": path.name, "skipped": f"not run: {run.left():.0f} s of the check's time left"})
            continue
        ply = _plain(path, work)
        row = {"scene": ply.name, **run_child(ply, "cuda", limit=min(run.left() - reserve, 300))}
        run.say(f"  {row['scene']}: {_brief(row)}")
        rows.append(row)
    ok = bool(rows) and all("error" not in r and "skipped" not in r for r in rows)
    return {"rows": rows, "ok": ok, **({} if ok else {"error": "a scene failed or was skipped: see its row"})}


def _brief(row: dict) -> str:
    if "error" in row:
        return "FAILED " + row["error"]
    return f"{row['wall']:.1f} s, {row['bytes']:,} B, {row['psnr']:.2f} dB, {row['levels']} level(s)"


# ---------------------------------------------------------------------------------------------------------------
# The Markdown block.


def _stages(seconds: dict) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in seconds.items())


def markdown(run: Run, info: dict) -> str:
    """Three tables (the steps, the timing table, the real scenes), each followed by its notes: the blocks
    ``gpu-steps``, ``gpu-timing`` and ``gpu-real`` of BENCHMARKS.md."""
    return "\n\n".join([_steps_table(run, info), _timing_table(run), _real_table(run)]) + "\n"


def _steps_table(run: Run, info: dict) -> str:
    lines = ["| step | result | seconds |", "|---|---|---:|"]
    for name, step in run.steps.items():
        if step.get("ok"):
            result = "ok"
        elif "skipped" in step:
            result = "skipped: " + step["skipped"]
        else:
            result = "FAILED: " + (step.get("error") or "see the log").splitlines()[0][:200]
        if name == "kernels" and "build_s" in step:
            result += f" (built in {step['build_s']:.0f} s; {step['check']}; numba's in {step['numba_s']:.0f} s)"
        if name == "cuda tests" and "summary" in step:
            result += f" ({step['summary']})"
        if name == "api job" and "job_s" in step:
            result += (f" ({step['state']} on the {step['queue']} queue in {step['job_s']:.1f} s, "
                       f"{step['mirrors']} level(s))")
        lines.append(f"| {name} | {result} | {step.get('seconds', 0.0):.0f} |")
    lines += ["", f"GPU: {info['gpu']} ({info['gpu_memory_gib']:.0f} GiB), {info['cores']} CPU cores beside it "
              f"({info['cpu']}); torch {info['torch']}, CUDA {info['cuda']}, gsplat {info['gsplat']}."]  # fmt: skip
    return "\n".join(lines)


_TIMING_HEAD = ("| N | device | seconds per stage | wall s | speed-up | peak GPU GiB | peak host GiB | archive B | "
                "size CUDA / CPU | PSNR dB | PSNR CUDA - CPU dB | levels |\n"
                "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")  # fmt: skip


def _timing_table(run: Run) -> str:
    lines = [_TIMING_HEAD]
    step = run.steps.get("timing", {})
    for row in step.get("rows", []):
        if "skipped" in row:
            lines.append(f"| {row['label']} | - | not run: {row['skipped']} | | | | | | | | | |")
            continue
        not_run = {"skipped": "not run: its CPU run does not fit the check's time"}
        gpu, cpu = row["cuda"], row.get("cpu", not_run)
        for device, r in (("cuda", gpu), ("cpu", cpu)):
            if "skipped" in r or "error" in r:
                why = r.get("skipped") or f"FAILED: {r['error'][:160]}"
                lines.append(f"| {row['n']:,} | {device} | {why} | | | | | | | | | |")
                continue
            both = device == "cuda" and "wall" in cpu
            speed = f"{cpu['wall'] / gpu['wall']:.1f}x" if both else ""
            size = f"{gpu['bytes'] / cpu['bytes']:.4f}" if both else ""
            dpsnr = f"{gpu['psnr'] - cpu['psnr']:+.3f}" if both else ""
            lines.append(f"| {row['n']:,} | {device} | {_stages(r['seconds'])} | {r['wall']:.1f} | {speed} | "
                         f"{r['gpu_peak'] / 2**30:.2f} | {r['rss_peak'] / 2**30:.2f} | {r['bytes']:,} | {size} | "
                         f"{r['psnr']:.2f} | {dpsnr} | {r['levels']} |")  # fmt: skip
    if len(lines) == 1:
        lines.append(f"| - | - | not run: {step.get('skipped') or step.get('error') or 'left out'} | | | | | | | | | |")
    return "\n".join(lines)


def _real_table(run: Run) -> str:
    lines = ["| real scene on CUDA | result | wall s | archive B | PSNR dB (full / object) | levels kept / tried |",
             "|---|---|---:|---:|---|---|"]  # fmt: skip
    step = run.steps.get("real scenes", {})
    for r in step.get("rows", []):
        if "error" in r or "skipped" in r:
            lines.append(f"| {r['scene']} | {'FAILED: ' + r['error'][:160] if 'error' in r else r['skipped']} "
                         "| | | | |")  # fmt: skip
        else:
            lines.append(f"| {r['scene']} | ok | {r['wall']:.1f} | {r['bytes']:,} | {r['psnr']:.2f} / "
                         f"{r['psnr_object']:.2f} | {r['levels']} / {r['tried']} |")  # fmt: skip
    if len(lines) == 2:
        lines.append(f"| - | not run: {step.get('skipped') or step.get('error') or 'no scene named'} | | | | |")
    return "\n".join(lines)


def machine() -> dict:
    import torch

    info = {"cores": os.cpu_count(), "cpu": platform.processor() or platform.machine(), "torch": torch.__version__,
            "cuda": torch.version.cuda, "gpu": "none", "gpu_memory_gib": 0.0, "gsplat": "not installed",
            "commit": os.environ.get("SYMGS_COMMIT") or _commit(), "command": " ".join(sys.argv)}  # fmt: skip
    try:
        from symgs_core.bench.stamp import cpu_model

        info["cpu"] = cpu_model()
    except Exception:  # noqa: BLE001 - the model name is a courtesy
        pass
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except ImportError:
        pass
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        info["gpu"], info["gpu_memory_gib"] = props.name, props.total_memory / 2**30
    return info


def _commit() -> str:
    try:
        from symgs_core.bench.stamp import commit

        return commit()
    except Exception:  # noqa: BLE001
        return "unknown"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--scene", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cuda", help=argparse.SUPPRESS)
    parser.add_argument("--profile", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=ROOT / "bench-out" / "gpu")
    parser.add_argument("--real", type=Path, nargs="*", default=[],
                        help="real scenes (.ply or .ply.zst) to compress on CUDA")  # fmt: skip
    parser.add_argument("--sizes", default="125k,500k,1M", help=f"timing table sizes, of {', '.join(SIZES)}")
    parser.add_argument("--cpu-sizes", help="sizes also run on the CPU (default: every size)")
    parser.add_argument("--base", type=Path, help="the timing table's base scene (default: a generated one)")
    parser.add_argument("--profile-size", default="500k", help="size profiled at the end ('' for none)")
    parser.add_argument("--budget", type=float, default=480.0, help="seconds the whole check may take")
    parser.add_argument("--skip", default="", help="steps to leave out: kernels,tests,api,timing,real")
    args = parser.parse_args()
    if args.child:
        child(args)
        return 0

    args.out.mkdir(parents=True, exist_ok=True)
    run = Run(args.budget, args.out)
    info = machine()
    run.say(f"{info['gpu']}, {info['cores']} cores, torch {info['torch']} (CUDA {info['cuda']}), "
            f"gsplat {info['gsplat']}")
    skip = set(filter(None, args.skip.split(",")))
    work = Path(tempfile.mkdtemp(prefix="symgs-gpu-check-"))
    if "kernels" not in skip:
        run.step("kernels", kernels)
    if "tests" not in skip:
        run.step("cuda tests", lambda: cuda_tests(args.out), needs=60)
    if "api" not in skip:
        run.step("api job", lambda: api_job(work), needs=45)
    if "real" not in skip and args.real:
        reserve = 0.0 if "timing" in skip else TIMING_RESERVE
        run.step("real scenes", lambda: real_scenes(run, args.real, work, reserve), needs=30)
    if "timing" not in skip:
        labels = [s for s in args.sizes.split(",") if s]
        cpu_labels = set(labels if args.cpu_sizes is None else args.cpu_sizes.split(","))
        run.step("timing", lambda: timing(run, work, labels, cpu_labels, args.profile_size or None, args.base),
                 needs=60)  # fmt: skip
    block = markdown(run, info)
    stamp = (f"<sub>Generated by `benchmarks/gpu_check.py` ({time.perf_counter() - run.start:.0f} s): commit "
             f"{info['commit']}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Command: "
             f"`{info['command']}`</sub>")  # fmt: skip
    (args.out / "gpu.md").write_text(block + "\n" + stamp + "\n")
    found = {"machine": info, "steps": run.steps}
    (args.out / "gpu.json").write_text(json.dumps(found, indent=1, default=str))
    profile = run.steps.get("timing", {}).get("profile")
    if profile:
        (args.out / "profile.txt").write_text(profile)
    print(block)
    return 0 if all(step.get("ok") for step in run.steps.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
