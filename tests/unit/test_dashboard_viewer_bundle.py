"""The committed 3D view bundle (``service/dashboard/static/viewer.js`` and its licence file) is exactly what its
build makes from ``service/dashboard/viewer/`` with the locked packages, and stays under the 2 MB a committed file
may weigh. Skips, with the reason, without Node.js or when npm cannot install the locked packages."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import pytest

VIEWER = Path(__file__).resolve().parents[2] / "service" / "dashboard" / "viewer"
STATIC = VIEWER.parent / "static"


def test_committed_bundle_is_the_build_of_the_source() -> None:
    assert (STATIC / "viewer.js").stat().st_size < 2 * 1024 * 1024
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("Node.js/npm not installed: cannot rebuild the viewer bundle")
    lock = (VIEWER / "package-lock.json").read_bytes()
    cache = Path(os.environ.get("SYMGS_NPM_CACHE", Path.home() / ".cache" / "symgs" / "npm"))
    build = cache / f"viewer-{hashlib.sha256(lock).hexdigest()[:16]}" / "viewer"
    if not (build / "node_modules").is_dir():
        build.mkdir(parents=True, exist_ok=True)
        for name in ("package.json", "package-lock.json"):
            shutil.copy(VIEWER / name, build / name)
        done = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=build, capture_output=True, text=True,
                              timeout=300)  # fmt: skip
        if done.returncode != 0:
            shutil.rmtree(build / "node_modules", ignore_errors=True)
            pytest.skip(f"npm ci failed: {done.stderr.strip()[-300:]}")
    shutil.copy(VIEWER / "build.mjs", build / "build.mjs")
    shutil.rmtree(build / "src", ignore_errors=True)
    shutil.copytree(VIEWER / "src", build / "src")
    done = subprocess.run(["node", "build.mjs"], cwd=build, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    for name in ("viewer.js", "viewer-license.txt"):
        assert (build.parent / "static" / name).read_bytes() == (STATIC / name).read_bytes(), (
            f"{name} is stale: run `npm ci && npm run build` in service/dashboard/viewer"
        )
