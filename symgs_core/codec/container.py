"""The `.symgs` container: a fixed prefix, a JSON header, then the sections back to back.

    offset  size  field
    0       8     magic  b"\\x89SYMGS\\r\\n" (the high byte and CR LF expose 7-bit and newline-mangling transfers)
    8       4     format version, uint32 little-endian (FORMAT_VERSION)
    12      4     header length H in bytes, uint32 little-endian
    16      4     CRC32 of the header bytes, uint32 little-endian
    20      H     header: one zstd frame of a UTF-8 JSON object (schema in ``archive.py``); version 1 files hold
                  the JSON itself, and readers still read them
    20 + H  ...   section payloads, contiguous, in section-table order, ending exactly at the end of the file

Section offsets in the header count from the first byte after the header, so the header never depends on its own
length. The header is compressed since version 2: its JSON repeats keys per section, and zstd takes a 1.5 kB header
to about 0.7 kB, which is 0.2% of a 30,000-Gaussian archive. Version 3 adds a section, the stored Gaussians' step
classes (``classes``), which every quantising section reads. Version 4 adds a kind of entropy table (``entropy``:
every symbol of a table as one column), which older readers could not read. Version 5 lets a quantising section
code its symbols less their prediction from neighbours decoded before them (``neighbours``; params ``predict``).
Version 6 lets an attribute section put every Gaussian on its own step, whatever its class (``classes.OneStep``).
This module only frames and unframes;
it knows nothing of Gaussians.
"""

from __future__ import annotations

import json
import struct
import zlib
from typing import Any

import zstandard

from .errors import ArchiveError
from .section import zstd_compress, zstd_decompress_exact

MAGIC = b"\x89SYMGS\r\n"
FORMAT_VERSION = 6
# 1: the header is plain JSON; 2: a zstd frame of it; 3: and the step classes' section; 4: and flat entropy tables;
# 5: and symbols predicted from neighbours; 6: and attribute sections on one step whatever the classes
READ_VERSIONS = (1, 2, 3, 4, 5, 6)
_PREFIX = struct.Struct("<8sIII")
PREFIX_SIZE = _PREFIX.size  # 20


def crc32(data: bytes | memoryview) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


def header_text(header: dict[str, Any]) -> bytes:
    """The canonical JSON of ``header``, as ``frame`` compresses it (its length is what readers limit)."""
    return json.dumps(header, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode("ascii")


def frame(header: dict[str, Any], body: bytes) -> bytes:
    """prefix + compressed canonical JSON of ``header`` + ``body`` (the sections, laid out as the header says)."""
    packed = zstd_compress(header_text(header), 19)
    return _PREFIX.pack(MAGIC, FORMAT_VERSION, len(packed), crc32(packed)) + packed + body


def _inflate(packed: bytes, max_header_bytes: int) -> bytes:
    """The JSON of a version 2 header, whose zstd frame must declare a size within ``max_header_bytes``."""
    try:
        size = zstandard.frame_content_size(packed)
    except zstandard.ZstdError as exc:
        raise ArchiveError("bad_header", f"header is not a zstd frame ({exc})") from exc
    if size < 0:
        raise ArchiveError("bad_header", "header's zstd frame does not declare its size")
    if size > max_header_bytes:
        raise ArchiveError("limit_exceeded", f"header of {size} bytes exceeds the limit of {max_header_bytes}")
    try:
        return zstd_decompress_exact(packed, size, "header")
    except ArchiveError as exc:
        raise ArchiveError("bad_header", f"header does not inflate ({exc})") from exc


def _reject_constant(name: str) -> None:
    raise ArchiveError("bad_header", f"header contains the non-JSON number {name}")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        raise ArchiveError("bad_header", f"header object repeats a key among {keys[:8]}")
    return dict(pairs)


def unframe(data: bytes, max_header_bytes: int) -> tuple[dict[str, Any], int, int]:
    """Check magic, version, header size and CRC, and parse the header strictly.

    Returns the header object, the offset of the first section byte and the format version. Nothing is allocated
    beyond the header, whose size ``max_header_bytes`` bounds.
    """
    view = memoryview(data)
    if len(view) < len(MAGIC):
        if bytes(view) == MAGIC[: len(view)]:
            raise ArchiveError("truncated", f"{len(view)} bytes: the file ends inside the magic bytes")
        raise ArchiveError("bad_magic", "not a .symgs archive (too short for the magic bytes)")
    if bytes(view[: len(MAGIC)]) != MAGIC:
        raise ArchiveError("bad_magic", f"not a .symgs archive (starts with {bytes(view[:8])!r})")
    if len(view) < PREFIX_SIZE:
        raise ArchiveError("truncated", f"{len(view)} bytes: the file ends inside the {PREFIX_SIZE}-byte prefix")
    _, version, header_len, header_crc = _PREFIX.unpack_from(view)
    if version not in READ_VERSIONS:
        raise ArchiveError("unsupported_version", f"format version {version}; this build reads {READ_VERSIONS}")
    if header_len > max_header_bytes:
        raise ArchiveError("limit_exceeded", f"header of {header_len} bytes exceeds the limit of {max_header_bytes}")
    end = PREFIX_SIZE + header_len
    if len(view) < end:
        raise ArchiveError("truncated", f"{len(view)} bytes: the {header_len}-byte header needs {end}")
    text: memoryview | bytes = view[PREFIX_SIZE:end]
    if crc32(text) != header_crc:
        raise ArchiveError("bad_checksum", f"header CRC32 {crc32(text):08x}, prefix says {header_crc:08x}")
    if version >= 2:
        text = _inflate(bytes(text), max_header_bytes)
    try:
        header = json.loads(
            bytes(text).decode("utf-8"), parse_constant=_reject_constant, object_pairs_hook=_unique_keys
        )
    except ArchiveError:
        raise
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise ArchiveError("bad_header", f"header is not UTF-8 JSON ({exc})") from exc
    if not isinstance(header, dict):
        raise ArchiveError("bad_header", f"header is a JSON {type(header).__name__}, expected an object")
    return header, end, version
