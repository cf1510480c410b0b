"""Attribute symbols predicted from neighbours decoded before them (``codec.neighbours``): the neighbours against a
brute-force oracle, residuals that restore exactly, sections that decode to the same values predicted or not and
code smaller where neighbours are alike, archives of earlier versions that still read, and hostile parameters."""

from __future__ import annotations

import base64
import hashlib
import json

import numpy as np
import pytest
import torch

from symgs_core.codec import ArchiveContents, ArchiveError, decode_archive, encode_archive, read_header
from symgs_core.codec.neighbours import MOST, WINDOW, Neighbours
from symgs_core.codec.quantize import MAX_LEVELS, OpacityCodec, ScalarGridCodec, ShDcCodec
from symgs_core.codec.steps import QuantSteps
from symgs_core.scene import GaussianScene


def _oracle(points: np.ndarray, classes: np.ndarray | None) -> np.ndarray:
    """Each row's nearest MOST among the WINDOW rows of its class before it, by (distance, rows between)."""
    classes = np.zeros(len(points), np.int64) if classes is None else classes
    out = np.full((len(points), MOST), -1)
    for c in np.unique(classes):
        rows = np.flatnonzero(classes == c)
        for i in range(len(rows)):
            before = rows[max(0, i - WINDOW) : i]
            d = ((points[before].astype(np.float64) - points[rows[i]].astype(np.float64)) ** 2).sum(axis=1)
            ranked = sorted(range(len(before)), key=lambda k: (d[k], -k))[:MOST]
            out[rows[i], : len(ranked)] = before[ranked]
    return out


@pytest.mark.parametrize("with_classes", [False, True])
def test_neighbours_are_the_nearest_before_in_each_class(with_classes: bool) -> None:
    rng = np.random.default_rng(1)
    points = rng.normal(size=(400, 3)).astype(np.float32)
    points[50:60] = points[40]  # equal distances: the one nearer in order wins
    classes = rng.integers(0, 3, 400).astype(np.uint8) if with_classes else None
    found = Neighbours(points, classes).index
    np.testing.assert_array_equal(found, _oracle(points, classes))
    assert (found < np.arange(400)[:, None]).all()  # only rows a reader has decoded


@pytest.mark.parametrize("count", [1, 2, MOST])
def test_residuals_restore_exactly(count: int) -> None:
    rng = np.random.default_rng(count)
    points = rng.uniform(size=(300, 3)).astype(np.float32)
    neighbours = Neighbours(points, rng.integers(0, 2, 300).astype(np.uint8))
    q = rng.integers(-1000, 1000, size=(300, 3))
    residuals = neighbours.residuals(q, count)
    np.testing.assert_array_equal(neighbours.restore(residuals, count, MAX_LEVELS, "test"), q)
    # the first row of each class has nothing before it: predicted 0
    assert (residuals[0] == q[0]).all()


