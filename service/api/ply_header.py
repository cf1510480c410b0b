"""Check an uploaded PLY's header before accepting a job: numpy only, no scene is loaded (the worker does that).

Codes match ``symgs_core.ply.PlyError``: not_ply, unsupported_format, malformed, missing_property, bad_sh_count,
truncated, too_many_gaussians, plus empty_scene.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .errors import ApiError

MAX_HEADER_BYTES = 1 << 16
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")  # fmt: skip
_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip
_FLOATS = {"float", "float32", "double", "float64"}
_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest properties -> SH degree


@dataclass(frozen=True)
class PlyHeader:
    format: str
    gaussians: int
    sh_degree: int
    properties: tuple[str, ...]


def _invalid(code: str, message: str) -> ApiError:
    return ApiError(413 if code == "too_many_gaussians" else 422, code, message)


def check_ply(path: str | os.PathLike[str], *, max_gaussians: int, name: str = "scene.ply") -> PlyHeader:
    """Parse the header, check the Gaussian properties and that the file is large enough to hold the vertices the
    header claims. Raises ApiError (422, or 413 for too many Gaussians)."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(MAX_HEADER_BYTES)
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise _invalid("not_ply", f"{name}: not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    newline = head.find(b"\n", end) if end >= 0 else -1
    if newline < 0:
        raise _invalid("not_ply", f"{name}: no complete 'end_header' line in the first {MAX_HEADER_BYTES} bytes")
    try:
        lines = head[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise _invalid("malformed", f"{name}: the header is not ASCII text") from None

    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []  # name, count, [(property, type or None)]
    for number, raw in enumerate(lines, start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        bad = _invalid("malformed", f"{name}: header line {number} is malformed: {raw.strip()[:80]!r}")
        if words[0] == "format":
            if len(words) != 3:
                raise bad
            fmt = words[1]
            if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise _invalid("unsupported_format", f"{name}: unknown PLY format {fmt[:40]!r}")
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if len(words) == 3 and words[1] in _SIZES:
                elements[-1][2].append((words[2], words[1]))
            elif len(words) == 5 and words[1] == "list" and words[2] in _SIZES and words[3] in _SIZES:
                elements[-1][2].append((words[4], None))
            else:
                raise bad
        else:
            raise bad
    if fmt is None:
        raise _invalid("malformed", f"{name}: the header has no 'format' line")
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None:
        raise _invalid("missing_property", f"{name}: no 'vertex' element")
    _, count, properties = vertex
    names = [p for p, _ in properties]
    if len(set(names)) != len(names):
        raise _invalid("malformed", f"{name}: a vertex property appears twice")
    missing = [p for p in REQUIRED if p not in names]
    if missing:
        raise _invalid("missing_property", f"{name}: missing required properties {', '.join(missing)}")
    rest = sorted((p for p in names if p.startswith("f_rest_")), key=lambda p: (len(p), p))
    if rest != [f"f_rest_{i}" for i in range(len(rest))] or len(rest) not in _REST_COUNTS:
        raise _invalid(
            "bad_sh_count",
            f"{name}: {len(rest)} f_rest properties match no SH degree (expected 0, 9, 24 or 45, numbered from 0)",
        )
    used = set(REQUIRED) | set(rest)
    for prop, kind in properties:
        if prop in used and kind not in _FLOATS:
            raise _invalid("unsupported_format", f"{name}: property {prop!r} is {kind or 'a list'}, expected float")
    if count == 0:
        raise _invalid("empty_scene", f"{name}: the scene has no Gaussians")
    if count > max_gaussians:
        raise _invalid("too_many_gaussians", f"{name}: {count} Gaussians exceed the limit of {max_gaussians}")
    _check_size(fmt, elements, vertex, path.stat().st_size - (newline + 1), name)
    return PlyHeader(fmt, count, _REST_COUNTS[len(rest)], tuple(names))


def _check_size(fmt: str, elements: list, vertex: tuple, body: int, name: str) -> None:
    """Refuse a header that claims more vertices than the file holds."""
    if fmt == "ascii":
        needed = vertex[1] * len(vertex[2]) * 2  # at least one character and one separator per value
    else:
        needed = 0
        for element in elements:
            if any(kind is None for _, kind in element[2]):
                break  # variable-length rows: only what precedes them can be checked
            needed += element[1] * sum(_SIZES[kind] for _, kind in element[2])
            if element is vertex:
                break
    if needed > body:
        raise _invalid(
            "truncated",
            f"{name}: the header claims {vertex[1]} Gaussians ({needed} bytes of data) but the file holds {body} bytes",
        )
