"""Encoding and decoding of a whole `.symgs` archive: the stored set, the mirror planes, the level bits, metadata.

Header (JSON object, format version 1; every key required, no others):
    count                   int, stored Gaussians N
    sh_degree               int, 0..3
    coordinate_convention   str, ``cameras.COORDINATE_CONVENTION``
    codec                   str, the archive codec that wrote the file (informational: sections name their own)
    planes                  [{"normal": [x, y, z], "offset": g}], level 0 first; unit normals, finite
    sections                [{"name", "codec", "offset", "length", "raw_length", "crc32", "params"}], exactly
                            ``SECTION_NAMES`` in that order (versions 1 and 2: without ``classes``); offsets count
                            from the end of the header; an attribute's entry may add "classes": false (version 6
                            on): its Gaussians all take the section's own step, whatever their class
    meta                    object, the caller's metadata, returned as given
Shapes follow from the header alone: attributes [N, ...] as in ``GaussianScene``, bits [N, len(planes)], classes [N].
The bits are decoded first, then the classes, then each attribute with the classes (``codec.classes``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..cameras import COORDINATE_CONVENTION
from ..mirror import Plane, expand_planes
from ..scene import SH_REST_COUNT, GaussianScene
from . import container
from .classes import MAX_CLASS, unwrapped
from .errors import ArchiveError
from .neighbours import Neighbours
from .registry import ATTRIBUTE_NAMES, SECTION_NAMES, ArchiveCodec, archive_codec, section_codec
from .section import MAX_MAGNITUDE, SectionCodec

_HEADER_KEYS = {"count", "sh_degree", "coordinate_convention", "codec", "planes", "sections", "meta"}
_SECTION_KEYS = {"name", "codec", "offset", "length", "raw_length", "crc32", "params"}
_MAX_NAME = 64


def physical_memory() -> int | None:
    """Bytes of memory this machine has; None where the system does not say."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


@dataclass(frozen=True)
class DecodeLimits:
    """What a reader accepts before it allocates anything; a file asking for more is refused: ``limit_exceeded``
    past a fixed limit or the memory budget, ``disproportionate`` for more Gaussians than a file of its size holds.

    A count in the header costs the writer nothing: a few kilobytes of constant sections can claim millions of
    Gaussians (zstd packs a megabyte of zeros into a few dozen bytes). Archives the pipeline writes spend 5 bytes a
    stored Gaussian or more (BENCHMARKS, "Decoding") and expand each one a few times, so the counts allowed grow with
    the file: ``per_byte`` Gaussians a byte, past the first ``floor``. What is left, the memory the decode and
    expansion would take (``decode_memory``), is checked against ``max_memory_bytes`` (this machine's memory by
    default) once the level bits, a small section, are read, before any attribute is decoded."""

    max_gaussians: int = 10_000_000  # stored
    max_expanded_gaussians: int = 40_000_000  # after expansion through every level
    max_levels: int = 32
    max_header_bytes: int = 1 << 20
    max_section_bytes: int = 1 << 31  # both stored and decoded size of one section
    stored_per_byte: float = 2.0
    expanded_per_byte: float = 8.0
    floor: int = 1 << 16  # Gaussians any archive may hold, stored and expanded, whatever its size
    max_memory_bytes: int | None = field(default_factory=physical_memory)  # None: no budget

    def proportional(self, per_byte: float, size: int) -> int:
        """The most Gaussians a file of ``size`` bytes may hold at ``per_byte`` a byte."""
        return self.floor + int(per_byte * size)


def decode_memory(stored: int, expanded: int, sh_degree: int, levels: int) -> int:
    """About the peak bytes of decoding an archive and expanding it (``expand_archive``): the stored attributes as
    float32, and the expanded scene three times over (each level's concatenation copies what it joins, and reflects
    a copy of the half it mirrors), with its bit rows and origin indices."""
    per_gaussian = 4 * (14 + 3 * SH_REST_COUNT[sh_degree])
    return stored * per_gaussian + 3 * expanded * (per_gaussian + 8 + levels)


