"""Whether this machine can render jobs on its GPU: gsplat imports, its CUDA kernels are built and load, and a small
scene renders there as the CPU renders it.

    python -m symgs_core.render.gpu --build   # compile the kernels (nvcc needed, no GPU): a GPU image's build step
    python -m symgs_core.render.gpu           # the check a GPU worker runs before it takes jobs (exit 1: why not)

The worker runs the check in a child process: its own process forks the job pool, and CUDA does not survive a fork.
"""

from __future__ import annotations

import argparse
import sys

import torch

# A render of the check scene on the GPU may differ from the CPU's by float32 rounding and gsplat's alpha clamp
# (tests/unit/test_render.py): far less than this on average, while a broken kernel is off by tenths.
AGREE = 5e-3


class GpuUnavailableError(RuntimeError):
    """This machine cannot render on its GPU; the message says why."""


def build_kernels() -> None:
    """gsplat's CUDA kernels, compiled on first use and cached (``TORCH_EXTENSIONS_DIR``); nothing to do later."""
    try:
        from gsplat.cuda._backend import _C
    except ImportError as err:
        raise GpuUnavailableError(f"gsplat (the 'gpu' extra) does not import: {err}") from err
    except Exception as err:  # noqa: BLE001 - a failed nvcc build surfaces as any of several errors
        raise GpuUnavailableError(f"gsplat's CUDA kernels did not build: {err}") from err
    if _C is None:
        raise GpuUnavailableError("gsplat found no CUDA toolkit (nvcc) to build its kernels with")


def check_gpu() -> str:
    """The GPU's name, once a small scene rendered on it matches the CPU's render; else GpuUnavailableError."""
    from ..cameras import Camera
    from ..synthetic import synthetic_scene
    from .dispatch import render

    if not torch.cuda.is_available():
        raise GpuUnavailableError("no CUDA device is visible to this process")
    build_kernels()
    scene = synthetic_scene("global", n=2000, seed=0, sh_degree=3).scene
    camera = Camera.look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 50.0, 64, 48)
    background = torch.tensor([0.2, 0.5, 0.9])
    with torch.no_grad():
        expected = render(scene, camera, background, backend="cpu").image
        try:
            drawn = render(scene.to("cuda"), camera.to("cuda"), background.cuda(), backend="gsplat").image.cpu()
        except Exception as err:  # noqa: BLE001 - kernel launch failures come as RuntimeError or CUDA errors
            raise GpuUnavailableError(f"gsplat's kernels did not run on {torch.cuda.get_device_name()}: {err}") from err
    error = float((drawn - expected).abs().mean())
    if not error < AGREE:
        raise GpuUnavailableError(f"a render on {torch.cuda.get_device_name()} differs from the CPU's by {error:.3g}")
    return torch.cuda.get_device_name()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m symgs_core.render.gpu", description=__doc__.splitlines()[0])
    parser.add_argument("--build", action="store_true", help="only compile gsplat's kernels (no GPU needed)")
    args = parser.parse_args(argv)
    try:
        if args.build:
            build_kernels()
            print("gsplat's CUDA kernels are built")
        else:
            print(f"renders on {check_gpu()} as on the CPU")
    except GpuUnavailableError as err:
        print(str(err), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
