"""PLY reading and writing: layout, round trips, repairs and hostile files."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from symgs_core.export import save_scene
from symgs_core.ply import OPACITY_LOGIT_MAX, PlyError, graphdeco_properties, load_scene, read_scene
from symgs_core.scene import SH_REST_COUNT, GaussianScene
from tests.conftest import shared_file


def random_columns(n: int, degree: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random float32 values for every graphdeco property, keyed by property name."""
    rng = np.random.default_rng(seed)
    cols = {name: rng.normal(size=n).astype(np.float32) for name in graphdeco_properties(degree)}
    for name in ("nx", "ny", "nz"):
        cols[name] = np.zeros(n, dtype=np.float32)
    return cols


def write_ply(path: Path, cols: dict[str, np.ndarray], *, text: bool = False, byte_order: str = "<") -> Path:
    """A PLY with the properties of ``cols`` in the dict's order."""
    n = len(next(iter(cols.values())))
    swap = lambda code: code.replace("<", byte_order).replace(">", byte_order)
    dtype = [(name, swap(np.asarray(v).dtype.str)) for name, v in cols.items()]
    rows = np.empty(n, dtype=dtype)
    for name, v in cols.items():
        rows[name] = v
    PlyData([PlyElement.describe(rows, "vertex")], text=text, byte_order=byte_order).write(str(path))
    return path


def expected_scene(cols: dict[str, np.ndarray], degree: int) -> GaussianScene:
    """The scene ``cols`` describes, assembled independently of the reader (channel-major f_rest)."""
    k = SH_REST_COUNT[degree]
    stack = lambda names: torch.from_numpy(np.stack([cols[n] for n in names], axis=1).astype(np.float32))
    rest = torch.zeros(len(cols["x"]), k, 3)
    for c in range(3):
        for j in range(k):
            rest[:, j, c] = torch.from_numpy(cols[f"f_rest_{c * k + j}"].astype(np.float32))
    return GaussianScene(
        means=stack(["x", "y", "z"]),
        quats=stack([f"rot_{i}" for i in range(4)]),
        scales=stack([f"scale_{i}" for i in range(3)]),
        opacities=torch.from_numpy(cols["opacity"].astype(np.float32)),
        sh_dc=stack([f"f_dc_{i}" for i in range(3)]),
        sh_rest=rest,
    )


def assert_bit_equal(a: GaussianScene, b: GaussianScene) -> None:
    for name, ta in a.tensors().items():
        tb = b.tensors()[name]
        assert ta.shape == tb.shape, name
        assert ta.numpy().tobytes() == tb.contiguous().numpy().tobytes(), name


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_graphdeco_round_trip_is_byte_identical(tmp_path: Path, degree: int) -> None:
    cols = random_columns(57, degree, seed=degree)
    original = write_ply(tmp_path / "in.ply", cols)
    scene, report = read_scene(original)
    assert report.count == 57 and report.sh_degree == degree and report.repairs == {}
    assert report.properties == graphdeco_properties(degree)
    assert report.ignored == ["nx", "ny", "nz"]
    assert_bit_equal(scene, expected_scene(cols, degree))
    save_scene(scene, tmp_path / "out.ply")
    assert (tmp_path / "out.ply").read_bytes() == original.read_bytes()


def test_save_writes_graphdeco_order_and_channel_major_rest(tmp_path: Path) -> None:
    g = torch.Generator().manual_seed(1)
    n, k = 5, 8
    scene = GaussianScene(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.randn(n, 3, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, 3, generator=g),
        torch.randn(n, k, 3, generator=g),
    )
    save_scene(scene, tmp_path / "s.ply", comments=("made by a test",))
    ply = PlyData.read(str(tmp_path / "s.ply"))
    v = ply["vertex"]
    assert [p.name for p in v.properties] == graphdeco_properties(2)
    assert ply.comments == ["made by a test"]
    assert np.all(v["nx"] == 0) and np.all(v["nz"] == 0)
    # f_rest_{c*K + j} is coefficient j+1 of channel c
    assert np.array_equal(v["f_rest_9"], scene.sh_rest[:, 1, 1].numpy())
    assert np.array_equal(v["f_rest_23"], scene.sh_rest[:, 7, 2].numpy())
    assert np.array_equal(v["rot_0"], scene.quats[:, 0].numpy())