def _smooth(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Two strands wound together, rows alternating between them as a space-filling order can leave them, and a
    field that varies slowly along each strand but differs between them: a row's nearest neighbour before it is
    two rows back, not the one before it (which the entropy coder's differences already use)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 1, n))
    strand = np.arange(n) % 2
    points = np.stack([np.cos(6 * t), np.sin(6 * t), t + 0.2 * strand], axis=1).astype(np.float32)
    field = np.where(strand[:, None] == 0, np.sin(10 * t)[:, None], 3.0 + np.cos(10 * t)[:, None]) * 0.5
    return points, (field + rng.normal(0, 0.02, (n, 3))).astype(np.float32)


@pytest.mark.parametrize(
    ("codec", "shape"),
    [(ScalarGridCodec(0.02), (3,)), (OpacityCodec(0.01), ()), (ShDcCodec(0.02), (3,))],
)
def test_a_predicted_section_decodes_to_the_same_values_in_fewer_bytes(codec, shape) -> None:  # noqa: ANN001
    points, field = _smooth(3000, seed=2)
    values = np.ascontiguousarray(field[:, : (shape[0] if shape else 1)].reshape(3000, *shape))
    classes = (np.arange(3000) * 2 // 3000).astype(np.uint8)  # two classes, in runs as the coding order leaves them
    neighbours = Neighbours(points, classes)
    plain = codec.encode(values, classes=classes)
    predicted = codec.encode(values, classes=classes, neighbours=neighbours)
    assert plain.params["predict"] == 0 and predicted.params["predict"] > 0
    assert len(predicted.payload) < 0.8 * len(plain.payload)
    codec.check(values.shape, predicted.params, predicted.raw_length)
    back = codec.decode(predicted.payload, values.shape, predicted.params, predicted.raw_length, classes=classes,
                        neighbours=neighbours)  # fmt: skip
    same = codec.decode(plain.payload, values.shape, plain.params, plain.raw_length, classes=classes)
    assert back.dtype == np.float32 and np.array_equal(back, same)


def test_values_unlike_their_neighbours_are_not_predicted() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(size=(2000, 3)).astype(np.float32)
    values = rng.normal(size=(2000, 3)).astype(np.float32)
    coded = ScalarGridCodec(0.05).encode(values, neighbours=Neighbours(points, None))
    assert coded.params["predict"] == 0


def _smooth_scene(n: int) -> GaussianScene:
    points, field = _smooth(n, seed=4)
    g = torch.Generator().manual_seed(4)
    return GaussianScene(
        means=torch.from_numpy(points),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.from_numpy(field) - 4.0,
        opacities=torch.from_numpy(field[:, 0]),
        sh_dc=torch.from_numpy(field),
        sh_rest=torch.zeros(n, 3, 3),
    )


def test_an_archive_predicts_from_the_positions_its_reader_decodes() -> None:
    scene = _smooth_scene(2000)
    extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
    name = QuantSteps().archive_codec(extent, "test-neighbours")
    classes = torch.arange(2000) * 3 // 2000
    contents = ArchiveContents(scene, [], torch.zeros(2000, 0, dtype=torch.bool), {}, classes)
    data = encode_archive(contents, codec=name)
    params = {s["name"]: s["params"] for s in read_header(data)["sections"]}
    assert params["scales"]["predict"] > 0
    decoded = decode_archive(data).stored
    codecs, given = QuantSteps().codecs(extent), classes.numpy().astype(np.uint8)
    for key, value in scene.tensors().items():  # each section as its codec decodes it without predictions
        array = value.numpy()
        coded = codecs[key].encode(array, classes=given)
        alone = codecs[key].decode(coded.payload, array.shape, coded.params, coded.raw_length, classes=given)
        assert np.array_equal(decoded.tensors()[key].numpy(), alone), key


# An archive of format version 4 (before predictions), as that version's writer wrote it: 40 generated Gaussians,
# SH degree 1, step classes 0..3, the default quantising codec.
GOLDEN_V4 = (
    "iVNZTUdTDQoEAAAAQQIAAKNV5XEotS/9YDgEvREARmFfHVBrHti2vd1BEzAwDhhlnpmZ9Co6Igco+CRmZkIIWgBVAFQAsnlorcyjZExzx5506eVK"
    "xrWF5JGgyrBL4khQPhiYmzQShCeDK3NzgybyUkdOxWZlaa5lJHExK31sx66WyZUuqp0DmmVllmvtbPSxKb0GugwOuJGv2Lkq7GxI0KEzx9BSC7Zv"
    "6h+q1RzAFORae+7pXb3mDaCUytiGOPLKp9FTqsH08FfspOadjfytAUPeRo6p2IdsqLRp5LEzxYWCtY+SwFVSp2PXhkyKGwkCsTGtAerbP3dOHp5G"
    "MpmZ8rGp/VPs3UF3KzHnAE1JDTL3y99b8B9bmGugjZyYuffu3/lyzlhTaTVXKdubpSKBIhGKG1mIXW2+1mnE0it3ntK7O8BjPzQ3D5EIJLbM1FEP"
    "+nLVXksJYiyb6Wm1B6F6asn4oSCwdBhCY4a9WWEdsgkIAI5fpbX+PT3/A86YXpplQ++1jWB7UHlaD9mCzSWm2PJvD9l7c5kKultvMbYCUqjRmOcU"
    "mpmZjLSkrQaAJiox3QHBmBEQQphodiuFYTPuAeK0JPoPF7r+6lmNzFbNpLs0khN2oELq7ZIo3QHPRF7etHz6WILGIIGN28N7/MPWCFUBVQ0dAQGY"
    "D+B8DwEqnDFe+CF+DxUmy6C5isJYaPSzIxscUxnraOlmUnFi9PlAJwAe9+9OGFhfubHaktLMgjZTZ+FG1ABjIEX7s/5sQWmuBDVy2g3wtQ5CzW5T"
    "ktX+EYR/mUGrcwAAAAH8KcbwAapKBGkotS/9IHgFAwCihhUhkE1zgomaQqcj40ymNfisvKxyM6q+QnB6xHVILTm5ATIFC9pXYE/mD7tD2YXmpAZF"
    "Joh2oJI0X0pLJgPeG8zWacMoG7QTjd01ArKl+mBcMb0o/KwVhwIAB1VewA5MAAAAAgAAwhsCRSi1L/0gPOEBAHUINW4bK4dDPQjANrVCyDazGOg3"
    "9mCFGss7GlYqkpwqRTRPVCwy+jXgQwAADVsCT8BSQUPGXFsvTim4M0sAAAACAAAAAkUotS/9IDzhAQBMDQAtuCWaNDoRiCXBFPcv1Q42D8dITx9o"
    "DicNbBoaNIIxJS9SAZInISrFGlgjNhE4GQAAECKILgwqHxxLAAAAAgAAAAJFKLUv/SA84QEARRUPFHUgTxUPB/QNBxLaD70HcBdcCgAAhRZGDCoL"
    "NASHEFcWxRYEDb8DFA2iFHUHAACwEDASLQnPC6ITNwAAAAIAAGsBMSi1L/0gKEEBADYFExc4U0kTNm4kIThGAEY4D19eNmYnQDdPJWo5ZyRkOR0Y"
    "EDlPa0E3AAAAAgAAMwExKLUv/SAoQQEAGxcjEhwJFgAcKysuGhgmCBoOFC8bAiYmHA4SEhspKikdBy4GHSUDCzcAAAACAAAZATEotS/9IChBAQAN"
    "FRMFDRQSCg0CBBgODgoPEAYFChAUDhgNFgQJDhkRDRAXDQ8PCwAMMQAAAAIBAAsNFii1L/0gDWkAAAIDAgQBBwUDBwIBAQIFkHKIWVdJ2N/N01gu"
    "MCmmMPZBzCotAAAAASYAMgEnKLUv/SAe8QAAEzMRGjYfDCkPCQAqADAUIkgZFEAaCBUFLj8AJUIJLQAAAAEkDhABJyi1L/0gHvEAAAkUAAkFGgsO"
    "CQAWFg8LEwQLGgIADgcHCg4KEwYQCi0AAAABCggKAScotS/9IB7xAAAFDgMIBgkJBw0JCgcGBAACCAkJAAICBAMACgoJCgEnAAAAAgEABgcQKLUv"
    "/SAHOQAAAgMHBgQHAQRLIr4xQ3NmhXfwJE4KAAAAFwAAAAEOARMotS/9IApRAAAADi0dYj8JWBQLFwAAAAEGARMotS/9IApRAAAyJRAHGisAMhQm"
    "FwAAAAEEARMotS/9IApRAAAACwYSERgZBBQOFwAAAAEEARMotS/9IApRAAACCgUBAQoACwgILgAAAAIAALEBAScotS/9IB7xAABIIk42PK51ZRdR"
    "TjIxbYBbSTErAC1EG0lTb3x/NjctAAAAAScpUwEnKLUv/SAe8QAABBVDKwMqEAwpHC8tFQAdHUAsAB4AKwUuKxw7FRRMLQAAAAEbHR8BJyi1L/0g"
    "HvEAAAsODgMOBgYKCxUACwUOAA0RDgsUBQAXDRYJFQ8SJi0AAAABCQ0VAScotS/9IB7xAAAECRkABA8ABAkGCQkHAAUDBwcFAxEMCAMJBQAMBRAV"
    "AAAAAQIBESi1L/0gKEUAABAAAAEAH4AFEAEAAFEAAAACAAAZAUsotS/9IFoVAgCihQ8LIKLdAas5NMzbB/T1vWhxggJP6pbmhh2SqC+zMlUhicj4"
    "7OickhBkp0dSHxKYvJhjOaZvOKjBjpc0XhWMAgBFAAAAAgAADQE/KLUv/SBatQEAooUMjxEjNEQ0QTEQLXmJZGt0wkhXwM57Sd+jV8qDx9oVeNqH"
    "wWKv0oYom30IyowdC6ieEggAPQAAAAIAAAcBNyi1L/0gWnUBAMIECIcRNDQxLoaQRMfVfIlmDk/xbDEWbJU50oZFYbmvo9UKAwCnIAFSYeerkAEt"
    "AAAAAgEAAwUOKLUv/SAFKQAAAhcyDgEGLftKwhl1vQjr7EwRNNooHKGa2g0BAAAAKLUv/SAAAQAAAAABAAEUKLUv/SAoXQAAGAAAAQIALVe8AAs="
)
GOLDEN_V4_DECODED = "5f5557900b4cd1a1844ae9d54ffea33d04958f2d382735d4f35a5c8f7030a73f"


def test_an_archive_written_before_predictions_still_decodes() -> None:
    data = base64.b64decode("".join(GOLDEN_V4))
    assert data[8] == 4
    stored = decode_archive(data).stored
    digest = hashlib.sha256(b"".join(v.numpy().tobytes() for v in stored.tensors().values())).hexdigest()
    assert digest == GOLDEN_V4_DECODED


@pytest.mark.parametrize("count", [MOST + 1, -1, 1.0, True, "1"])
def test_impossible_prediction_counts_are_refused_before_decoding(count: object) -> None:
    with pytest.raises(ArchiveError) as err:
        ScalarGridCodec(0.1).check((4, 3), {"origin": 0.0, "step": 0.1, "predict": count}, 48)
    assert err.value.code == "bad_header"


def test_a_predicted_section_without_positions_or_with_runaway_residuals_is_refused() -> None:
    points, field = _smooth(500, seed=5)
    neighbours = Neighbours(points, None)
    codec = ScalarGridCodec(0.02)
    coded = codec.encode(field, neighbours=neighbours)
    assert coded.params["predict"] > 0
    with pytest.raises(ArchiveError) as err:
        codec.decode(coded.payload, field.shape, coded.params, coded.raw_length)
    assert err.value.code == "bad_header"
    # Residuals of hostile bytes, each within the grid, whose chain of predictions walks past it.
    runaway = np.full((500, 3), MAX_LEVELS - 1)
    with pytest.raises(ArchiveError) as err:
        neighbours.restore(runaway, 1, MAX_LEVELS, "test")
    assert err.value.code == "corrupt_section"


def test_an_archive_of_an_earlier_version_may_not_hold_predictions() -> None:
    from tests.unit.test_archive_hostile import frame, split

    scene = _smooth_scene(500)
    extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
    contents = ArchiveContents(scene, [], torch.zeros(500, 0, dtype=torch.bool), {})
    data = encode_archive(contents, codec=QuantSteps().archive_codec(extent, "test-neighbours"))
    header, body = split(data)
    assert any(s["params"].get("predict") for s in header["sections"])
    with pytest.raises(ArchiveError) as err:
        decode_archive(frame(json.dumps(header, separators=(",", ":")).encode(), body, version=4))
    assert err.value.code == "bad_header"
