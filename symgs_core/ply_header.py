"""The PLY header of a Gaussian scene: parsed and checked against the file's size before any data is read.

Standard library only, so the API process checks uploads with the very rules the worker's reader applies
(``ply.read_scene`` calls ``check_header`` first). A header is refused when it cannot describe a graphdeco scene
(required properties, f_rest numbering, float types) or a PlayCanvas compressed one (its elements, ranges and packed
types), or when its elements cannot fit in the file: every element's rows are counted at their smallest size (a list
may be empty), so a header claiming 1e12 faces before its vertices is refused without reading them; a binary file
without lists must be exactly as long as its header says. Header
lines end in LF or CRLF and may carry trailing whitespace (the magic line and end_header's too); comment and obj_info
lines may hold any bytes (exporters write names in UTF-8), every other line is ASCII.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

MAX_HEADER_BYTES = 1 << 20
GEOMETRY = ("x", "y", "z")
NORMALS = ("nx", "ny", "nz")
DC = ("f_dc_0", "f_dc_1", "f_dc_2")
SCALES = ("scale_0", "scale_1", "scale_2")
ROTATIONS = ("rot_0", "rot_1", "rot_2", "rot_3")
REQUIRED = GEOMETRY + DC + ("opacity",) + SCALES + ROTATIONS
SH_DEGREE_OF_REST = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest properties -> SH degree
# PlayCanvas compressed PLY (SuperSplat's and splat-transform's export): chunks of 256 Gaussians, each chunk's
# ranges in ``chunk`` (the colour ranges only in later writers), the Gaussians packed in four uint32, the higher SH
# as uchar in ``sh``.
CHUNK = 256
CHUNK_RANGES = tuple(f"{end}_{axis}" for end in ("min", "max") for axis in "xyz") + tuple(
    f"{end}_scale_{axis}" for end in ("min", "max") for axis in "xyz"
)
CHUNK_COLOURS = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")

# PLY scalar types: byte size and numpy kind.
TYPES = {
    "char": (1, "i"), "int8": (1, "i"), "uchar": (1, "u"), "uint8": (1, "u"),
    "short": (2, "i"), "int16": (2, "i"), "ushort": (2, "u"), "uint16": (2, "u"),
    "int": (4, "i"), "int32": (4, "i"), "uint": (4, "u"), "uint32": (4, "u"),
    "float": (4, "f"), "float32": (4, "f"), "double": (8, "f"), "float64": (8, "f"),
}  # fmt: skip
FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
# The end_header line: a whole line (a comment may mention it), ended by LF or CRLF, or cut off by the end of the file.
_END_HEADER = re.compile(rb"^[^\S\n]*end_header[^\S\n]*(?:\n|\Z)", re.MULTILINE)


class PlyError(ValueError):
    """A PLY file that cannot be read as a Gaussian scene; ``code`` says why in a machine-readable word.

    Codes: not_ply, unsupported_format, malformed, missing_property, bad_sh_count, truncated, trailing_data,
    non_finite, out_of_range, too_many_gaussians, empty_scene.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)
        self.code, self.message = code, message

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class Element:
    name: str
    count: int
    properties: tuple[tuple[str, str, str | None], ...]  # (name, value type, list length type or None)

    @property
    def has_lists(self) -> bool:
        return any(length is not None for _, _, length in self.properties)

    def min_row_bytes(self, ascii: bool) -> int:
        """The fewest bytes a row can take: exact for binary rows without lists (a list may be empty)."""
        if ascii:
            return 2 * len(self.properties)  # every value takes at least one character and one separator
        return sum(TYPES[length or value][0] for _, value, length in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """A checked Gaussian-scene header. ``size``: bytes up to and including the end_header line. ``layout``:
    "graphdeco" (float properties by name) or "compressed" (PlayCanvas' packed chunks, ``CHUNK_RANGES``)."""

    format: str
    elements: tuple[Element, ...]
    comments: tuple[str, ...]
    size: int
    vertex: Element
    rest: tuple[str, ...]  # f_rest_0 .. f_rest_{3K-1}
    layout: str = "graphdeco"

    @property
    def count(self) -> int:
        return self.vertex.count

    @property
    def sh_degree(self) -> int:
        return SH_DEGREE_OF_REST[len(self.rest)]

    @property
    def properties(self) -> list[str]:
        return [p[0] for p in self.vertex.properties]

    @property
    def used(self) -> set[str]:
        return set(PACKED if self.layout == "compressed" else REQUIRED) | set(self.rest)


# Splat formats an upload may come in by mistake, by their first bytes: named in the refusal, so a user knows why.
_OTHER_FORMATS = (
    (b"NGSP", "an uncompressed .spz"), (b"\x1f\x8b", "a gzip file (a .spz)"), (b"PK\x03\x04", "a zip archive (a .sog)"),
    (b"glTF", "glTF binary (a .glb)"),
)  # fmt: skip


def _header_lines(head: bytes, name: str) -> tuple[list[bytes], int]:
    """The lines between the magic line and the end_header line, and the offset of the body (just past the newline
    that ends the end_header line). Lines end in LF or CRLF; trailing whitespace is allowed on every line."""
    first = head.split(b"\n", 1)[0]
    if first.rstrip() != b"ply":
        if first.startswith(b"ply\r"):  # classic Mac line ends: the whole header is one line to this reader
            raise PlyError(
                "unsupported_format", f"{name}: the header's lines end in a bare CR; only LF and CRLF are read"
            )
        known = next((what for magic, what in _OTHER_FORMATS if head.startswith(magic)), None)
        hint = f"; it looks like {known}: scenes come in as graphdeco .ply" if known else ""
        raise PlyError("not_ply", f"{name}: not a PLY file (its first line is not 'ply'){hint}")
    end = _END_HEADER.search(head, len(first))
    if end is None:
        raise PlyError("not_ply", f"{name}: no 'end_header' line in the first {MAX_HEADER_BYTES} bytes")
    if not end.group().endswith(b"\n"):
        raise PlyError("truncated", f"{name}: the file ends inside its header")
    return head[len(first) + 1 : end.start()].split(b"\n"), end.end()


def _parse(head: bytes, name: str) -> tuple[str, list[Element], list[str], int]:
    lines, size = _header_lines(head, name)
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []
    comments: list[str] = []
    for number, line in enumerate(lines, start=2):
        keyword = line.split(None, 1)[:1]
        if keyword in ([], [b"obj_info"]):
            continue
        if keyword == [b"comment"]:  # free text: exporters write their names and dates in UTF-8
            comments.append(line.strip()[len("comment") :].strip().decode("utf-8", errors="replace"))
            continue
        try:
            raw = line.decode("ascii")
        except UnicodeDecodeError:
            raise PlyError("malformed", f"{name}: header line {number} is not ASCII text") from None
        words = raw.split()
        bad = PlyError("malformed", f"{name}: header line {number} is malformed: {raw.strip()[:80]!r}")
        if words[0] == "format":
            if len(words) != 3:
                raise bad
            fmt = words[1]
            if fmt not in FORMATS:
                raise PlyError("unsupported_format", f"{name}: unknown PLY format {fmt[:40]!r}")
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad
            if any(e[0] == words[1] for e in elements):  # which would hold the Gaussians? plyfile refuses it too
                raise PlyError("malformed", f"{name}: element {words[1][:40]!r} appears twice")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise bad
            prop: tuple[str, str, str | None]
            if len(words) == 3 and words[1] in TYPES:
                prop = (words[2], words[1], None)
            elif len(words) == 5 and words[1] == "list" and words[2] in TYPES and words[3] in TYPES:
                prop = (words[4], words[3], words[2])
            else:
                raise bad
            if any(p[0] == prop[0] for p in elements[-1][2]):
                raise PlyError("malformed", f"{name}: property {prop[0][:40]!r} appears twice")
            elements[-1][2].append(prop)
        else:
            raise bad
    if fmt is None:
        raise PlyError("malformed", f"{name}: the header has no 'format' line")
    return fmt, [Element(n, c, tuple(p)) for n, c, p in elements], comments, size


def _rest_names(names: list[str], name: str) -> tuple[str, ...]:
    rest = [n for n in names if n.startswith("f_rest_")]
    expected = [f"f_rest_{i}" for i in range(len(rest))]
    given, wanted = set(rest), set(expected)
    if given != wanted:  # a gap or a stray name: the count alone would name a degree the file may well have
        missing = [n for n in expected if n not in given]
        stray = [n[:40] for n in rest if n not in wanted]
        raise PlyError(
            "bad_sh_count",
            f"{name}: the {len(rest)} f_rest properties are not numbered 0..{len(rest) - 1}: "
            f"{', '.join(missing[:3])} missing, {', '.join(stray[:3])} in their place",
        )
    if len(rest) not in SH_DEGREE_OF_REST:
        raise PlyError(
            "bad_sh_count",
            f"{name}: {len(rest)} f_rest properties match no SH degree (expected 0, 9, 24 or 45)",
        )
    return tuple(expected)


def _check_size(fmt: str, elements: list[Element], vertex: Element, body: int, name: str) -> None:
    ascii = fmt == "ascii"
    needed = sum(e.count * e.min_row_bytes(ascii) for e in elements)
    if needed > body:
        others = "" if elements == [vertex] else " and its other elements"
        raise PlyError(
            "truncated",
            f"{name}: the header claims {vertex.count} Gaussians{others}, at least {needed} bytes of data, "
            f"but the file holds {body} bytes after the header",
        )
    if not ascii and not any(e.has_lists for e in elements) and body > needed:
        raise PlyError(
            "trailing_data",
            f"{name}: the header describes {needed} bytes of data but the file holds {body}: "
            f"it declares {vertex.count} Gaussians, fewer than the file carries",
        )


def _compressed(fmt: str, elements: list[Element], comments: list[str], size: int, file_size: int, name: str,
                max_gaussians: int | None) -> PlyHeader:  # fmt: skip
    """The header of a PlayCanvas compressed PLY: elements ``chunk``, ``vertex`` and optionally ``sh``, each property
    by name with its type, one chunk per 256 Gaussians, the file exactly as long as they are."""
    what = f"{name}: a PlayCanvas compressed PLY"
    if fmt != "binary_little_endian":
        raise PlyError("unsupported_format", f"{what} in {fmt}; its writers use binary_little_endian")
    by_name = {e.name: e for e in elements}
    if set(by_name) - {"chunk", "vertex", "sh"} or "chunk" not in by_name:
        raise PlyError("unsupported_format", f"{what} has elements {', '.join(e.name[:40] for e in elements)}; "
                       "expected chunk, vertex and optionally sh")  # fmt: skip
    kinds = {"chunk": "f", "vertex": "u", "sh": "u"}
    widths = {"chunk": 4, "vertex": 4, "sh": 1}
    for e in elements:
        for prop, value, length in e.properties:
            if length is not None or TYPES[value] != (widths[e.name], kinds[e.name]):
                raise PlyError("unsupported_format", f"{what}: {e.name} property {prop[:40]!r} is {value}")
    chunk, vertex = by_name["chunk"], by_name["vertex"]
    ranges = {p[0] for p in chunk.properties}
    if ranges not in (set(CHUNK_RANGES), set(CHUNK_RANGES + CHUNK_COLOURS)) or len(ranges) != len(chunk.properties):
        raise PlyError("missing_property", f"{what}: chunk properties {sorted(ranges)[:20]} are not its ranges")
    if {p[0] for p in vertex.properties} != set(PACKED) or len(vertex.properties) != len(PACKED):
        raise PlyError("missing_property", f"{what}: vertex properties are not {', '.join(PACKED)}")
    rest: tuple[str, ...] = ()
    if "sh" in by_name:
        sh = by_name["sh"]
        rest = _rest_names([p[0] for p in sh.properties], name)
        if len(rest) != len(sh.properties) or sh.count != vertex.count:
            raise PlyError("malformed", f"{what}: sh holds {sh.count} rows of {len(sh.properties)} values for "
                           f"{vertex.count} Gaussians")  # fmt: skip
    if chunk.count != -(-vertex.count // CHUNK):
        raise PlyError("malformed", f"{what}: {chunk.count} chunks for {vertex.count} Gaussians (one per {CHUNK})")
    if max_gaussians is not None and vertex.count > max_gaussians:
        raise PlyError("too_many_gaussians", f"{name}: {vertex.count} Gaussians exceed the limit of {max_gaussians}")
    _check_size(fmt, elements, vertex, file_size - size, name)
    return PlyHeader(fmt, tuple(elements), tuple(comments), size, vertex, rest, "compressed")


def check_header(
    head: bytes, file_size: int, *, name: str = "scene.ply", max_gaussians: int | None = None
) -> PlyHeader:
    """Parse ``head`` (the first bytes of a file of ``file_size`` bytes) as a Gaussian-scene PLY header, graphdeco or
    PlayCanvas compressed; PlyError names what is wrong."""
    fmt, elements, comments, size = _parse(head[:MAX_HEADER_BYTES], name)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        raise PlyError("missing_property", f"{name}: no 'vertex' element")
    names = [p[0] for p in vertex.properties]
    missing = [p for p in REQUIRED if p not in names]
    if missing and "packed_position" in names:  # what SuperSplat and splat-transform write
        return _compressed(fmt, elements, comments, size, file_size, name, max_gaussians)
    if missing:
        raise PlyError("missing_property", f"{name}: missing required properties {', '.join(missing)}")
    rest = _rest_names(names, name)
    used = set(REQUIRED) | set(rest)
    for prop, value, length in vertex.properties:
        if prop in used and (length is not None or TYPES[value][1] != "f"):
            kind = "a list" if length is not None else value
            raise PlyError("unsupported_format", f"{name}: property {prop!r} is {kind}, expected float")
    if max_gaussians is not None and vertex.count > max_gaussians:
        raise PlyError("too_many_gaussians", f"{name}: {vertex.count} Gaussians exceed the limit of {max_gaussians}")
    _check_size(fmt, elements, vertex, file_size - size, name)
    return PlyHeader(fmt, tuple(elements), tuple(comments), size, vertex, rest)


def read_header(
    path: str | os.PathLike[str], *, max_gaussians: int | None = None, name: str | None = None
) -> PlyHeader:
    """``check_header`` of the file at ``path``; messages call it ``name`` (default: the file's name)."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(MAX_HEADER_BYTES)
    return check_header(head, path.stat().st_size, name=name or path.name, max_gaussians=max_gaussians)
