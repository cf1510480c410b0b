"""How a job reads photographs larger than its judges need (``views.photo_reading``), and what its report says."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from symgs_core.bench.photos import photographed
from symgs_core.views import dataset_views, photo_reading
from tests.conftest import shared_file


def test_photographs_are_judged_at_the_jobs_resolution_never_above_their_own(tmp_path: Path) -> None:
    scene = photographed("global", tmp_path, n=200, photos=6, tests=2, resolution=64)
    smaller = dataset_views(tmp_path, scene, fit=2, eval=2, resolution=32, background=torch.zeros(3))
    assert smaller.read is not None and (smaller.read.width, smaller.read.height, smaller.read.scale) == (64, 64, 0.5)
    assert "decoded at 0.5 of their 64x64" in smaller.read.reason and "eval_resolution, 32 px" in smaller.read.reason
    assert all(v.image.shape == (32, 32, 3) for v in [*smaller.train, *smaller.fit, *smaller.eval])
    assert {s.resolution for s in smaller.sets} == {32}
    whole = dataset_views(tmp_path, scene, fit=2, eval=2, resolution=256, background=torch.zeros(3))
    assert whole.read is not None and whole.read.scale == 1.0 and "their own size, 64x64" in whole.read.reason
    assert all(v.image.shape == (64, 64, 3) for v in whole.eval)  # a render larger than its photograph invents pixels
    assert whole.on(torch.ones(3)).read == whole.read  # laid on another background, read as it was


@pytest.mark.realdata
def test_phone_photographs_say_how_they_were_read() -> None:
    read = photo_reading(shared_file("instant_ngp_fox_capture"), 256)
    assert (read.width, read.height) == (1067, 1898) and read.scale == pytest.approx(256 / 1898)
    assert "(undistorted from 1080x1920)" in read.reason and "up to 1898" in read.reason
