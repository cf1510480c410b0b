"""glTF binary with KHR_gaussian_splatting: the container and document the extension asks for, the glTF frame
(our RDF scene turned 180 degrees about z, SH included), exact round trips, a pinned checksum, and refusals."""

from __future__ import annotations

import hashlib
import json
import struct

import numpy as np
import pytest
import torch

from symgs_core.export import GlbError, export_scene, import_scene, read_glb, write_glb
from symgs_core.export.formats import by_path
from symgs_core.export.glb import EXTENSION, read_glb_document
from symgs_core.scene import GaussianScene
from symgs_core.sh import eval_sh
from symgs_core.synthetic import quat_to_matrix
from tests.unit.test_export import scene_for_export

TURN = torch.diag(torch.tensor([-1.0, -1.0, 1.0]))  # RDF -> LUF, 180 degrees about z


def accessor(document: dict, binary: bytes, name: str) -> np.ndarray:
    a = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"][name]]
    view = document["bufferViews"][a["bufferView"]]
    dtype = {5126: "<f4", 5121: "u1"}[a["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a["type"]]
    return np.frombuffer(binary, dtype=dtype, count=a["count"] * width, offset=view["byteOffset"]).reshape(-1, width)


def test_document_is_a_points_primitive_with_the_extension() -> None:
    scene = scene_for_export(n=300, degree=2)
    data = write_glb(scene)
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_length, json_kind = struct.unpack_from("<II", data, 12)
    assert json_kind == 0x4E4F534A and json_length % 4 == 0
    document, binary = read_glb_document(data)
    assert len(binary) % 4 == 0 and document["asset"]["version"] == "2.0"
    assert document["extensionsUsed"] == [EXTENSION] and "extensionsRequired" not in document
    primitive = document["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0
    assert primitive["extensions"][EXTENSION] == {
        "kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
        "sortingMethod": "cameraDistance",
    }  # fmt: skip
    sh = [f"{EXTENSION}:SH_DEGREE_{ell}_COEF_{m}" for ell in (0, 1, 2) for m in range(2 * ell + 1)]
    expected = {"POSITION", "COLOR_0", f"{EXTENSION}:ROTATION", f"{EXTENSION}:SCALE", f"{EXTENSION}:OPACITY", *sh}
    assert set(primitive["attributes"]) == expected
    for view in document["bufferViews"]:
        assert view["byteOffset"] % 4 == 0 and view["byteOffset"] + view["byteLength"] <= len(binary)
    for a in document["accessors"]:
        assert a["count"] == 300
    position = accessor(document, binary, "POSITION")
    a = document["accessors"][primitive["attributes"]["POSITION"]]
    assert a["min"] == position.min(axis=0).tolist() and a["max"] == position.max(axis=0).tolist()
    rotation = accessor(document, binary, f"{EXTENSION}:ROTATION")
    assert np.allclose(np.linalg.norm(rotation, axis=1), 1.0, atol=1e-6)
    assert (accessor(document, binary, f"{EXTENSION}:SCALE") > 0).all()
    opacity = accessor(document, binary, f"{EXTENSION}:OPACITY")
    assert np.allclose(opacity[:, 0], torch.sigmoid(scene.opacities).numpy(), atol=1e-6)
    colour = document["accessors"][primitive["attributes"]["COLOR_0"]]
    assert colour["componentType"] == 5121 and colour["normalized"] and colour["type"] == "VEC4"


def test_values_are_in_the_gltf_frame() -> None:
    scene = scene_for_export(n=40, degree=3, seed=2)
    document, binary = read_glb_document(write_glb(scene))
    position = torch.from_numpy(accessor(document, binary, "POSITION").copy())
    assert torch.allclose(position, scene.means @ TURN.T, atol=1e-6)
    # Covariances turn with the frame: R S^2 R^T -> T R S^2 R^T T.
    xyzw = torch.from_numpy(accessor(document, binary, f"{EXTENSION}:ROTATION").copy())
    scale = torch.from_numpy(accessor(document, binary, f"{EXTENSION}:SCALE").copy())
    rotation = quat_to_matrix(xyzw[:, [3, 0, 1, 2]])
    ours = quat_to_matrix(torch.nn.functional.normalize(scene.quats, dim=1))
    cov = rotation @ torch.diag_embed(scale**2) @ rotation.transpose(1, 2)
    expected = TURN @ ours @ torch.diag_embed(scene.scales.exp() ** 2) @ ours.transpose(1, 2) @ TURN
    assert torch.allclose(cov, expected, atol=1e-5, rtol=1e-4)
    # A Gaussian seen along d in our frame shows the colour of the stored SH along T d.
    dirs = torch.nn.functional.normalize(torch.randn(32, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    stored = torch.stack([
        torch.from_numpy(accessor(document, binary, f"{EXTENSION}:SH_DEGREE_{ell}_COEF_{m}").copy())
        for ell in range(4) for m in range(2 * ell + 1)
    ], dim=1)  # fmt: skip
    ours_sh = torch.cat([scene.sh_dc[:, None], scene.sh_rest], dim=1)
    for i in range(3):
        seen = eval_sh(ours_sh[i][None].expand(32, -1, -1), dirs)
        assert torch.allclose(eval_sh(stored[i][None].expand(32, -1, -1), dirs @ TURN.T), seen, atol=1e-5)


def test_round_trip_and_choice_by_extension(tmp_path) -> None:  # noqa: ANN001
    scene = scene_for_export(n=200, degree=1)
    assert by_path(tmp_path / "a.GLB").name == "glb"
    export_scene(scene, tmp_path / "a.glb")
    back = import_scene(tmp_path / "a.glb")
    unit = torch.nn.functional.normalize(scene.quats, dim=1)
    assert torch.allclose(back.quats * torch.sign((back.quats * unit).sum(1, keepdim=True)), unit, atol=1e-6)
    assert torch.allclose(back.means, scene.means) and torch.allclose(back.scales, scene.scales, atol=1e-5)
    assert torch.allclose(back.opacities, scene.opacities, atol=1e-4)
    assert torch.equal(back.sh_dc, scene.sh_dc) and torch.equal(back.sh_rest, scene.sh_rest)


def test_pinned_bytes() -> None:
    """A format change is never silent: a small scene of exact values encodes to these bytes."""
    n = 4
    scene = GaussianScene(
        means=torch.arange(12, dtype=torch.float32).reshape(n, 3) - 5, quats=torch.eye(4)[[0, 1, 2, 3]],
        scales=torch.zeros(n, 3), opacities=torch.zeros(n), sh_dc=torch.ones(n, 3) * 0.5,
        sh_rest=torch.full((n, 3, 3), 0.25),
    )  # fmt: skip
    data = write_glb(scene)
    assert len(data) == 2404
    assert hashlib.sha256(data).hexdigest() == "8a1d462ec30099fefced4ff8d44fc4df82cc39716714f1bcf2aeebb2bdefde32"


def test_reader_refuses_broken_files() -> None:
    data = write_glb(scene_for_export(n=20, degree=0))
    document, binary = read_glb_document(data)

    def rebuild(doc: dict, blob: bytes = binary) -> bytes:
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        total = 12 + 8 + len(text) + 8 + len(blob)
        return struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(text), 0x4E4F534A) + text + (
            struct.pack("<II", len(blob), 0x004E4942) + blob
        )

    short = json.loads(json.dumps(document))
    short["accessors"][0]["count"] = 10**6
    plain = json.loads(json.dumps(document))
    del plain["meshes"][0]["primitives"][0]["extensions"]
    cases = [
        (b"glTF", "shorter"),
        (data[:-4], "length"),
        (rebuild(short), "holds"),
        (rebuild(plain), "carries"),
        (rebuild(document, binary[:64]), "reaches past"),
    ]
    for broken, message in cases:
        with pytest.raises(GlbError, match=message):
            read_glb(broken)
    with pytest.raises(ValueError, match="at least one"):
        write_glb(scene_for_export(n=0, degree=0))


def test_a_scale_beyond_float32_is_refused_not_written_as_infinity() -> None:
    scene = scene_for_export(n=20, degree=0)
    scales = scene.scales.clone()
    scales[3, 1] = 100.0  # finite as a log-scale, exp(100) is not a float32
    with pytest.raises(ValueError, match="SCALE overflows float32"):
        write_glb(scene.with_(scales=scales))


def test_a_zero_quaternion_is_written_as_the_identity() -> None:
    """The PLY reader's repair: a zero quaternion stands for no rotation. It was written as (0, 0, 0, 0), which the
    extension's unit rotations exclude and a viewer normalises to NaN."""
    scene = scene_for_export(n=20, degree=0)
    quats = scene.quats.clone()
    quats[4] = 0.0
    document, binary = read_glb_document(write_glb(scene.with_(quats=quats)))
    rotation = accessor(document, binary, f"{EXTENSION}:ROTATION")
    assert np.allclose(np.linalg.norm(rotation, axis=1), 1.0, atol=1e-6)
    back = read_glb(write_glb(scene.with_(quats=quats)))
    assert torch.allclose(back.quats[4].abs(), torch.tensor([1.0, 0.0, 0.0, 0.0]), atol=1e-6)