@dataclass
class ArchiveContents:
    """Everything an archive holds. bits [|S|, L+1] bool, one column per plane (level 0 first); classes [|S|] int,
    each stored Gaussian's step class in 0..``MAX_CLASS`` (None: class 0 throughout)."""

    stored: GaussianScene
    planes: list[Plane]
    bits: Tensor
    meta: dict[str, Any] = field(default_factory=dict)
    classes: Tensor | None = None

    def __post_init__(self) -> None:
        expected = (len(self.stored), len(self.planes))
        if tuple(self.bits.shape) != expected or self.bits.dtype != torch.bool:
            raise ValueError(
                f"bits must be a bool tensor of shape {expected} (stored Gaussians, planes), "
                f"got {self.bits.dtype} of shape {tuple(self.bits.shape)}"
            )
        if not all(isinstance(p, Plane) for p in self.planes):
            raise ValueError(f"planes must be Plane objects, got {[type(p).__name__ for p in self.planes]}")
        if not isinstance(self.meta, dict):
            raise ValueError(f"meta must be a dict, got {type(self.meta).__name__}")
        classes = self.classes
        if classes is not None:
            n, kind = len(self.stored), classes.dtype
            if tuple(classes.shape) != (n,) or kind.is_floating_point or kind.is_complex or kind == torch.bool:
                raise ValueError(f"classes must be integers [{n}], got {kind} of shape {tuple(classes.shape)}")
            if n and not 0 <= int(classes.min()) <= int(classes.max()) <= MAX_CLASS:
                raise ValueError(f"classes must lie in 0..{MAX_CLASS}, got {int(classes.min())}..{int(classes.max())}")

    def permuted(self, perm: Tensor) -> ArchiveContents:
        """The same archive with the stored set, its bit rows and classes in the order ``perm`` [|S|] (see
        ``coding_order``)."""
        classes = None if self.classes is None else self.classes[perm.to(self.classes.device)]
        return ArchiveContents(self.stored.select(perm), list(self.planes), self.bits[perm], dict(self.meta), classes)


def _section_arrays(contents: ArchiveContents) -> dict[str, np.ndarray]:
    arrays = {k: v.detach().cpu().contiguous().numpy() for k, v in contents.stored.tensors().items()}
    arrays["bits"] = contents.bits.detach().cpu().contiguous().numpy()
    classes = contents.classes
    arrays["classes"] = np.zeros(len(contents.stored), np.uint8) if classes is None else classes.cpu().numpy().astype(
        np.uint8)
    return arrays


