"""`symgs bench` on a small generated scene with fast settings: the table and both charts appear and parse."""

from __future__ import annotations

import csv
import math

import pytest
from PIL import Image

from service.cli import main
from symgs_core.bench import COLUMNS, budget_for_floor
from symgs_core.config import CompressConfig
from symgs_core.ply import save_scene
from symgs_core.synthetic import synthetic_scene


def test_budget_for_floor_inverts_the_self_supervised_floor() -> None:
    for floor in (38.0, 45.5, 61.6):
        budget = budget_for_floor(floor, 30.0)
        assert CompressConfig(psnr_budget=budget, nominal_psnr=30.0).self_supervised_floor() == pytest.approx(floor)


def test_bench_writes_a_table_and_two_charts(tmp_path, monkeypatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.setenv("SYMGS_NPM_CACHE", str(tmp_path / "no-npm"))  # only our own peers: fast and offline
    monkeypatch.delenv("SPLAT_TRANSFORM", raising=False)
    scene = synthetic_scene("global", n=500, seed=1, sh_degree=1).scene
    save_scene(scene, tmp_path / "tiny.ply")
    out = tmp_path / "out"
    code = main(["bench", str(tmp_path / "tiny.ply"), "--presets", "balanced", "--mirrors", "off", "--out", str(out),
                 "--resolution", "32", "--train-views", "2", "--eval-views", "2", "--iterations", "2",
                 "--max-levels", "1"])  # fmt: skip
    assert code == 0
    rows = list(csv.DictReader((out / "bench.csv").open()))
    assert list(rows[0]) == COLUMNS
    entries = {r["entry"] for r in rows}
    assert {"spz v3 (symgs)", "symgs", "symgs matched to spz v3 (symgs)"} <= entries
    ply_bytes = (tmp_path / "tiny.ply").stat().st_size
    for row in rows:
        assert int(row["bytes"]) > 0
        assert float(row["ratio_to_ply"]) == pytest.approx(ply_bytes / int(row["bytes"]), rel=1e-6)
    spz = next(r for r in rows if r["entry"] == "spz v3 (symgs)")
    matched = next(r for r in rows if r["entry"].startswith("symgs matched"))
    assert float(matched["psnr"]) >= float(spz["psnr"]) or math.isinf(float(matched["psnr"]))
    table = (out / "bench.md").read_text()
    assert table.count("\n") == len(rows) + 2 and "| tiny |" in table
    for chart in ("rate_distortion.png", "speed_accuracy.png"):
        with Image.open(out / chart) as image:
            assert image.format == "PNG" and image.size[0] > 300
    assert "wrote" in capsys.readouterr().out
