"""A GPU worker that could not render a job refuses to start, and says why, before it takes any."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from tests.conftest import PROJECT_ROOT


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_a_gpu_worker_without_a_cuda_device_exits_at_start_with_the_reason() -> None:
    symgs = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]
    argv = [*symgs, "worker", "--mode", "gpu"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=PROJECT_ROOT,
                          env={"PATH": "/usr/bin:/bin", "SYMGS_REDIS_URL": "redis://127.0.0.1:1/0"})  # fmt: skip
    assert done.returncode != 0
    assert "no CUDA device is visible" in done.stderr and "run a cpu worker here" in done.stderr


@pytest.mark.cuda
def test_the_gpu_check_names_what_is_missing() -> None:
    from symgs_core.render.gpu import GpuUnavailableError, check_gpu

    if torch.cuda.is_available():
        pytest.importorskip("gsplat")
        assert check_gpu() == torch.cuda.get_device_name()
    else:
        with pytest.raises(GpuUnavailableError, match="no CUDA device"):
            check_gpu()