def _plain_json(meta: dict[str, Any]) -> None:
    """ValueError unless ``meta`` survives JSON unchanged (so decode gives back exactly what was encoded)."""
    try:
        again = json.loads(json.dumps(meta, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"meta must be plain JSON (finite numbers, str keys): {exc}") from exc
    if again != meta:
        raise ValueError("meta must be plain JSON: dict, list, str, int, float, bool, None (tuples become lists)")


def _in_range(values: np.ndarray) -> np.ndarray:
    """Where ``values`` are finite and within +-MAX_MAGNITUDE (what an archive may hold)."""
    return np.isfinite(values) & (np.abs(values) <= MAX_MAGNITUDE)


def encode_archive(contents: ArchiveContents, *, codec: str | ArchiveCodec = "lossless") -> bytes:
    """The `.symgs` bytes of ``contents``, each section written by ``codec`` (an ``ArchiveCodec``, or the name of
    one registered in ``registry``)."""
    writer = archive_codec(codec)
    codecs = writer.sections
    _plain_json(contents.meta)
    arrays = _section_arrays(contents)
    for name, values in arrays.items():
        if values.dtype != np.bool_ and not _in_range(values).all():
            raise ValueError(f"{name}: attributes must be finite and within +-{MAX_MAGNITUDE:g} to be archived")
    offsets = np.array([p.offset for p in contents.planes], dtype=np.float64)
    if not _in_range(offsets).all():
        raise ValueError(f"plane offsets must be within +-{MAX_MAGNITUDE:g}, got {offsets.tolist()}")
    table, payloads, offset = [], [], 0
    classes = arrays["classes"] if arrays["classes"].any() else None
    neighbours = None
    for name in SECTION_NAMES:
        coder, classed = unwrapped(codecs[name])
        own = classes if classed and name in ATTRIBUTE_NAMES else None
        coded = coder.encode(arrays[name], classes=own, neighbours=neighbours)
        if name == "means":  # what a reader finds its neighbours by: the positions as it decodes them
            shape = arrays[name].shape
            points = coder.decode(coded.payload, shape, coded.params, coded.raw_length, classes=own)
            neighbours = Neighbours(points, classes)
        entry = {
            "name": name,
            "codec": coder.name,
            "offset": offset,
            "length": len(coded.payload),
            "raw_length": coded.raw_length,
            "crc32": container.crc32(coded.payload),
            "params": coded.params,
        }
        table.append(entry if classed else entry | {"classes": False})
        payloads.append(coded.payload)
        offset += len(coded.payload)
    header = {
        "count": len(contents.stored),
        "sh_degree": contents.stored.sh_degree,
        "coordinate_convention": COORDINATE_CONVENTION,
        "codec": writer.name,
        "planes": [{"normal": list(p.normal), "offset": p.offset} for p in contents.planes],
        "sections": table,
        "meta": contents.meta,
    }
    data = container.frame(header, b"".join(payloads))
    header_bytes = len(container.header_text(header))
    if header_bytes > DecodeLimits().max_header_bytes:
        raise ValueError(f"archive header of {header_bytes} bytes exceeds what readers accept; shrink meta")
    return data


# ----------------------------------------------------------------------------------------------- validation


def _bad(message: str) -> ArchiveError:
    return ArchiveError("bad_header", message)


def _count(value: Any, what: str) -> int:
    """A non-negative JSON integer (bool is not one)."""
    if type(value) is not int or value < 0:
        raise _bad(f"{what} must be a non-negative integer, got {value!r:.80}")
    return value


def _number(value: Any, what: str) -> float:
    if type(value) not in (int, float) or not math.isfinite(value):
        raise _bad(f"{what} must be a finite number, got {value!r:.80}")
    return float(value)


def _name(value: Any, what: str) -> str:
    if type(value) is not str or not 0 < len(value) <= _MAX_NAME:
        raise _bad(f"{what} must be a string of 1..{_MAX_NAME} characters, got {value!r:.80}")
    return value


def _keys(obj: Any, keys: set[str], what: str) -> dict[str, Any]:
    if not isinstance(obj, dict) or set(obj) != keys:
        got = sorted(obj) if isinstance(obj, dict) else type(obj).__name__
        raise _bad(f"{what} must be an object with keys {sorted(keys)}, got {got}")
    return obj


def _planes(value: Any, limits: DecodeLimits) -> list[Plane]:
    if not isinstance(value, list):
        raise _bad(f"planes must be a list, got {type(value).__name__}")
    if len(value) > limits.max_levels:
        raise ArchiveError("limit_exceeded", f"{len(value)} levels exceed the limit of {limits.max_levels}")
    planes = []
    for i, item in enumerate(value):
        entry = _keys(item, {"normal", "offset"}, f"plane {i}")
        normal = entry["normal"]
        if not isinstance(normal, list) or len(normal) != 3:
            raise _bad(f"plane {i}: normal must be a list of 3 numbers, got {normal!r:.80}")
        n = tuple(_number(c, f"plane {i} normal") for c in normal)
        offset = _number(entry["offset"], f"plane {i} offset")
        if abs(offset) > MAX_MAGNITUDE:
            raise _bad(f"plane {i}: offset {offset:g} lies beyond +-{MAX_MAGNITUDE:g}")
        try:
            planes.append(Plane((n[0], n[1], n[2]), offset))
        except ValueError as exc:
            raise _bad(f"plane {i}: {exc}") from exc
    return planes


@dataclass(frozen=True)
class _Section:
    name: str
    codec: SectionCodec
    shape: tuple[int, ...]
    start: int  # absolute offset in the file
    length: int
    raw_length: int
    params: dict[str, Any]
    classed: bool = True  # whether its Gaussians take their step classes (``classes.OneStep``)


def _sections(value: Any, shapes: dict[str, tuple[int, ...]], limits: DecodeLimits, version: int) -> list[_Section]:
    names = list(SECTION_NAMES) if version >= 3 else [name for name in SECTION_NAMES if name != "classes"]
    if not isinstance(value, list) or [s.get("name") if isinstance(s, dict) else None for s in value] != names:
        raise _bad(f"sections must list exactly {names} in that order")
    sections = []
    for entry in value:
        name = entry["name"]
        _keys(entry, _SECTION_KEYS | ({"classes"} if "classes" in entry else set()), f"section {name!r}")
        classed = entry.get("classes", True)
        if "classes" in entry and (classed is not False or name not in ATTRIBUTE_NAMES or version < 6):
            raise _bad(f"section {name!r}: classes {classed!r:.20} (only false, on an attribute, from version 6)")
        offset = _count(entry["offset"], f"section {name!r} offset")
        length = _count(entry["length"], f"section {name!r} length")
        raw_length = _count(entry["raw_length"], f"section {name!r} raw_length")
        crc = _count(entry["crc32"], f"section {name!r} crc32")
        if crc > 0xFFFFFFFF:
            raise _bad(f"section {name!r} crc32 {crc} is not a 32-bit value")
        if max(length, raw_length) > limits.max_section_bytes:
            raise ArchiveError(
                "limit_exceeded",
                f"section {name!r}: {length} stored / {raw_length} decoded bytes exceed the limit of "
                f"{limits.max_section_bytes}",
            )
        if not isinstance(entry["params"], dict):
            raise _bad(f"section {name!r} params must be an object")
        if version < 5 and "predict" in entry["params"]:  # predictions from neighbours came with version 5
            raise _bad(f"section {name!r}: predicted symbols in an archive of format version {version}")
        codec = section_codec(_name(entry["codec"], f"section {name!r} codec"), name)
        codec.check(shapes[name], entry["params"], raw_length)
        sections.append(_Section(name, codec, shapes[name], offset, length, raw_length, entry["params"], classed))
    return sections


def _layout(sections: list[_Section], body_start: int, size: int) -> list[_Section]:
    """Sections must tile the body exactly: no gaps, no overlaps, nothing after the last, nothing past the end."""
    placed, expected = [], 0
    for s in sections:
        if s.start != expected:
            kind = "overlaps the previous section" if s.start < expected else "leaves a gap"
            raise _bad(f"section {s.name!r} at offset {s.start} {kind} (expected offset {expected})")
        expected += s.length
        placed.append(replace(s, start=body_start + s.start))
    if body_start + expected > size:
        raise ArchiveError("truncated", f"{size} bytes: the sections end at byte {body_start + expected}")
    if body_start + expected < size:
        raise ArchiveError("trailing_data", f"{size - body_start - expected} bytes after the last section")
    return placed


def _validate(data: bytes, limits: DecodeLimits) -> tuple[dict[str, Any], list[Plane], list[_Section]]:
    """Everything but the payloads' contents: prefix, header schema, limits, codecs, layout, checksums."""
    header, body_start, version = container.unframe(data, limits.max_header_bytes)
    _keys(header, _HEADER_KEYS, "header")
    n = _count(header["count"], "count")
    if n > limits.max_gaussians:
        raise ArchiveError("limit_exceeded", f"{n} stored Gaussians exceed the limit of {limits.max_gaussians}")
    if n > (most := limits.proportional(limits.stored_per_byte, len(data))):
        raise ArchiveError(
            "disproportionate", f"a file of {len(data)} bytes claims {n} stored Gaussians; it may hold at most {most}"
        )
    degree = _count(header["sh_degree"], "sh_degree")
    if degree not in SH_REST_COUNT:
        raise _bad(f"sh_degree must be 0..3, got {degree}")
    if header["coordinate_convention"] != COORDINATE_CONVENTION:
        got = header["coordinate_convention"]
        raise _bad(f"coordinate convention {got!r:.120}; this build reads {COORDINATE_CONVENTION!r}")
    _name(header["codec"], "codec")
    if not isinstance(header["meta"], dict):
        raise _bad(f"meta must be an object, got {type(header['meta']).__name__}")
    planes = _planes(header["planes"], limits)
    shapes = {
        "means": (n, 3),
        "quats": (n, 4),
        "scales": (n, 3),
        "opacities": (n,),
        "sh_dc": (n, 3),
        "sh_rest": (n, SH_REST_COUNT[degree], 3),
        "bits": (n, len(planes)),
        "classes": (n,),
    }
    sections = _layout(_sections(header["sections"], shapes, limits, version), body_start, len(data))
    crcs = {e["name"]: e["crc32"] for e in header["sections"]}
    view = memoryview(data)
    for s in sections:
        got = container.crc32(view[s.start : s.start + s.length])
        if got != crcs[s.name]:
            raise ArchiveError("bad_checksum", f"section {s.name!r}: CRC32 {got:08x}, header says {crcs[s.name]:08x}")
    return header, planes, sections


def read_header(data: bytes, *, limits: DecodeLimits = DecodeLimits()) -> dict[str, Any]:
    """The validated header of an archive (section sizes, planes, meta) without decoding any section."""
    return _validate(data, limits)[0]


def section_bytes(data: bytes, *, limits: DecodeLimits = DecodeLimits()) -> list[tuple[str, int]]:
    """Where a valid archive's bytes are, in its order: ``header`` (the framing and the header), then each section,
    those whose codec tells its parts (``parts``: the higher SH's index and bands) part by part. They add up to
    ``len(data)``; nothing is decoded."""
    _, _, sections = _validate(data, limits)
    out = [("header", sections[0].start if sections else len(data))]
    for s in sections:
        parts = getattr(s.codec, "parts", None)
        payload = bytes(memoryview(data)[s.start : s.start + s.length])
        out += list(parts(payload, s.params).items()) if parts is not None else [(s.name, s.length)]
    return out


def _decode_section(data: bytes, s: _Section, classes: np.ndarray | None = None,
                    neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
    payload = bytes(memoryview(data)[s.start : s.start + s.length])
    classes = classes if s.classed else None
    try:
        values = s.codec.decode(payload, s.shape, s.params, s.raw_length, classes=classes, neighbours=neighbours)
    except ArchiveError:
        raise
    except (ValueError, IndexError, OverflowError, TypeError) as exc:  # a codec tripped on hostile bytes
        raise ArchiveError("corrupt_section", f"section {s.name!r}: {exc}") from exc
    want = {"float32": np.float32, "bool": np.bool_, "uint8": np.uint8}[s.codec.kind]
    if values.shape != s.shape or values.dtype != want:
        raise ArchiveError(
            "corrupt_section",
            f"section {s.name!r} decoded to {values.dtype} {values.shape}, expected {np.dtype(want)} {s.shape}",
        )
    if want == np.float32:
        bad = values.size - int(np.count_nonzero(_in_range(values)))
        if bad:
            beyond = f"not finite or beyond +-{MAX_MAGNITUDE:g}"
            raise ArchiveError("corrupt_section", f"section {s.name!r} decodes to {bad} values {beyond}")
    return values


def expanded_count(bits: Tensor) -> int:
    """Gaussians after expansion: each stored Gaussian becomes 2^(its number of set bits)."""
    popcounts = torch.bincount(bits.sum(dim=1), minlength=1) if len(bits) else torch.zeros(1, dtype=torch.int64)
    return sum(int(c) << p for p, c in enumerate(popcounts.tolist()))


def _check_expansion(bits: Tensor, sh_degree: int, size: int, limits: DecodeLimits) -> None:
    """ArchiveError unless the Gaussians ``bits`` expand to, and the memory they would take, are within ``limits``
    for a file of ``size`` bytes."""
    total = expanded_count(bits)
    if total > limits.max_expanded_gaussians:
        limit = limits.max_expanded_gaussians
        raise ArchiveError("limit_exceeded", f"the levels expand to {total} Gaussians, over the limit of {limit}")
    if total > (most := limits.proportional(limits.expanded_per_byte, size)):
        raise ArchiveError(
            "disproportionate", f"a file of {size} bytes expands to {total} Gaussians; it may expand to at most {most}"
        )
    need = decode_memory(len(bits), total, sh_degree, bits.shape[1])
    if limits.max_memory_bytes is not None and need > limits.max_memory_bytes:
        raise ArchiveError(
            "limit_exceeded",
            f"decoding {len(bits)} Gaussians expanded to {total} would take about {need >> 20} MiB, over the memory "
            f"budget of {limits.max_memory_bytes >> 20} MiB",
        )


def decode_archive(data: bytes, *, limits: DecodeLimits = DecodeLimits()) -> ArchiveContents:
    """Inverse of ``encode_archive``; ArchiveError (with ``.code``) for any file that is not a valid archive.

    Everything the header says is validated, and every section's checksum verified, before any section is decoded;
    the level bits are decoded first, and what they expand to checked (``DecodeLimits``) before any attribute is; then
    the step classes (class 0 throughout in archives of versions 1 and 2, which hold none), which every attribute
    section reads.
    """
    header, planes, sections = _validate(data, limits)
    by_name = {s.name: s for s in sections}
    bits = torch.from_numpy(_decode_section(data, by_name["bits"]))
    _check_expansion(bits, header["sh_degree"], len(data), limits)
    classes = _decode_section(data, by_name["classes"]) if "classes" in by_name else None
    given = classes if classes is not None and classes.any() else None
    arrays = {"means": _decode_section(data, by_name["means"], given)}
    neighbours = Neighbours(arrays["means"], given)
    arrays |= {name: _decode_section(data, by_name[name], given, neighbours) for name in ATTRIBUTE_NAMES[1:]}
    stored = GaussianScene(**{k: torch.from_numpy(v) for k, v in arrays.items()})
    return ArchiveContents(stored, planes, bits, header["meta"], None if classes is None else torch.from_numpy(classes))


def expand_archive(contents: ArchiveContents) -> GaussianScene:
    """The full scene: the stored set expanded through every level (``hierarchy.expand``)."""
    return expand_planes(contents.stored, contents.planes, contents.bits)
