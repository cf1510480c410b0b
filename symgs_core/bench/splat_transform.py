"""PlayCanvas ``splat-transform`` (npm), the peer that benchmarks and job charts compare against.

One pinned version, installed with npm into a cache folder outside the repository (``SYMGS_NPM_CACHE``, default
``~/.cache/symgs/npm``, one sub-folder per version so other pins on the same machine stay as they are), run as a
subprocess under a time limit. ``SPLAT_TRANSFORM`` names an executable to use instead of the pinned one (its
version is then whatever it reports).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path

VERSION = "3.7.0"
PACKAGE = f"@playcanvas/splat-transform@{VERSION}"
INSTALL_TIMEOUT_S = 240.0


class ToolError(RuntimeError):
    """splat-transform is missing, cannot be installed, or failed on a file (the message says which)."""


def cache_folder() -> Path:
    root = Path(os.environ.get("SYMGS_NPM_CACHE", Path.home() / ".cache" / "symgs" / "npm"))
    return root / f"splat-transform-{VERSION}"


def find() -> str | None:
    """The executable to run: ``SPLAT_TRANSFORM`` when set, else the pinned version in the cache, else None."""
    given = os.environ.get("SPLAT_TRANSFORM")
    if given:
        return given
    exe = cache_folder() / "node_modules" / ".bin" / "splat-transform"
    return str(exe) if exe.exists() else None


def install(timeout: float = INSTALL_TIMEOUT_S) -> str:
    """The pinned executable, installed with npm first when the cache lacks it; ToolError says why it cannot be."""
    found = find()
    if found:
        return found
    if shutil.which("npm") is None or shutil.which("node") is None:
        raise ToolError(f"Node.js and npm are needed to install {PACKAGE}")
    folder = cache_folder()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        done = subprocess.run(
            ["npm", "install", "--prefix", str(folder), "--no-audit", "--no-fund", PACKAGE],
            capture_output=True, text=True, timeout=timeout,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        raise ToolError(f"npm install {PACKAGE} ran past {timeout:.0f} s (registry unreachable?)") from None
    found = find()
    if done.returncode != 0 or found is None:
        raise ToolError(f"npm install {PACKAGE} failed: {done.stderr.strip()[-300:]}")
    return found


def version(exe: str) -> str:
    """The version ``exe`` reports (e.g. ``3.7.0``); ToolError when it does not run."""
    try:
        done = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ToolError(f"{exe} --version: {exc}") from None
    found = re.search(r"v?(\d+\.\d+\.\d+)", done.stdout + done.stderr)
    if done.returncode != 0 or found is None:
        raise ToolError(f"{exe} --version failed: {(done.stdout + done.stderr).strip()[-200:]}")
    return found.group(1)


def convert(exe: str, source: Path, target: Path, options: tuple[str, ...], timeout: float) -> float:
    """Convert ``source`` into ``target`` (formats by extension); returns the wall seconds it took.

    subprocess.TimeoutExpired when it runs past ``timeout`` seconds (the process is killed); ToolError when it fails.
    """
    t0 = time.perf_counter()
    try:
        done = subprocess.run([exe, "-w", "-q", str(source), str(target), *options], capture_output=True, text=True,
                              timeout=timeout)  # fmt: skip
    except OSError as exc:
        raise ToolError(f"cannot run {exe}: {exc}") from None
    seconds = time.perf_counter() - t0
    if done.returncode != 0 or not target.exists():
        raise ToolError(f"splat-transform {source.name} -> {target.name}: {done.stderr.strip()[-400:]}")
    return seconds
