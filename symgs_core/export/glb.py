"""glTF binary (`.glb`) with ``KHR_gaussian_splatting``: writer and reader.

One mesh of one ``POINTS`` primitive whose attributes are float32 accessors, one buffer view each, in the GLB's
binary chunk: ``POSITION``, ``KHR_gaussian_splatting:ROTATION`` (unit quaternion x, y, z, w), ``:SCALE`` (linear
standard deviations, exp of our log-scales), ``:OPACITY`` (sigmoid of our logits), ``:SH_DEGREE_0_COEF_0`` and
``:SH_DEGREE_l_COEF_m`` for l = 1..degree, m = 0..2l (RGB each, the 3DGS real SH basis); plus ``COLOR_0`` (the
DC colour as linear RGB, opacity as alpha, unsigned bytes) for viewers that only draw points. The extension's
``kernel`` is ``ellipse`` and its ``colorSpace`` ``srgb_rec709_display`` (colours as 3DGS trains them).

Axes: glTF is y-up; splat glTF files are written LUF (x left, y up, z forward), as PlayCanvas' ``splat-transform``
writes them and as Niantic's ``spz`` documents GLB's frame: our RDF scene turned 180 degrees about z, so x and y
change sign, the rotation is composed with that turn, and the SH coefficients odd in (x, y) change sign.
``asset.extras`` records the frame.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np
import torch

from ..ply import OPACITY_LOGIT_MAX, OPACITY_LOGIT_MIN
from ..scene import SH_REST_COUNT, GaussianScene

EXTENSION = "KHR_gaussian_splatting"
MAGIC = 0x46546C67  # "glTF"
JSON_CHUNK = 0x4E4F534A
BIN_CHUNK = 0x004E4942
FLOAT, UNSIGNED_BYTE = 5126, 5121
ARRAY_BUFFER = 34962
POINTS = 0
C0 = 0.28209479177387814
# Sign of each SH rest coefficient (basis index 1..15) under the turn about z: x -> -x, y -> -y. Odd indices are
# odd in (x, y) together: y, x; yz, xz; y(3x^2 - y^2), y(4z^2 - ...), x(4z^2 - ...), x(x^2 - 3y^2).
SH_TURN = np.array([-1.0 if i % 2 else 1.0 for i in range(1, 16)])
AXES = "LUF: x left, y up, z forward (the PLY's RDF turned 180 degrees about z)"
_HEADER = struct.Struct("<III")
_CHUNK = struct.Struct("<II")
_MAX_JSON = 1 << 24


class GlbError(ValueError):
    """A file that is not a readable glTF binary with one Gaussian splat primitive."""


def _turn_quats(wxyz: np.ndarray) -> np.ndarray:
    """(0, 0, 0, 1) (x) q: each rotation composed with the 180-degree turn about z, as (w, x, y, z). Turning twice
    gives -q, the same rotation: the turn is its own inverse."""
    w, x, y, z = wxyz.T
    return np.stack([-z, -y, x, w], axis=1)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _sh_names(degree: int) -> list[str]:
    return [f"{EXTENSION}:SH_DEGREE_{ell}_COEF_{m}" for ell in range(1, degree + 1) for m in range(2 * ell + 1)]


def write_glb(scene: GaussianScene) -> bytes:
    """The `.glb` bytes of ``scene`` (in its order)."""
    n = len(scene)
    if n == 0:
        raise ValueError("a glTF splat primitive needs at least one Gaussian")
    t = {k: v.detach().cpu().double().numpy() for k, v in scene.tensors().items()}
    if not all(np.isfinite(v).all() for v in t.values()):
        raise ValueError("a glTF file stores finite attributes only")
    turn = np.array([-1.0, -1.0, 1.0])
    norm = np.linalg.norm(t["quats"], axis=1, keepdims=True)
    # A zero quaternion is the identity, as the PLY reader repairs it: the extension asks for unit rotations.
    unit = np.where(norm < 1e-12, np.array([1.0, 0.0, 0.0, 0.0]), t["quats"] / np.maximum(norm, 1e-12))
    q = _turn_quats(unit)
    with np.errstate(over="ignore"):  # exp of a huge logit or log-scale is inf: an opacity of 0, a scale refused below
        opacity = 1.0 / (1.0 + np.exp(-t["opacities"]))
        scale = np.exp(t["scales"])
    k = scene.sh_rest.shape[1]
    rest = t["sh_rest"] * SH_TURN[:k, None]
    colour = np.clip(t["sh_dc"] * C0 + 0.5, 0.0, 1.0)
    fallback = np.round(np.concatenate([_srgb_to_linear(colour), opacity[:, None]], axis=1) * 255.0)
    attributes: list[tuple[str, np.ndarray, str]] = [
        ("POSITION", t["means"] * turn, "VEC3"),
        ("COLOR_0", fallback.astype(np.uint8), "VEC4"),
        (f"{EXTENSION}:ROTATION", q[:, [1, 2, 3, 0]], "VEC4"),
        (f"{EXTENSION}:SCALE", scale, "VEC3"),
        (f"{EXTENSION}:OPACITY", opacity, "SCALAR"),
        (f"{EXTENSION}:SH_DEGREE_0_COEF_0", t["sh_dc"], "VEC3"),
    ]
    attributes += [(name, rest[:, i], "VEC3") for i, name in enumerate(_sh_names(scene.sh_degree))]

    blob, views, accessors, semantic = bytearray(), [], [], {}
    for index, (name, values, kind) in enumerate(attributes):
        with np.errstate(over="ignore"):
            raw = values.astype(np.uint8 if values.dtype == np.uint8 else "<f4")
        if not np.isfinite(raw).all():  # exp of a huge log-scale: finite in float64, not in the file's float32
            raise ValueError(f"a glTF file stores finite attributes only: {name} overflows float32")
        data = raw.tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": ARRAY_BUFFER})
        accessor = {
            "bufferView": index, "componentType": UNSIGNED_BYTE if raw.dtype == np.uint8 else FLOAT, "count": n,
            "type": kind,
        }  # fmt: skip
        if name == "POSITION":  # glTF requires the bounds of positions, as the stored float32 values
            accessor["min"] = raw.min(axis=0).astype(np.float64).tolist()
            accessor["max"] = raw.max(axis=0).astype(np.float64).tolist()
        if raw.dtype == np.uint8:
            accessor["normalized"] = True
        accessors.append(accessor)
        semantic[name] = index
        blob += data + bytes(-len(data) % 4)
    gltf = {
        "asset": {"version": "2.0", "generator": "SymGS", "extras": {"axes": AXES}},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": semantic, "mode": POINTS,
            "extensions": {EXTENSION: {
                "kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
                "sortingMethod": "cameraDistance",
            }},
        }]}],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }  # fmt: skip
    text = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = _HEADER.size + 2 * _CHUNK.size + len(text) + len(blob)
    return b"".join([
        _HEADER.pack(MAGIC, 2, total), _CHUNK.pack(len(text), JSON_CHUNK), text,
        _CHUNK.pack(len(blob), BIN_CHUNK), bytes(blob),
    ])  # fmt: skip


def read_glb_document(data: bytes) -> tuple[dict, bytes]:
    """The JSON document and binary chunk of a GLB; GlbError unless the container is well formed."""
    if len(data) < _HEADER.size + _CHUNK.size:
        raise GlbError(f"glb: {len(data)} bytes, shorter than a header")
    magic, version, total = _HEADER.unpack_from(data)
    if magic != MAGIC or version != 2 or total != len(data):
        raise GlbError(f"glb: magic {magic:#x}, version {version}, length {total} for {len(data)} bytes")
    length, kind = _CHUNK.unpack_from(data, _HEADER.size)
    start = _HEADER.size + _CHUNK.size
    if kind != JSON_CHUNK or length > min(len(data) - start, _MAX_JSON):
        raise GlbError("glb: the first chunk is not a JSON chunk that fits the file")
    try:
        document = json.loads(data[start : start + length])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GlbError(f"glb: the JSON chunk does not parse ({exc})") from exc
    pos = start + length
    binary = b""
    if pos + _CHUNK.size <= len(data):
        length, kind = _CHUNK.unpack_from(data, pos)
        if kind != BIN_CHUNK or pos + _CHUNK.size + length > len(data):
            raise GlbError("glb: the second chunk is not a binary chunk that fits the file")
        binary = data[pos + _CHUNK.size : pos + _CHUNK.size + length]
    if not isinstance(document, dict):
        raise GlbError("glb: the JSON chunk is not an object")
    return document, binary


_COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
_DTYPES: dict[int, np.dtype] = {FLOAT: np.dtype("<f4"), UNSIGNED_BYTE: np.dtype("u1")}


def _accessor(document: dict, binary: bytes, index: object, count: int) -> np.ndarray:
    """The values [count, components] of accessor ``index`` (tightly packed float or byte data in the BIN chunk)."""
    try:
        accessor = document["accessors"][index]
        view = document["bufferViews"][accessor["bufferView"]]
        dtype = _DTYPES[accessor["componentType"]]
        width = _COMPONENTS[accessor["type"]]
        offset = int(view.get("byteOffset", 0)) + int(accessor.get("byteOffset", 0))
    except (KeyError, IndexError, TypeError) as exc:
        raise GlbError(f"glb: accessor {index!r} is not a float or byte accessor of a buffer view") from exc
    if view.get("buffer", 0) != 0 or view.get("byteStride", dtype.itemsize * width) != dtype.itemsize * width:
        raise GlbError(f"glb: accessor {index!r} is not tightly packed in the binary chunk")
    if accessor.get("count") != count:
        raise GlbError(f"glb: accessor {index!r} holds {accessor.get('count')} values, POSITION {count}")
    size = count * width * dtype.itemsize
    if offset < 0 or offset + size > len(binary) or size > int(view.get("byteLength", 0)):
        raise GlbError(f"glb: accessor {index!r} reaches past its buffer view or the binary chunk")
    values = np.frombuffer(binary, dtype=dtype, count=count * width, offset=offset).reshape(count, width)
    if dtype == np.uint8 and accessor.get("normalized"):
        return values / 255.0
    return values.astype(np.float64)


def read_glb(data: bytes) -> GaussianScene:
    """The Gaussians of the first ``KHR_gaussian_splatting`` primitive of a GLB, back in our RDF axes."""
    document, binary = read_glb_document(data)
    try:
        primitive = next(
            p for mesh in document.get("meshes", []) for p in mesh.get("primitives", [])
            if EXTENSION in p.get("extensions", {})
        )  # fmt: skip
    except (StopIteration, AttributeError, TypeError) as exc:
        raise GlbError(f"glb: no mesh primitive carries {EXTENSION}") from exc
    semantic = primitive.get("attributes", {})
    try:
        count = document["accessors"][semantic["POSITION"]]["count"]
    except (KeyError, IndexError, TypeError) as exc:
        raise GlbError("glb: the splat primitive has no POSITION accessor") from exc
    if not isinstance(count, int) or count < 1:
        raise GlbError(f"glb: POSITION holds {count!r} values")

    def attribute(name: str) -> np.ndarray:
        if name not in semantic:
            raise GlbError(f"glb: the splat primitive has no {name} attribute")
        return _accessor(document, binary, semantic[name], count)

    degree = 0
    while degree < 3 and f"{EXTENSION}:SH_DEGREE_{degree + 1}_COEF_0" in semantic:
        degree += 1
    k = SH_REST_COUNT[degree]
    rest = np.stack([attribute(name) for name in _sh_names(degree)], axis=1) if k else np.zeros((count, 0, 3))
    turn = np.array([-1.0, -1.0, 1.0])
    xyzw = attribute(f"{EXTENSION}:ROTATION")
    scale = attribute(f"{EXTENSION}:SCALE")[:, :3]
    opacity = np.clip(attribute(f"{EXTENSION}:OPACITY")[:, 0], 1e-6, 1 - 1e-6)
    if (scale < 0).any():
        raise GlbError("glb: negative scales")

    def f32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    with np.errstate(divide="ignore"):
        return GaussianScene(
            means=f32(attribute("POSITION") * turn),
            quats=f32(-_turn_quats(xyzw[:, [3, 0, 1, 2]])),
            scales=f32(np.log(np.maximum(scale, 1e-30))),
            opacities=f32(np.clip(np.log(opacity / (1 - opacity)), OPACITY_LOGIT_MIN, OPACITY_LOGIT_MAX)),
            sh_dc=f32(attribute(f"{EXTENSION}:SH_DEGREE_0_COEF_0")),
            sh_rest=f32(rest * SH_TURN[:k, None]),
        )


def load_glb(path: str | os.PathLike[str]) -> GaussianScene:
    """``read_glb`` of the file at ``path``."""
    return read_glb(Path(path).read_bytes())