def test_any_property_order_extra_properties_and_doubles(tmp_path: Path) -> None:
    cols = random_columns(40, 1, seed=3)
    rng = np.random.default_rng(4)
    names = list(cols)
    rng.shuffle(names)
    shuffled = {name: cols[name] for name in names if name not in ("nx", "ny", "nz")}
    shuffled["red"] = rng.integers(0, 255, size=40).astype(np.uint8)
    shuffled["scale_1"] = shuffled["scale_1"].astype(np.float64)
    shuffled["confidence"] = rng.normal(size=40)
    scene, report = read_scene(write_ply(tmp_path / "odd.ply", shuffled))
    assert report.properties == list(shuffled)
    assert sorted(report.ignored) == ["confidence", "red"]
    assert_bit_equal(scene, expected_scene(cols, 1))


def test_ascii_and_big_endian_files_read_the_same(tmp_path: Path) -> None:
    cols = random_columns(12, 2, seed=5)
    reference = load_scene(write_ply(tmp_path / "le.ply", cols))
    assert_bit_equal(load_scene(write_ply(tmp_path / "be.ply", cols, byte_order=">")), reference)
    ascii_scene, report = read_scene(write_ply(tmp_path / "ascii.ply", cols, text=True))
    assert report.format == "ascii"
    assert_bit_equal(ascii_scene, reference)


def test_infinite_opacities_and_zero_quaternions_are_repaired_and_reported(tmp_path: Path) -> None:
    cols = random_columns(10, 0, seed=6)
    cols["opacity"][[1, 4, 7]] = [np.inf, np.inf, -np.inf]
    for i in range(4):
        cols[f"rot_{i}"][[2, 3]] = 0.0
    cols["rot_0"][5], cols["rot_1"][5], cols["rot_2"][5], cols["rot_3"][5] = 2.0, 0.5, 0.0, 0.0  # unnormalised: kept
    scene, report = read_scene(write_ply(tmp_path / "repair.ply", cols))
    assert report.repairs == {
        "opacity_pos_inf_clamped": 2,
        "opacity_neg_inf_clamped": 1,
        "zero_quaternion_set_to_identity": 2,
    }
    limit = math.log(511.0)
    assert scene.opacities[1].item() == pytest.approx(limit, abs=1e-6)
    assert torch.sigmoid(scene.opacities[1]).item() == pytest.approx(1 - 1 / 512, abs=1e-7)
    assert scene.opacities[7].item() == pytest.approx(-limit, abs=1e-6)
    assert scene.quats[2].tolist() == [1.0, 0.0, 0.0, 0.0] == scene.quats[3].tolist()
    assert scene.quats[5].tolist() == [2.0, 0.5, 0.0, 0.0]
    untouched = [0, 2, 3, 5, 6, 8, 9]
    assert torch.equal(scene.opacities[untouched], torch.from_numpy(cols["opacity"][untouched]))


@pytest.mark.parametrize("name", ["x", "f_dc_2", "f_rest_5", "scale_0", "rot_3", "opacity"])
def test_nan_is_refused_naming_the_property(tmp_path: Path, name: str) -> None:
    cols = random_columns(8, 1, seed=7)
    cols[name][3] = np.nan
    with pytest.raises(PlyError, match=name) as err:
        read_scene(write_ply(tmp_path / "nan.ply", cols))
    assert err.value.code == "non_finite"


@pytest.mark.parametrize("name", ["y", "scale_2", "f_rest_1"])
def test_infinity_outside_opacity_is_refused(tmp_path: Path, name: str) -> None:
    cols = random_columns(8, 1, seed=8)
    cols[name][0] = -np.inf
    with pytest.raises(PlyError, match=name) as err:
        read_scene(write_ply(tmp_path / "inf.ply", cols))
    assert err.value.code == "non_finite"


