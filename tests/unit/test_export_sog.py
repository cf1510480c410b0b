"""PlayCanvas SOG (`.sog` bundle and `meta.json` folder): round trips within the format's precision, exact where
the codebooks and palette hold every distinct value, the documented layout, and refusal of broken files."""

from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pytest
import torch
from PIL import Image

from symgs_core import files
from symgs_core.export import SogError, export_scene, import_scene, read_sog, sog_files, sog_order, write_sog
from symgs_core.export.formats import by_path
from symgs_core.export.sog import CODEBOOK, fit_codebook, read_sog_files, save_sog_folder, texture_size
from symgs_core.scene import GaussianScene
from tests.unit.test_export import same_rotation, scene_for_export


def on_grids(n: int = 600, degree: int = 2, seed: int = 0) -> GaussianScene:
    """A scene whose scales and colours take at most 256 distinct values and whose higher SH has 40 distinct rows:
    SOG stores those exactly."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    grid = torch.linspace(-1.0, 1.0, 200)
    rows = grid[torch.randint(0, 200, (40, k, 3), generator=g)]
    return GaussianScene(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.linspace(-7.0, -1.0, 256)[torch.randint(0, 256, (n, 3), generator=g)],
        opacities=torch.randn(n, generator=g) * 2,
        sh_dc=torch.linspace(-2.0, 2.0, 256)[torch.randint(0, 256, (n, 3), generator=g)],
        sh_rest=rows[torch.randint(0, 40, (n,), generator=g)],
    )


def texels(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as image:
        return np.asarray(image.convert("RGBA"))


def test_round_trip_is_exact_where_the_codebooks_hold_every_value() -> None:
    scene = on_grids()
    back = read_sog(write_sog(scene))
    ref = scene.select(sog_order(scene))
    assert torch.equal(back.scales, ref.scales) and torch.equal(back.sh_dc, ref.sh_dc)
    assert torch.equal(back.sh_rest, ref.sh_rest)
    # 16 bits per axis on sign(x) ln(1 + |x|): a relative step of at most 2^-16 of the log range.
    log_range = torch.log1p(ref.means.abs()).max() * 2
    assert (back.means - ref.means).abs().max() <= (ref.means.abs().max() + 1) * log_range / 65535
    assert (torch.sigmoid(back.opacities) - torch.sigmoid(ref.opacities)).abs().max() <= 0.5 / 255 + 1e-6
    # Smallest three at 8 bits: each within 1/255 of the unit interval mapped to +-1/sqrt2.
    assert same_rotation(back.quats, ref.quats).min() >= math.cos(0.012)


def test_random_scene_round_trip_within_codebook_precision() -> None:
    scene = scene_for_export(n=3000, degree=1, seed=4)
    back = read_sog(write_sog(scene, sh_palette=4096))
    ref = scene.select(sog_order(scene))
    # 256 entries over a uniform spread of 4 (log-scales) and 4 (DC): about 4 / 256 apart.
    assert (back.scales - ref.scales).abs().max() <= 4.0 / 256
    assert (back.sh_dc - ref.sh_dc).abs().max() <= 4.0 / 256
    assert same_rotation(back.quats, ref.quats).min() >= math.cos(0.012)
    # 3000 rows into a palette of 4096: every distinct row kept, each value on a 256-entry codebook of [-0.8, 0.8].
    assert (back.sh_rest - ref.sh_rest).abs().max() <= 1.6 / 256


def test_codebook_keeps_the_sparse_tails() -> None:
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0, 1, 100_000), np.full(100, 9.0), np.full(100, -12.0)])
    book, labels = fit_codebook(values)
    assert book.shape == (CODEBOOK,) and book.dtype == np.float32 and (np.diff(book) >= 0).all()
    decoded = book[labels]
    assert np.abs(decoded[-200:] - values[-200:]).max() < 1e-3  # the 200 outliers keep entries of their own
    assert np.abs(decoded - values).mean() < 0.01
    exact_book, exact_labels = fit_codebook(np.array([3.0, -1.0, 3.0, 0.5]))
    assert exact_book[exact_labels].tolist() == [3.0, -1.0, 3.0, 0.5] and exact_book[-1] == 3.0


def test_layout_is_the_playcanvas_meta_and_webp_textures() -> None:
    scene = on_grids(n=500, degree=3)
    files = sog_files(scene)
    meta = json.loads(files["meta.json"])
    assert meta["version"] == 2 and meta["count"] == 500 and meta["asset"]["generator"] == "SymGS"
    assert meta["means"]["files"] == ["means_l.webp", "means_u.webp"] and len(meta["means"]["mins"]) == 3
    assert all(len(meta[key]["codebook"]) == 256 for key in ("scales", "sh0", "shN"))
    assert meta["shN"]["bands"] == 3 and meta["shN"]["count"] == 40
    assert list(files) == ["meta.json", "means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp",
                           "shN_centroids.webp", "shN_labels.webp"]  # fmt: skip
    width, height = texture_size(500)
    assert (width, height) == (24, 24)
    for name in ("means_l.webp", "quats.webp", "scales.webp", "sh0.webp", "shN_labels.webp"):
        assert files[name][:4] == b"RIFF" and files[name][8:16] == b"WEBPVP8L"  # lossless WebP
        assert texels(files[name]).shape == (height, width, 4)
    assert texels(files["shN_centroids.webp"]).shape == (1, 64 * 15, 4)  # 40 entries, 64 a row, 15 texels each
    quats = texels(files["quats.webp"]).reshape(-1, 4)[:500]
    assert set(np.unique(quats[:, 3])) <= {252, 253, 254, 255}
    # Opacity is sh0's alpha; transparent texels keep their colour indices (exact WebP).
    alpha = texels(files["sh0.webp"]).reshape(-1, 4)[:500, 3]
    ordered = scene.select(sog_order(scene))
    assert np.array_equal(alpha, np.round(torch.sigmoid(ordered.opacities).double().numpy() * 255))


def test_bundle_is_a_stored_zip_of_the_folder(tmp_path) -> None:  # noqa: ANN001
    scene = on_grids(n=300, degree=1)
    bundle = write_sog(scene)
    with zipfile.ZipFile(io.BytesIO(bundle)) as z:
        assert all(info.compress_type == zipfile.ZIP_STORED for info in z.infolist())
        inside = {info.filename: z.read(info) for info in z.infolist()}
    assert inside == sog_files(scene) and bundle == write_sog(scene)
    assert by_path(tmp_path / "x.SOG").name == "sog" and by_path(tmp_path / "out" / "meta.json").name == "sog"
    export_scene(scene, tmp_path / "folder" / "meta.json")
    assert {p.name for p in (tmp_path / "folder").iterdir()} == set(inside)
    export_scene(scene, tmp_path / "scene.sog")
    for path in (tmp_path / "folder" / "meta.json", tmp_path / "scene.sog"):
        assert torch.equal(import_scene(path).sh_rest, read_sog(bundle).sh_rest)


def test_degree_zero_has_no_sh_palette() -> None:
    scene = scene_for_export(n=50, degree=0)
    files = sog_files(scene)
    assert "shN" not in json.loads(files["meta.json"]) and "shN_labels.webp" not in files
    assert read_sog(write_sog(scene)).sh_degree == 0


def test_writer_refuses_what_sog_cannot_hold() -> None:
    with pytest.raises(ValueError, match="at least one"):
        write_sog(scene_for_export(n=0, degree=0))
    with pytest.raises(ValueError, match="sh_palette"):
        write_sog(scene_for_export(n=10, degree=1), sh_palette=1 << 17)
    bad = scene_for_export(n=10, degree=0)
    bad.means[3, 1] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        write_sog(bad)


def _broken(files: dict[str, bytes], **meta_changes) -> dict[str, bytes]:  # noqa: ANN003
    meta = json.loads(files["meta.json"])
    for key, value in meta_changes.items():
        section, _, field = key.partition("__")
        if field:
            meta[section][field] = value
        else:
            meta[section] = value
    return {**files, "meta.json": json.dumps(meta).encode()}


def test_readers_refuse_broken_files() -> None:
    files = sog_files(on_grids(n=100, degree=1))
    with pytest.raises(SogError, match="zip"):
        read_sog(b"PK\x03\x04 not really")
    with pytest.raises(SogError, match="meta.json is missing"):
        read_sog_files({k: v for k, v in files.items() if k != "meta.json"})
    cases = [
        (_broken(files, version=1), "version"),
        (_broken(files, count=10_000), "texels"),
        (_broken(files, count=-1), "count"),
        (_broken(files, scales__codebook=[0.0] * 10), "codebook"),
        (_broken(files, shN__count=3), "palette entry"),
        (_broken(files, shN__bands=2), "texels wide"),
        ({**files, "quats.webp": files["sh0.webp"]}, "alpha"),
        ({**files, "sh0.webp": b"RIFF....WEBPnope"}, "WebP"),
        ({k: v for k, v in files.items() if k != "scales.webp"}, "missing"),
        ({**files, "meta.json": b"{"}, "JSON"),
    ]
    for broken, message in cases:
        with pytest.raises(SogError, match=message):
            read_sog_files(broken)


def test_decompress_command_writes_the_sog_folder_and_bundle(tmp_path) -> None:  # noqa: ANN001
    from service.cli import main
    from symgs_core.codec import ArchiveContents, encode_archive

    scene = on_grids(n=300, degree=1)
    archive = tmp_path / "scene.symgs"
    archive.write_bytes(encode_archive(ArchiveContents(scene, [], torch.zeros(300, 0, dtype=torch.bool), {})))
    assert main(["decompress", str(archive), "-o", str(tmp_path / "web" / "meta.json")]) == 0
    assert main(["decompress", str(archive), "-o", str(tmp_path / "out.sog")]) == 0
    folder = import_scene(tmp_path / "web" / "meta.json")
    assert torch.equal(folder.sh_rest, read_sog((tmp_path / "out.sog").read_bytes()).sh_rest)
    assert len(folder) == 300 and (tmp_path / "web" / "quats.webp").is_file()


def test_a_folder_write_that_fails_leaves_the_previous_export_whole(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    """Writing over an unbundled SOG (the same export twice) with the disk filling up part way: the folder still
    holds the previous export, every file as it was, and no temporary file. ``meta.json`` used to be written first,
    in place: it then named the new scene's count over the old scene's images, which reads as a wrong scene."""
    meta = tmp_path / "web" / "meta.json"
    save_sog_folder(on_grids(n=300, degree=2, seed=1), meta)
    before = {p.name: p.read_bytes() for p in meta.parent.iterdir()}
    create, calls = files.create_exclusive, []

    def disk_fills(path: Path) -> BinaryIO:
        calls.append(path.name)
        if len(calls) == 3:  # the third file, created before the disk filled, takes no bytes
            create(path).close()
            raise OSError(28, "No space left on device", str(path))
        return create(path)

    monkeypatch.setattr(files, "create_exclusive", disk_fills)
    with pytest.raises(OSError, match="No space left"):
        save_sog_folder(on_grids(n=700, degree=1, seed=2), meta)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in meta.parent.iterdir()} == before
    save_sog_folder(on_grids(n=700, degree=1, seed=2), meta)  # the same write with room succeeds
    assert len(import_scene(meta)) == 700 and not list(meta.parent.glob(".*"))
