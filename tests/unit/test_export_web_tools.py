"""Our `.sog` and `.glb` against the tools web platforms use: PlayCanvas ``splat-transform`` 3.7 reads our SOG (bundle
and folder) exactly as our reader does and at the fidelity of the scene it came from, our reader reads its SOG,
its `.glb` of a scene holds what ours holds, and the Khronos glTF validator finds nothing wrong with ours but the
extension it does not know. Skips, with the reason, without Node.js or when npm cannot install a tool."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch

from symgs_core.export import read_glb, read_sog, save_scene, write_glb, write_sog
from symgs_core.export.sog import save_sog_folder
from symgs_core.ply import load_scene
from symgs_core.scene import GaussianScene
from symgs_core.synthetic import synthetic_scene
from tests.npm_tools import GLTF_VALIDATOR, convert, npm_package, splat_transform
from tests.unit.test_export import EDGE_SCENES, edge_scene, same_rotation, scene_for_export

FIDELITY_DB = 30.0


@pytest.fixture(scope="module")
def tool() -> str:
    return splat_transform()


def render_psnr(candidate: GaussianScene, reference: GaussianScene, views: int = 6, resolution: int = 96) -> float:
    """PSNR (dB) of renders of ``candidate`` against renders of ``reference`` from cameras around it."""
    from symgs_core.views import evaluate, self_supervised_views

    held_out = self_supervised_views(reference, train=1, fit=1, eval=views, resolution=16,
                                     eval_resolution=resolution, background=torch.zeros(3))  # fmt: skip
    return evaluate(candidate, held_out.eval, held_out.background).psnr


def assert_same_decode(theirs: GaussianScene, ours: GaussianScene) -> None:
    for name in ("means", "scales", "sh_dc", "sh_rest"):
        assert torch.allclose(theirs.tensors()[name], ours.tensors()[name], atol=1e-6, rtol=1e-6), name
    assert same_rotation(theirs.quats, ours.quats).min() > 1 - 1e-6
    # Their reader maps alpha 0 and 255 to logits of +-13.8, ours to the PLY reader's +-6.2: the same bytes.
    assert (torch.sigmoid(theirs.opacities) - torch.sigmoid(ours.opacities)).abs().max() <= 1 / 510


def test_splat_transform_decodes_our_sog_as_our_reader_does(tool: str, tmp_path: Path) -> None:
    scene = scene_for_export(n=2500, degree=3, seed=5)
    (tmp_path / "ours.sog").write_bytes(write_sog(scene))
    save_sog_folder(scene, tmp_path / "folder" / "meta.json")
    ours = read_sog((tmp_path / "ours.sog").read_bytes())
    for source in (tmp_path / "ours.sog", tmp_path / "folder" / "meta.json"):
        convert(tool, source, tmp_path / "theirs.ply")
        assert_same_decode(load_scene(tmp_path / "theirs.ply"), ours)


@pytest.mark.parametrize("kind", EDGE_SCENES)
def test_splat_transform_decodes_our_edge_scene_sog_as_ours_does(tool: str, tmp_path: Path, kind: str) -> None:
    """One Gaussian (textures of 4 x 4 for one texel), identical ones (codebooks and palette of one entry), a flat
    scene far from the origin (an axis of no extent) with odd quaternions and saturated opacities."""
    (tmp_path / "ours.sog").write_bytes(write_sog(edge_scene(kind)))
    convert(tool, tmp_path / "ours.sog", tmp_path / "theirs.ply")
    assert_same_decode(load_scene(tmp_path / "theirs.ply"), read_sog((tmp_path / "ours.sog").read_bytes()))


def test_splat_transform_reads_our_sog_at_the_fidelity_of_its_source(tool: str, tmp_path: Path) -> None:
    source = synthetic_scene("global", n=3000, seed=2, sh_degree=3).scene
    (tmp_path / "ours.sog").write_bytes(write_sog(source))
    convert(tool, tmp_path / "ours.sog", tmp_path / "theirs.ply")
    theirs = load_scene(tmp_path / "theirs.ply")
    assert len(theirs) == len(source) and theirs.sh_degree == 3
    assert render_psnr(theirs, source) >= FIDELITY_DB


def test_our_reader_decodes_splat_transform_sog(tool: str, tmp_path: Path) -> None:
    save_scene(synthetic_scene("global", n=1500, seed=1, sh_degree=2).scene, tmp_path / "source.ply")
    convert(tool, tmp_path / "source.ply", tmp_path / "theirs.sog")
    convert(tool, tmp_path / "theirs.sog", tmp_path / "theirs.ply")
    assert_same_decode(load_scene(tmp_path / "theirs.ply"), read_sog((tmp_path / "theirs.sog").read_bytes()))


def test_splat_transform_glb_holds_what_ours_holds(tool: str, tmp_path: Path) -> None:
    scene = scene_for_export(n=400, degree=2, seed=8)
    save_scene(scene, tmp_path / "source.ply")
    convert(tool, tmp_path / "source.ply", tmp_path / "theirs.glb")
    theirs, ours = read_glb((tmp_path / "theirs.glb").read_bytes()), read_glb(write_glb(scene))
    for name in ("means", "scales", "opacities", "sh_dc", "sh_rest"):  # both in the same glTF frame
        assert torch.allclose(theirs.tensors()[name], ours.tensors()[name], atol=1e-5), name
    assert same_rotation(theirs.quats, ours.quats).min() > 1 - 1e-6


def test_gltf_validator_finds_nothing_but_the_extension_it_does_not_know(tmp_path: Path) -> None:
    """A random scene and each edge scene (one Gaussian: bounds of one point; a flat one: an axis of no extent)."""
    modules = npm_package(GLTF_VALIDATOR)
    scenes = {"random": scene_for_export(n=300, degree=3)} | {kind: edge_scene(kind) for kind in EDGE_SCENES}
    for name, scene in scenes.items():
        (tmp_path / f"{name}.glb").write_bytes(write_glb(scene))
    script = (
        f"import {{ validateBytes }} from {json.dumps(str(modules / 'gltf-validator' / 'module.mjs'))};\n"
        "import { readFileSync } from 'node:fs';\n"
        "for (const file of process.argv.slice(1)) {\n"
        "  const report = await validateBytes(new Uint8Array(readFileSync(file)), {maxIssues: 1000});\n"
        "  console.log(JSON.stringify(report));\n"
        "}\n"
    )
    done = subprocess.run(
        ["node", "--input-type=module", "-e", script, *(str(tmp_path / f"{name}.glb") for name in scenes)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    reports = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(reports) == len(scenes)
    for name, report in zip(scenes, reports):
        assert report["info"]["version"] == "2.0" and report["info"]["extensionsUsed"] == ["KHR_gaussian_splatting"]
        # This validator predates the extension: it names it unsupported and its attribute semantics unknown, and
        # checks everything else (container, buffers, views, accessors, bounds, POSITION and COLOR_0).
        for message in report["issues"]["messages"]:
            known = message["code"] == "UNSUPPORTED_EXTENSION" and "KHR_gaussian_splatting" in message["message"]
            semantic = message["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" and message["pointer"].startswith(
                "/meshes/0/primitives/0/attributes/KHR_gaussian_splatting:"
            )
            assert known or semantic, (name, message)
        assert report["issues"]["numWarnings"] == 0, name