def test_missing_properties_are_named(tmp_path: Path) -> None:
    cols = random_columns(4, 0)
    del cols["opacity"], cols["rot_2"]
    with pytest.raises(PlyError, match="opacity, rot_2") as err:
        read_scene(write_ply(tmp_path / "missing.ply", cols))
    assert err.value.code == "missing_property"


@pytest.mark.parametrize(("count", "drop"), [(7, None), (24, "f_rest_3"), (12, None)])
def test_wrong_f_rest_counts_are_refused(tmp_path: Path, count: int, drop: str | None) -> None:
    cols = random_columns(4, 0)
    for i in range(count):
        cols[f"f_rest_{i}"] = np.zeros(4, dtype=np.float32)
    if drop:
        cols[f"f_rest_{count}"] = cols.pop(drop)  # 24 properties, but numbered with a gap
    with pytest.raises(PlyError) as err:
        read_scene(write_ply(tmp_path / "rest.ply", cols))
    assert err.value.code == "bad_sh_count"


def test_header_claiming_more_vertices_than_the_file_holds(tmp_path: Path) -> None:
    path = write_ply(tmp_path / "ok.ply", random_columns(100, 0))
    data = path.read_bytes()
    cut = tmp_path / "cut.ply"
    cut.write_bytes(data[:-1])
    with pytest.raises(PlyError, match="100 Gaussians") as err:
        read_scene(cut)
    assert err.value.code == "truncated"
    # A billion Gaussians claimed in a few bytes: refused from the header, nothing allocated.
    hostile = tmp_path / "hostile.ply"
    hostile.write_bytes(data.replace(b"element vertex 100", b"element vertex 1000000000"))
    with pytest.raises(PlyError) as err:
        read_scene(hostile)
    assert err.value.code == "truncated"
    # The vertices are all there, but a list element after them claims a billion rows.
    faces = tmp_path / "faces.ply"
    header_end = data.index(b"end_header")
    faces.write_bytes(
        data[:header_end] + b"element face 1000000000\nproperty list uchar int vertex_indices\n" + data[header_end:]
    )
    with pytest.raises(PlyError, match="other elements") as err:
        read_scene(faces)
    assert err.value.code == "truncated"


def test_header_claiming_fewer_vertices_than_the_file_holds(tmp_path: Path) -> None:
    """The rows the header leaves out would be dropped without a word: the file is refused instead."""
    data = write_ply(tmp_path / "ok.ply", random_columns(100, 0)).read_bytes()
    short = tmp_path / "short.ply"
    short.write_bytes(data.replace(b"element vertex 100", b"element vertex 60"))
    with pytest.raises(PlyError, match="fewer than the file carries") as err:
        read_scene(short)
    assert err.value.code == "trailing_data"


def test_ply_errors_keep_their_code_through_pickling() -> None:
    """Celery carries a worker's exception to the failure hook by pickling it: the code must survive."""
    again = pickle.loads(pickle.dumps(PlyError("non_finite", "s.ply: NaN in x")))
    assert (type(again), again.code, str(again)) == (PlyError, "non_finite", "s.ply: NaN in x")


def test_truncated_ascii_file(tmp_path: Path) -> None:
    path = write_ply(tmp_path / "a.ply", random_columns(50, 0), text=True)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(PlyError) as err:
        read_scene(path)
    assert err.value.code == "truncated"


def test_gaussian_limit_is_checked_from_the_header(tmp_path: Path) -> None:
    path = write_ply(tmp_path / "s.ply", random_columns(30, 0))
    assert len(read_scene(path, max_gaussians=30)[0]) == 30
    with pytest.raises(PlyError, match="30 Gaussians exceed the limit of 29") as err:
        read_scene(path, max_gaussians=29)
    assert err.value.code == "too_many_gaussians"


