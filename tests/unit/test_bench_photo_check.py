"""``benchmarks/bench_photo_check.py``: one row per upload against a photograph set, on a small generated capture."""

from __future__ import annotations

from pathlib import Path

from benchmarks.bench_photo_check import row
from symgs_core.bench.photos import photographed
from symgs_core.synthetic import synthetic_scene


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_a_row_accepts_photographs_of_the_upload_and_refuses_another_scenes(tmp_path: Path) -> None:
    shown = photographed("global", tmp_path, n=1500, photos=4, tests=1, resolution=48)
    other = synthetic_scene("asymmetric", n=1500, seed=5, sh_degree=1).scene
    accepted = _cells(row("shown", "of global", shown, tmp_path, fit=2, resolution=48))
    refused = _cells(row("another scene", "of global", other, tmp_path, fit=2, resolution=48))
    assert accepted[0] == "shown" and accepted[-1] == "accepted"
    assert refused[-1] == "images_mismatch"
    for cells in (accepted, refused):
        assert 0.0 < float(cells[2].rstrip("%")) <= 100.0  # the share of pixels the upload draws
    assert float(accepted[5]) > 3.0 > float(refused[5])  # the margin over a flat colour decides
