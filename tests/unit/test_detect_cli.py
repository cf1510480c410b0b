"""`symgs detect` through the command line's entry point."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.cli import main
from symgs_core.export import save_scene
from symgs_core.synthetic import synthetic_scene


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    s = synthetic_scene("local", n=3000, seed=1, sh_degree=1)
    path = tmp_path_factory.mktemp("detect") / "local.ply"
    save_scene(s.scene, path)
    return path, s


def test_json_output_parses_with_counts(scene_file, capsys: pytest.CaptureFixture[str]) -> None:
    path, s = scene_file
    assert main(["detect", str(path), "--json", "--max-mirrors", "2"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["gaussians"] == len(s.scene)
    assert len(report["mirrors"]) == 2
    for m, planted in zip(report["mirrors"], s.planes, strict=True):
        assert set(m) >= {"normal", "offset", "votes", "left", "right", "coverage", "level", "timings"}
        assert isinstance(m["left"], int) and isinstance(m["right"], int)
        cos = abs(sum(a * b for a, b in zip(m["normal"], planted.normal, strict=True)))
        assert cos > 0.9999
    first = report["mirrors"][0]
    assert first["coverage"] == pytest.approx((first["left"] + first["right"]) / len(s.scene))
    assert {"load", "detect", "vote", "membership"} <= set(report["timings"])


def test_text_output_lists_mirrors_and_step_times(scene_file, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = scene_file
    assert main(["detect", str(path), "--max-mirrors", "1"]) == 0
    out = capsys.readouterr().out
    assert "level 0: normal (" in out and "coverage" in out and "vote " in out


def test_errors_are_user_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["detect", str(tmp_path / "missing.ply")]) == 2
    assert "does not exist" in capsys.readouterr().err
    broken = tmp_path / "broken.ply"
    broken.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n")
    assert main(["detect", str(broken)]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["detect", str(broken), "--min-coverage", "2"]) == 2
    assert "min_coverage" in capsys.readouterr().err


def test_an_unreadable_scene_names_the_code_the_api_would(scene_file, tmp_path: Path, capsys) -> None:
    path, _ = scene_file
    cut = tmp_path / "cut.ply"
    cut.write_bytes(path.read_bytes()[:-100])
    assert main(["detect", str(cut)]) == 2
    assert capsys.readouterr().err.startswith(f"symgs detect: error: cannot read {cut}: truncated: ")


def test_photographs_name_where_to_search_and_bad_ones_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from symgs_core.bench.photos import photographed

    made = synthetic_scene("global", n=3000, seed=3, sh_degree=1, surroundings=20.0)
    photos = tmp_path / "photos"
    photographed("global", photos, n=200, photos=6, tests=1, resolution=32, sh_degree=0)  # cameras around the origin
    path = tmp_path / "among.ply"
    save_scene(made.scene, path)
    assert main(["detect", str(path), "--json", "--max-mirrors", "1"]) == 0
    planes = [(m["normal"][0], m["offset"]) for m in json.loads(capsys.readouterr().out)["mirrors"]]
    assert not any(abs(n) > 0.999 and abs(g) < 0.02 for n, g in planes)  # 5% of the scene, touching its slab
    assert main(["detect", str(path), "--json", "--max-mirrors", "1", "--images", str(photos)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["focus"]["radius"] > 0 and len(report["mirrors"]) == 1
    first = report["mirrors"][0]
    assert abs(first["normal"][0]) > 0.999 and abs(first["offset"]) < 0.02  # the planted plane, x = 0
    assert main(["detect", str(path), "--images", str(photos)]) == 0
    assert "the photographs' cameras look at (" in capsys.readouterr().out
    assert main(["detect", str(path), "--images", str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["detect", str(path), "--images", str(tmp_path / "empty")]) == 2
    assert "cannot read" in capsys.readouterr().err
