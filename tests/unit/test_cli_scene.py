"""`symgs info` and `symgs render` driven through the command line's own entry point."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from service.cli import main
from symgs_core.cameras import orbit_cameras, scene_bounds
from symgs_core.export import save_scene
from symgs_core.render import render
from symgs_core.scene import GaussianScene
from tests.conftest import PROJECT_ROOT, shared_file
from tests.unit.test_datasets import poses, write_nerf


def blob_scene(n: int = 200, degree: int = 1, seed: int = 0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianScene(
        means=torch.randn(n, 3, generator=g) * torch.tensor([1.0, 0.5, 0.3]),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.randn(n, 3, generator=g) * 0.2 - 2.5,
        opacities=torch.randn(n, generator=g) + 1.0,
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, k, 3, generator=g) * 0.1,
    )


@pytest.fixture
def scene_file(tmp_path: Path) -> tuple[GaussianScene, Path]:
    scene = blob_scene()
    save_scene(scene, tmp_path / "blob.ply")
    return scene, tmp_path / "blob.ply"


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_info_json(scene_file: tuple[GaussianScene, Path], capsys: pytest.CaptureFixture[str]) -> None:
    scene, path = scene_file
    code, out, _ = run(["info", str(path), "--json"], capsys)
    assert code == 0
    info = json.loads(out)
    assert info["count"] == 200 and info["sh_degree"] == 1 and info["repairs"] == {}
    np.testing.assert_allclose(info["bounds"]["min"], scene.means.min(dim=0).values.numpy(), rtol=1e-6)
    np.testing.assert_allclose(info["bounds"]["max"], scene.means.max(dim=0).values.numpy(), rtol=1e-6)
    assert info["properties"][:6] == ["x", "y", "z", "nx", "ny", "nz"] and len(info["properties"]) == 26
    assert info["ignored"] == ["nx", "ny", "nz"]


def test_info_text_reports_repairs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = blob_scene(10, degree=3)
    opacities = scene.opacities.clone()
    opacities[:3] = float("inf")
    quats = scene.quats.clone()
    quats[4] = 0.0
    save_scene(scene.with_(opacities=opacities, quats=quats), tmp_path / "r.ply")
    code, out, _ = run(["info", str(tmp_path / "r.ply")], capsys)
    assert code == 0
    assert "gaussians   10" in out and "sh degree   3" in out
    assert "f_rest_0..44" in out and "(62)" in out
    assert "opacity_pos_inf_clamped: 3" in out and "zero_quaternion_set_to_identity: 1" in out
    assert "ignored     nx ny nz\n" in out


def test_info_text_on_a_scene_of_no_gaussians(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    save_scene(GaussianScene.empty(), tmp_path / "zero.ply")
    code, out, err = run(["info", str(tmp_path / "zero.ply")], capsys)
    assert code == 0 and err == ""
    assert "gaussians   0\n" in out and "bounds      empty\n" in out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "does not exist"),
        (b"hello", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n", "missing required properties"),
    ],
)
def test_info_errors_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None, message: str
) -> None:
    path = tmp_path / "bad.ply"
    if content is not None:
        path.write_bytes(content)
    code, out, err = run(["info", str(path)], capsys)
    assert code == 2 and out == ""
    assert err.startswith("symgs info: error:") and message in err


@pytest.mark.parametrize("command", [["info"], ["render", "--orbit", "0", "-o", "OUT"]])
@pytest.mark.parametrize(("damage", "error"), [("truncate", "truncated"), ("replace", "not_ply")])
def test_unreadable_scenes_name_the_code_the_api_would(
    scene_file: tuple[GaussianScene, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    command: list[str],
    damage: str,
    error: str,
) -> None:
    _, path = scene_file
    data = path.read_bytes()
    path.write_bytes(data[:-100] if damage == "truncate" else b"hello")
    argv = [command[0], str(path), *(str(tmp_path / "x.png") if a == "OUT" else a for a in command[1:])]
    code, out, err = run(argv, capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"symgs {command[0]}: error: cannot read {path}: {error}: "), err


def test_render_orbit_writes_the_rendered_view(
    scene_file: tuple[GaussianScene, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scene, path = scene_file
    out_png = tmp_path / "out" / "orbit.png"
    argv = ["render", str(path), "--orbit", "3", "--views", "6", "--width", "48", "--height", "36"]
    code, out, _ = run([*argv, "--background", "0,0.5,1", "--backend", "cpu", "-o", str(out_png)], capsys)
    assert code == 0 and "48x36" in out and "orbit camera 3 of 6" in out
    center, radius = scene_bounds(scene.means)
    camera = orbit_cameras(center, radius, 6, 48, 36)[3]
    expected = render(scene, camera, torch.tensor([0.0, 0.5, 1.0])).image.clamp(0, 1).numpy()
    written = np.asarray(Image.open(out_png), dtype=np.float64) / 255
    assert written.shape == (36, 48, 3)
    assert np.abs(written - expected).max() <= 0.5 / 255 + 1e-6
    assert np.abs(written - [0.0, 0.5, 1.0]).max() > 0.2  # the scene is in view


def test_render_dataset_view(
    scene_file: tuple[GaussianScene, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, path = scene_file
    cams = poses(3)
    write_nerf(tmp_path / "data", {"train": cams[:2], "test": cams[2:]})
    out_png = tmp_path / "view.png"
    code, out, _ = run(
        ["render", str(path), "--dataset", str(tmp_path / "data"), "--view", "2", "-o", str(out_png)], capsys
    )
    assert code == 0 and "view 2 (./test/r_0) of 3" in out
    assert "PSNR" in out and "SSIM" in out
    assert Image.open(out_png).size == (40, 30)
    code, out, _ = run(["render", str(path), "--dataset", str(tmp_path / "data"), "--split", "test", "--view", "0",
                        "--width", "20", "-o", str(out_png)], capsys)  # fmt: skip
    assert code == 0 and Image.open(out_png).size == (20, 15)
    expected = render(blob_scene(), cams[2].resized(20, 15), torch.ones(3)).image.numpy()
    written = np.asarray(Image.open(out_png), dtype=np.float64) / 255
    assert np.abs(written - expected).max() <= 0.5 / 255 + 1e-6


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--dataset", "DATA", "--view", "3"], "view 3 is out of range: split 'all' has 3 views (0..2)"),
        (["--dataset", "DATA"], "--dataset needs --view"),
        (["--dataset", "NOWHERE", "--view", "0"], "does not exist"),
        (["--orbit", "8"], "orbit camera 8 is out of range"),
        (["--orbit", "0", "--view", "1"], "--view goes with --dataset"),
        (["--orbit", "0", "--background", "1,1"], "--background must be three numbers"),
        (["--orbit", "0", "--width", "0"], "--width must be in 1..16384"),
        (["--orbit", "0", "--up", "0,0,0"], "--up must not be the zero vector"),
    ],
)
def test_render_errors_exit_2(
    scene_file: tuple[GaussianScene, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    extra: list[str],
    message: str,
) -> None:
    _, path = scene_file
    cams = poses(3)
    write_nerf(tmp_path / "data", {"train": cams})
    extra = [
        str(tmp_path / "data") if a == "DATA" else str(tmp_path / "nowhere") if a == "NOWHERE" else a for a in extra
    ]
    code, _, err = run(["render", str(path), *extra, "-o", str(tmp_path / "x.png")], capsys)
    assert code == 2 and message in err, err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize(
    ("output", "message"),
    [
        ("adir", "-o adir is a folder; a file is expected there"),
        ("afile/x.png", "-o afile/x.png: afile is a file, not a folder"),
    ],
)
def test_render_unwritable_output_exit_2_before_rendering(
    scene_file: tuple[GaussianScene, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    output: str,
    message: str,
) -> None:
    _, path = scene_file
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("symgs_core.render.render", lambda *a, **k: pytest.fail("rendered"))
    code, out, err = run(["render", str(path), "--orbit", "0", "-o", output], capsys)
    assert code == 2 and out == "" and err == f"symgs render: error: {message}\n"


def test_render_missing_scene_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(["render", str(tmp_path / "none.ply"), "--orbit", "0", "-o", str(tmp_path / "x.png")], capsys)
    assert code == 2 and "does not exist" in err


def test_info_on_the_real_fox(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(["info", str(shared_file("fox_cc0_mujoco_warp/fox.ply")), "--json"], capsys)
    info = json.loads(out)
    assert code == 0 and info["count"] == 50000 and info["repairs"] == {"opacity_pos_inf_clamped": 37}
    assert "nx" not in info["properties"]


def test_the_command_module_imports_no_torch() -> None:
    code = "import sys, service.cli.scene; print(any(m == 'torch' or m.startswith('symgs_core') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
