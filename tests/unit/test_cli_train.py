"""`symgs train`: a scene from posed photographs, progress while it trains, and one-line errors for bad input."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from service.cli import main
from symgs_core.bench.photos import photographed
from symgs_core.ply import load_scene

LINE = re.compile(r"^train: train +(\d+)%  elapsed \d+:\d\d  left (?:\d+:\d\d|-:--)  ")


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("train") / "shots"
    photographed("global", folder, n=200, photos=4, tests=1, resolution=24)
    return folder


def test_train_writes_a_scene_and_scores_it_on_the_held_out_photographs(
    capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "scenes" / "trained.ply"
    argv = ["train", str(capture), "-o", str(out), "--iterations", "20", "--resolution", "24", "--device", "cpu"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert lines and all(LINE.match(line) for line in lines), lines  # plain progress lines, stderr not a terminal
    assert int(LINE.match(lines[-1]).group(1)) == 100  # type: ignore[union-attr]
    scene = load_scene(out)
    assert len(scene) > 0 and scene.sh_degree == 1
    assert re.fullmatch(rf"{re.escape(str(out))}: {len(scene):,} Gaussians, SH degree 1, trained on cpu in \d+ s "
                        r"\(20 steps at 24 px\); PSNR \d+\.\d\d dB on 1 held-out photographs\n", captured.out)


def test_bad_input_exits_2_with_one_line(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV_FISHEYE", "fl_x": 10, "frames": [
        {"file_path": "a.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}))
    (broken / "a.png").write_bytes((capture / "train" / "r_0.png").read_bytes())
    out = str(tmp_path / "s.ply")
    for argv, error in [
        (["train", str(tmp_path / "absent"), "-o", out], "photographs folder"),
        (["train", str(capture), "-o", str(tmp_path / "s.spz")], "written as a .ply file"),
        (["train", str(capture), "-o", out, "--device", "cpu", "--strategy", "mcmc"], "--strategy"),
        (["train", str(capture), "-o", out, "--device", "cpu", "--iterations", "2"], "--iterations must be at least"),
        (["train", str(capture), "-o", out, "--device", "cpu", "--resolution", "8"], "--resolution must be at least"),
        (["train", str(tmp_path), "-o", out, "--device", "cpu"], "unknown_layout: "),
        (["train", str(broken), "-o", out, "--device", "cpu"], "unsupported_camera_model: "),
    ]:  # fmt: skip
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("symgs train: error: ") and error in err and err.count("\n") == 1, err
    assert not (tmp_path / "s.ply").exists()


def test_cuda_asked_for_where_it_cannot_run_is_refused(
    capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["train", str(capture), "-o", str(tmp_path / "s.ply"), "--device", "cuda"]) == 2
    assert capsys.readouterr().err == ("symgs train: error: --device cuda needs a CUDA device; --device cpu trains on "
                                       "the CPU\n")  # fmt: skip
