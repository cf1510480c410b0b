"""Where and when a figure was measured: commit, date, machine (cores, load, CPU) and tool versions.

Benchmarks write this under every table they produce, so a figure can be traced to the code and the machine that
made it. Nothing here fails: a fact that cannot be found is reported as unknown.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


# What ``make bench`` itself writes while it runs: a change there is not a change of the code measured.
_OUTPUTS = ("BENCHMARKS.md", "benchmarks/times.json", "benchmarks/codec/", "benchmarks/scale/")


def commit() -> str:
    """The checked-out commit (short hash), with ``+changes`` when tracked files other than the benchmarks' own
    outputs differ from it."""
    head = _git("rev-parse", "--short=12", "HEAD")
    if head is None:
        return "unknown"
    changed = _git("diff", "--name-only", "HEAD") or ""  # tracked files, staged or not
    dirty = [name for name in changed.splitlines() if not name.startswith(_OUTPUTS)]
    return head + ("+changes" if dirty else "")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load() -> tuple[float, float, float] | None:
    try:
        return os.getloadavg()
    except OSError:
        return None


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "absent"


def machine() -> dict[str, object]:
    avg = load()
    return {
        "cores": os.cpu_count(),
        "cpu": cpu_model(),
        "load": [round(v, 2) for v in avg] if avg else None,
        "system": f"{platform.system()} {platform.release()}",
    }


def tools(splat_transform: str | None = None) -> dict[str, str]:
    found = {"python": platform.python_version()}
    for package in ("symgs", "torch", "numba", "numpy", "zstandard", "constriction"):
        found[package] = _version(package)
    if splat_transform is not None:
        found["splat-transform"] = splat_transform
    return found


def stamp(splat_transform: str | None = None) -> dict[str, object]:
    """Commit, UTC date, machine and tool versions, as a JSON-ready dict."""
    return {
        "commit": commit(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "tools": tools(splat_transform),
    }


def describe(info: dict[str, object], end_load: list[float] | None = None) -> str:
    """One line for under a table: commit and date; cores, CPU and load (at the start, and at the end when given);
    tool versions."""
    m = info["machine"]
    tools = info["tools"]
    assert isinstance(m, dict) and isinstance(tools, dict)
    loads = [(m.get("load"), "at the start"), (end_load, "at the end")]
    load = ", ".join(f"{' / '.join(f'{v:.1f}' for v in avg)} {when}" for avg, when in loads if avg)
    versions = ", ".join(f"{k} {v}" for k, v in tools.items() if v != "absent")
    return (f"commit {info['commit']}, {info['date']}; {m.get('cores')} cores ({m.get('cpu')})"
            f"{f', load average {load}' if load else ''}; {versions}")  # fmt: skip