@pytest.mark.parametrize(
    ("content", "code"),
    [
        (b"", "not_ply"),
        (b"\x89PNG\r\n\x1a\n", "not_ply"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n", "not_ply"),
        (b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n", "unsupported_format"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n", "malformed"),
        (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int idx\nend_header\n", "missing_property"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quaternion q\nend_header\n", "malformed"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nelement vertex 0\nproperty float y\nend_header\n",
         "malformed"),  # two elements of one name: the header check refuses what plyfile would
    ],
)
def test_not_a_scene(tmp_path: Path, content: bytes, code: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(PlyError) as err:
        read_scene(path)
    assert err.value.code == code
    assert isinstance(err.value, ValueError)


def test_integer_typed_required_property_is_refused(tmp_path: Path) -> None:
    cols = random_columns(4, 0)
    cols["opacity"] = np.arange(4, dtype=np.int32)
    with pytest.raises(PlyError, match="'opacity' is int") as err:
        read_scene(write_ply(tmp_path / "int.ply", cols))
    assert err.value.code == "unsupported_format"


def test_empty_scene_round_trip(tmp_path: Path) -> None:
    save_scene(GaussianScene.empty(3), tmp_path / "e.ply")
    scene, report = read_scene(tmp_path / "e.ply")
    assert len(scene) == 0 and scene.sh_degree == 3 and report.count == 0


def test_fox_repairs_match_the_sanitised_copy() -> None:
    # fox.ply: no normals, non-graphdeco order, +inf opacities; the data's sanitised copy clamps them the same way.
    raw, report = read_scene(shared_file("fox_cc0_mujoco_warp/fox.ply"))
    sanitised = load_scene(shared_file("fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply"))
    assert report.repairs == {"opacity_pos_inf_clamped": 37}
    assert report.ignored == []
    assert_bit_equal(raw, sanitised)
    assert float(raw.opacities.max()) == pytest.approx(OPACITY_LOGIT_MAX)


@pytest.mark.parametrize(
    ("relative", "count", "degree"),
    [
        ("kacytran_try_iter7000/point_cloud.ply", 9080, 3),
        ("playbot_cc_by_sa3d/playbot_lod3_31k_sh2.ply", 31000, 2),
        ("donut_mipsplatting/donut_graphdeco_sh0.ply", 45624, 0),
        ("padilla_captures_cc_by/plant_113k_sh0.ply", 113648, 0),
    ],
)
def test_real_graphdeco_files_round_trip_byte_identical(tmp_path: Path, relative: str, count: int, degree: int) -> None:
    path = shared_file(relative)
    scene, report = read_scene(path)
    assert (report.count, report.sh_degree, report.repairs) == (count, degree, {})
    save_scene(scene, tmp_path / "out.ply", comments=tuple(report.comments))
    assert (tmp_path / "out.ply").read_bytes() == path.read_bytes()


def test_every_real_scene_loads(shared_data: Path) -> None:
    scenes = [p for p in sorted(shared_data.rglob("*.ply")) if p.name != "points3D.ply"]
    assert len(scenes) >= 9
    for path in scenes:
        scene = load_scene(path)
        assert len(scene) > 0 and bool(torch.isfinite(scene.opacities).all()), path.name
    # A COLMAP point cloud is a PLY but not a Gaussian scene.
    with pytest.raises(PlyError, match="f_dc_0") as err:
        read_scene(shared_data / "snowmiku_plush_capture_mit/sparse/0/points3D.ply")
    assert err.value.code == "missing_property"


def test_other_elements_are_ignored(tmp_path: Path) -> None:
    cols = random_columns(6, 0, seed=9)
    rows = np.empty(6, dtype=[(name, "<f4") for name in cols])
    for name, v in cols.items():
        rows[name] = v
    faces = np.array([([0, 1, 2],), ([3, 4, 5, 1],)], dtype=[("vertex_indices", "O")])
    elements = [PlyElement.describe(faces, "face"), PlyElement.describe(rows, "vertex")]
    PlyData(elements, text=False).write(str(tmp_path / "mesh.ply"))
    assert_bit_equal(load_scene(tmp_path / "mesh.ply"), expected_scene(cols, 0))


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_fixed_size_elements_around_the_vertices_are_skipped(tmp_path: Path, byte_order: str) -> None:
    cols = random_columns(7, 1, seed=10)
    names = list(cols)
    np.random.default_rng(11).shuffle(names)
    rows = np.empty(7, dtype=[(name, f"{byte_order}f4") for name in names])
    for name in names:
        rows[name] = cols[name]
    before = np.array([(1, 2.5, 3), (4, 5.5, 6)], dtype=[("a", "i4"), ("b", "f8"), ("c", "u1")])
    after = np.array([(7,)], dtype=[("d", "i2")])
    elements = [PlyElement.describe(before, "camera"), PlyElement.describe(rows, "vertex"),
                PlyElement.describe(after, "extra")]  # fmt: skip
    path = tmp_path / "around.ply"
    PlyData(elements, text=False, byte_order=byte_order).write(str(path))
    scene, report = read_scene(path)
    assert report.properties == names
    assert_bit_equal(scene, expected_scene(cols, 1))


def test_the_scene_owns_its_values(tmp_path: Path) -> None:
    cols = random_columns(50, 2, seed=12)
    path = write_ply(tmp_path / "s.ply", cols)
    scene = load_scene(path)
    path.write_bytes(path.read_bytes()[:-400] + b"\xff" * 400)  # the file changes under a reader that kept it mapped
    assert_bit_equal(scene, expected_scene(cols, 2))
    for name, tensor in scene.tensors().items():
        assert tensor.is_contiguous() and tensor.dtype == torch.float32, name


def test_ascii_header_claiming_fewer_vertices_than_the_file_holds(tmp_path: Path) -> None:
    """As for a binary file: the rows past the declared count would be dropped without a word. Blank space is not
    data."""
    data = write_ply(tmp_path / "ok.ply", random_columns(10, 0, seed=13), text=True).read_bytes()
    short = tmp_path / "short.ply"
    short.write_bytes(data.replace(b"element vertex 10", b"element vertex 7"))
    with pytest.raises(PlyError, match="declares 7 Gaussians, fewer than the file carries") as err:
        read_scene(short)
    assert err.value.code == "trailing_data"
    blank = tmp_path / "blank.ply"
    blank.write_bytes(data + b"\n \t\r\n\n")
    assert len(load_scene(blank)) == 10


@pytest.mark.parametrize(
    ("names", "value"),
    [
        (["scale_0", "scale_1", "scale_2"], 1e30),  # exp overflows float32
        (["scale_1"], -100.0),  # exp is zero in float32
        (["x"], 3e38),
        (["rot_2"], -1e30),
        (["f_dc_1"], 1e5),  # beyond the codec's colour grids at fine steps
        (["f_rest_4"], -1e30),
    ],
)
def test_finite_values_the_pipeline_cannot_carry_are_refused_naming_the_property(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], names: list[str], value: float
) -> None:
    """Refused as the file is read, with a code of its own, rather than deep in the codec with an archive error."""
    from service.cli import main

    cols = random_columns(300, 1, seed=14)
    for name in names:
        cols[name][:5] = value
    path = write_ply(tmp_path / "huge.ply", cols)
    with pytest.raises(PlyError, match=f"{names[-1]} \\(5 values beyond") as err:
        read_scene(path)
    assert err.value.code == "out_of_range"
    assert main(["compress", str(path), "-o", str(tmp_path / "huge.symgs"), "--quiet"]) == 2
    printed = capsys.readouterr().err
    assert f"symgs compress: error: out_of_range: huge.ply: values out of range in {names[0]} (5 values" in printed


def test_opacity_logits_whose_exp_overflows_are_clamped_as_infinities_are(tmp_path: Path) -> None:
    cols = random_columns(10, 0, seed=15)
    cols["opacity"][[1, 2, 3]] = [1e30, np.inf, -100.0]
    cols["opacity"][4] = 88.0  # the last logit kept as stored
    scene, report = read_scene(write_ply(tmp_path / "opacity.ply", cols))
    assert report.repairs == {"opacity_pos_inf_clamped": 2, "opacity_neg_inf_clamped": 1}
    assert scene.opacities[[1, 2, 3, 4]].tolist() == [OPACITY_LOGIT_MAX, OPACITY_LOGIT_MAX, -OPACITY_LOGIT_MAX, 88.0]


def test_a_gap_in_the_f_rest_numbering_is_named_not_miscounted(tmp_path: Path) -> None:
    """45 f_rest properties are degree 3's count: the message must say what is wrong with them, not the count."""
    cols = random_columns(4, 0)
    for i in [*range(44), 50]:
        cols[f"f_rest_{i}"] = np.zeros(4, dtype=np.float32)
    with pytest.raises(PlyError, match="not numbered 0..44: f_rest_44 missing, f_rest_50 in their place") as err:
        read_scene(write_ply(tmp_path / "gap.ply", cols))
    assert err.value.code == "bad_sh_count"
    assert "match no SH degree" not in str(err.value)


def _with_header(path: Path, magic: bytes, extra: list[bytes], end: bytes) -> Path:
    """``path`` with its magic and end_header lines replaced and ``extra`` lines after its format line."""
    data = path.read_bytes()
    size = data.index(b"\nend_header\n") + len(b"\nend_header\n")
    lines = data[:size].split(b"\n")[:-1]
    lines = [magic, lines[1], *extra, *lines[2:-1], end]
    path.write_bytes(b"".join(line + b"\n" for line in lines) + data[size:])
    return path


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize(
    ("magic", "extra", "end", "comments"),
    [
        (b"ply \r", [], b"end_header", []),  # trailing whitespace on the magic line, as on any other
        (b"ply", [], b"end_header \t\r", []),  # and on end_header's: the body starts past its newline
        (b"ply", [b"comment see end_header docs", b"obj_info end_header"], b"end_header", ["see end_header docs"]),
        (b"ply", [b"comment Cr\xc3\xa9\xc3\xa9 par \xe9", b"obj_info \xff"], b"end_header", ["Créé par \ufffd"]),
    ],
)
def test_lenient_header_lines_read_the_same_scene(
    tmp_path: Path, magic: bytes, extra: list[bytes], end: bytes, comments: list[str], text: bool
) -> None:
    """What the header check accepts, the body reader reads (plyfile, for ascii, is given a plain header)."""
    cols = random_columns(9, 1, seed=16)
    path = _with_header(write_ply(tmp_path / "s.ply", cols, text=text), magic, extra, end)
    scene, report = read_scene(path)
    assert_bit_equal(scene, expected_scene(cols, 1))
    assert (report.count, report.comments) == (9, comments)


@pytest.mark.parametrize(
    ("content", "code", "message"),
    [
        (b"ply\rformat ascii 1.0\rend_header\r", "unsupported_format", "bad.ply: the header's lines end in a bare CR"),
        (b"plyx\nformat ascii 1.0\nend_header\n", "not_ply", "bad.ply: not a PLY file (its first line is not 'ply')"),
        (b" ply\nformat ascii 1.0\nend_header\n", "not_ply", "bad.ply: not a PLY file (its first line is not 'ply')"),
        (b"ply\nformat ascii 1.0\ncomment end_header\n", "not_ply", "bad.ply: no 'end_header' line in the first"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nend_header ", "truncated", "bad.ply: the file ends inside its"),
        (b"ply\nformat ascii 1.0\nelement v\xc3\xa9rtex 0\nend_header\n", "malformed",
         "bad.ply: header line 3 is not ASCII text"),
    ],
)  # fmt: skip
def test_header_lines_refused_with_an_exact_message(tmp_path: Path, content: bytes, code: str, message: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(PlyError) as err:
        read_scene(path)
    assert (err.value.code, str(err.value)[: len(message)]) == (code, message)


def test_blank_lines_between_ascii_rows_are_passed_over(tmp_path: Path) -> None:
    cols = random_columns(6, 0, seed=17)
    data = write_ply(tmp_path / "a.ply", cols, text=True).read_bytes()
    size = data.index(b"end_header\n") + len(b"end_header\n")
    rows = data[size:].splitlines(keepends=True)
    blank = tmp_path / "blank.ply"
    blank.write_bytes(data[:size] + b"\n \t\r\n" + b"".join(rows[:2]) + b"\n\n" + b"".join(rows[2:]))
    scene, report = read_scene(blank)
    assert (report.count, report.repairs) == (6, {})
    assert_bit_equal(scene, expected_scene(cols, 0))
    # Blank lines are not rows: one row fewer is a file cut short, whatever blank space follows it.
    blank.write_bytes(data[:size] + b"\n".join(rows[:2]) + b"\n\n" + b"".join(rows[2:-1]) + b"\n\n")
    with pytest.raises(PlyError, match="row 5: early end-of-file") as err:
        read_scene(blank)
    assert err.value.code == "truncated"


def test_a_short_ascii_row_is_malformed_unless_it_ends_the_file(tmp_path: Path) -> None:
    data = write_ply(tmp_path / "a.ply", random_columns(6, 0, seed=18), text=True).read_bytes()
    size = data.index(b"end_header\n") + len(b"end_header\n")
    rows = data[size:].splitlines(keepends=True)
    short = tmp_path / "short.ply"
    short.write_bytes(data[:size] + b"".join(rows[:3]) + rows[3].rsplit(b" ", 1)[0] + b"\n" + b"".join(rows[4:]))
    with pytest.raises(PlyError, match="row 3: property 'rot_3': early end-of-line") as err:
        read_scene(short)
    assert err.value.code == "malformed"
    short.write_bytes(data[:size] + b"".join(rows[:5]) + rows[5].rsplit(b" ", 1)[0] + b"\n\n")
    with pytest.raises(PlyError, match="row 5: property 'rot_3': early end-of-line") as err:
        read_scene(short)
    assert err.value.code == "truncated"


def test_ascii_rows_of_an_element_without_properties_stay_blank_lines(tmp_path: Path) -> None:
    """Such an element's rows are empty lines: they are rows there, not blank space to pass over."""
    cols = random_columns(3, 0, seed=19)
    data = write_ply(tmp_path / "a.ply", cols, text=True).read_bytes()
    path = tmp_path / "marks.ply"
    path.write_bytes(data.replace(b"element vertex", b"element mark 2\nelement vertex").replace(b"end_header\n",
                     b"end_header\n\n\n"))  # fmt: skip
    assert_bit_equal(load_scene(path), expected_scene(cols, 0))


def _georeferenced(n: int, offset: float, spread: float) -> dict[str, np.ndarray]:
    cols = random_columns(n, 0, seed=20)
    rng = np.random.default_rng(21)
    for axis in ("x", "y", "z"):
        cols[axis] = offset + spread * rng.uniform(-0.5, 0.5, size=n)
    return cols


@pytest.mark.parametrize("text", [False, True])
def test_float64_positions_that_lose_their_detail_in_float32_are_refused(tmp_path: Path, text: bool) -> None:
    """At 1e6 float32 keeps a step of 1/16: a 1 cm scene there would collapse to one point without a word."""
    cols = _georeferenced(500, 1e6, 0.01)
    path = write_ply(tmp_path / "utm.ply", cols, text=text)
    with pytest.raises(PlyError) as err:
        read_scene(path)
    moved = max(np.abs(cols[a] - cols[a].astype(np.float32)).max() for a in ("x", "y", "z"))
    spread = max(np.ptp(cols[a]) for a in ("x", "y", "z"))
    assert (err.value.code, str(err.value)) == (
        "out_of_range",
        f"utm.ply: float64 positions in x, y, z lose their detail in float32: at about 1e+06 with a spread of "
        f"{spread:.3g}, float32 moves them by up to {moved:.3g} (more than 0.0001 of the spread); move the scene "
        "near the origin",
    )


@pytest.mark.parametrize(
    ("offset", "spread"),
    [
        (0.0, 10.0),
        (1e3, 10.0),  # 100 spreads away: float32 moves them by 3e-5 at most, below 1e-4 of 10
        (500.0, 1.0),  # 500 spreads away: float32 moves them by 1.5e-5 at most, below 1e-4 of 1
        (1e6, 0.0),  # every Gaussian at one point: no detail to lose
    ],
)
def test_float64_positions_float32_keeps_are_read_as_float32(tmp_path: Path, offset: float, spread: float) -> None:
    cols = _georeferenced(500, offset, spread)
    scene, report = read_scene(write_ply(tmp_path / "near.ply", cols))
    assert report.repairs == {}
    assert_bit_equal(scene, expected_scene(cols, 0))  # each value cast to float32, to the nearest


def test_float64_positions_that_are_float32_values_are_kept_wherever_they_are(tmp_path: Path) -> None:
    cols = _georeferenced(500, 1e6, 0.01)
    for axis in ("x", "y", "z"):
        cols[axis] = cols[axis].astype(np.float32).astype(np.float64)  # a float32 scene written as doubles
    assert_bit_equal(load_scene(write_ply(tmp_path / "f32.ply", cols)), expected_scene(cols, 0))


def test_a_float64_scene_in_memory_is_checked_as_a_file_is() -> None:
    from symgs_core.ply import checked_scene

    scene = expected_scene(_georeferenced(50, 1e6, 0.01), 0)
    near = GaussianScene(**{**scene.tensors(), "means": torch.rand(50, 3, dtype=torch.float64) + 100.0})
    checked, repairs = checked_scene(near)
    assert repairs == {} and torch.equal(checked.means, near.means.float())
    far = GaussianScene(**{**scene.tensors(), "means": near.means - 100.0 + 1e6})
    with pytest.raises(PlyError, match="^scene: float64 positions in x, y, z lose their detail") as err:
        checked_scene(far)
    assert err.value.code == "out_of_range"


def test_save_scene_writes_ply_only_under_a_name_of_its_own(tmp_path: Path) -> None:
    from symgs_core.synthetic import synthetic_scene

    scene = synthetic_scene("global", n=40, seed=1).scene
    for name in ("x.spz", "x.compressed.ply", "x.sog", "x.glb", "meta.json"):
        with pytest.raises(ValueError, match="export_scene"):
            save_scene(scene, tmp_path / name)
        assert not (tmp_path / name).exists()
    for name in ("x.ply", "x.PLY", "x.part"):
        save_scene(scene, tmp_path / name)
        assert len(load_scene(tmp_path / name)) == len(scene)


def test_comments_round_trip_in_utf8_and_stay_one_line(tmp_path: Path) -> None:
    scene, path = GaussianScene.empty(3), tmp_path / "c.ply"
    save_scene(scene, path, comments=("Créé par un scanner", "plain"))
    _, report = read_scene(path)
    assert report.comments == ["Créé par un scanner", "plain"]
    with pytest.raises(ValueError, match="one line"):
        save_scene(scene, path, comments=("two\nelement face 9",))


@pytest.mark.parametrize("extension", [".spz", ".sog", ".glb"])
def test_an_upload_in_another_splat_format_is_named(tmp_path: Path, extension: str) -> None:
    from symgs_core.export import export_scene
    from symgs_core.synthetic import synthetic_scene

    path = tmp_path / f"s{extension}"
    export_scene(synthetic_scene("global", n=300, seed=1).scene, path)
    named = rf"it looks like .*\(a \{extension}\): scenes come in as graphdeco .ply"
    with pytest.raises(PlyError, match=named) as caught:
        load_scene(path)
    assert caught.value.code == "not_ply"
