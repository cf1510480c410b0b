"""Third-party Node.js tools that tests run against our files: PlayCanvas ``splat-transform`` (reads and writes the
splat formats) and the Khronos glTF validator. Each pinned version is installed once, with npm, into its own folder
of a cache outside the repository (``SYMGS_NPM_CACHE``, default ``~/.cache/symgs/npm``). A test that needs one
skips, with the reason, when Node.js/npm is missing or the install fails."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

SPLAT_TRANSFORM = "@playcanvas/splat-transform@3.7.0"
# 3.x reads and writes .spz in the PLY's axes without conversion; 2.7 converts from the RUB axes that Niantic's
# format documents, as our .spz does, so the .spz checks stay on 2.7.
SPLAT_TRANSFORM_SPZ = "@playcanvas/splat-transform@2.7.1"
GLTF_VALIDATOR = "gltf-validator@2.0.0-dev.3.10"


def npm_package(spec: str) -> Path:
    """The ``node_modules`` folder holding package ``spec`` (``name@version``), installing it first if needed."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip(f"Node.js/npm not installed: cannot run {spec}")
    name = spec.rsplit("@", 1)[0]
    cache = Path(os.environ.get("SYMGS_NPM_CACHE", Path.home() / ".cache" / "symgs" / "npm"))
    prefix = cache / spec.replace("/", "+")
    package = prefix / "node_modules" / name
    if not (package / "package.json").exists():
        prefix.mkdir(parents=True, exist_ok=True)
        try:
            done = subprocess.run(
                ["npm", "install", "--prefix", str(prefix), "--no-audit", "--no-fund", "--no-save", spec],
                capture_output=True, text=True, timeout=240,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            pytest.skip(f"npm install {spec} timed out (registry unreachable?)")
        if done.returncode != 0 or not (package / "package.json").exists():
            pytest.skip(f"npm install {spec} failed: {done.stderr.strip()[-300:]}")
    return package.parents[name.count("/")]


def splat_transform(spec: str = SPLAT_TRANSFORM) -> str:
    """The ``splat-transform`` executable of ``spec`` from the cache (``SPLAT_TRANSFORM`` names another one)."""
    return os.environ.get("SPLAT_TRANSFORM") or str(npm_package(spec) / ".bin" / "splat-transform")


def convert(exe: str, source: Path, target: Path) -> None:
    """``splat-transform source target`` on the CPU (its SOG writer would otherwise ask for a WebGPU device)."""
    done = subprocess.run(
        [exe, "-w", "-q", "-g", "cpu", str(source), str(target)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
