"""What a section codec is, and the bounded zstandard framing the built-in codecs share.

A section codec turns one array (a Gaussian attribute, the level bit matrix, or the step classes) into a payload and
back. Its ``name`` is written into the archive's section table and is the only thing a reader looks up, so
``decode`` must depend on nothing but the payload, the shape the header implies, the codec's ``params`` (JSON,
written beside the section), ``raw_length`` and the stored Gaussians' step classes (``classes``: their own section,
decoded first). ``check`` runs for every section before any payload is touched: it rejects parameters and sizes that
cannot be right, so decoding never allocates more than the header, already bounded by the reader's limits,
announced.
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
import zstandard

from .errors import ArchiveError

if TYPE_CHECKING:
    from .neighbours import Neighbours

SectionKind = Literal["float32", "bool", "uint8"]
# Every attribute value an archive holds, and every plane offset, lies within +-MAX_MAGNITUDE: then float32 sums and
# products of a few of them stay finite (reflections through every level, grid origins plus steps), so a decoded
# scene is always finite. Writers refuse anything beyond, and readers refuse archives that decode beyond it.
MAX_MAGNITUDE = 1e30


@dataclass(frozen=True)
class EncodedSection:
    """A coded section: the bytes stored, the size of its decoded byte stream, and the codec's parameters."""

    payload: bytes
    raw_length: int
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Estimate:
    """What ``encode`` then ``decode`` would give, without writing the bytes: the payload's bits, estimated from the
    symbols' statistics (``entropy.table_bits``), and the decoded values [N, ...], exactly: ``rows`` themselves, or
    with ``index`` [N], value i decoding to ``rows[index[i]]`` (a palette: what its error needs is per entry)."""

    bits: float
    rows: np.ndarray
    index: np.ndarray | None = None

    @property
    def decoded(self) -> np.ndarray:
        return self.rows if self.index is None else self.rows[self.index]


class SectionCodec(Protocol):
    """One way to store a section. ``kind``: what ``decode`` returns (float32 values, a bool matrix, or uint8 classes).

    ``classes`` [N] uint8: each stored Gaussian's step class, its steps 2^class times the section's (``classes``);
    None: class 0 throughout. A codec that quantises nothing ignores them, and so does the classes' own codec.
    """

    @property
    def name(self) -> str: ...

    @property
    def kind(self) -> SectionKind: ...

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        """``values`` [N, ...] (float32 for attributes, bool for the bit matrix) -> payload; ValueError if unfit."""
        ...

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        """Raise ArchiveError("bad_header") unless ``params`` and ``raw_length`` can describe an array of ``shape``."""
        ...

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        """The array of ``shape``; ArchiveError("corrupt_section") when the payload disagrees. Runs after ``check``."""
        ...


class RateCodec(SectionCodec, Protocol):
    """A section codec whose rate can be had without coding: the quantisers a rate model walks (``pipeline.budget``)."""

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        """``values`` as ``encode`` takes them -> their estimated bits and what ``decode`` would return."""
        ...


@functools.cache
def coding_pool() -> ThreadPoolExecutor:
    """One thread per core for coding streams side by side: zstd and numpy release the GIL, and each stream's bytes
    are the same whichever thread wrote it."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return ThreadPoolExecutor(max_workers=cores, thread_name_prefix="coding")


# A forked child (a Celery pool process) inherits the pool without its threads, and would wait on it forever.
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=coding_pool.cache_clear)


def zstd_compress(raw: bytes | np.ndarray, level: int) -> bytes:
    """One zstd frame that records its content size (readers rely on it to bound the output). ``raw``: bytes, or a
    C-contiguous array, read in place (its native bytes), not copied."""
    compressor = zstandard.ZstdCompressor(level=level, write_content_size=True)
    return compressor.compress(raw if isinstance(raw, bytes) else raw.data)


def zstd_decompress_exact(payload: bytes, raw_length: int, what: str) -> bytes:
    """Decompress one zstd frame that must hold exactly ``raw_length`` bytes and nothing after it.

    The frame's declared content size is checked before decompression: zstandard allocates whatever the frame
    declares, whatever ``max_output_size`` says.
    """
    try:
        declared = zstandard.frame_content_size(payload)
    except zstandard.ZstdError as exc:
        raise ArchiveError("corrupt_section", f"{what}: not a zstd frame ({exc})") from exc
    if declared != raw_length:
        raise ArchiveError("corrupt_section", f"{what}: zstd frame declares {declared} bytes, header says {raw_length}")
    try:
        raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=raw_length, allow_extra_data=False)
    except zstandard.ZstdError as exc:
        raise ArchiveError("corrupt_section", f"{what}: zstd decoding failed ({exc})") from exc
    if len(raw) != raw_length:
        raise ArchiveError("corrupt_section", f"{what}: decoded {len(raw)} bytes, header says {raw_length}")
    return raw


def check_params(codec: str, params: dict[str, Any], allowed: dict[str, tuple[object, ...]]) -> None:
    """Exactly the keys of ``allowed``, each with one of its listed values; ArchiveError("bad_header") otherwise."""
    if set(params) != set(allowed):
        raise ArchiveError("bad_header", f"{codec}: parameters {sorted(params)}, expected {sorted(allowed)}")
    for key, values in allowed.items():
        value = params[key]
        # bool is an int in Python and 1 == True: compare types too so a parameter keeps its JSON type.
        if not any(type(value) is type(v) and value == v for v in values):
            raise ArchiveError("bad_header", f"{codec}: parameter {key}={value!r}, expected one of {list(values)}")


def join_parts(parts: list[bytes]) -> bytes:
    """One payload of several streams, each behind its u32 length (``split_parts`` reads it back)."""
    return b"".join(len(p).to_bytes(4, "little") + p for p in parts)


def split_parts(payload: bytes, count: int, codec: str) -> list[bytes]:
    """The ``count`` streams of a ``join_parts`` payload; ArchiveError unless they fill it exactly."""
    parts = split_all(payload, codec)
    if len(parts) != count:
        raise ArchiveError("corrupt_section", f"{codec}: {len(parts)} parts, expected {count}")
    return parts


def split_all(payload: bytes, codec: str) -> list[bytes]:
    """Every stream of a ``join_parts`` payload, however many; ArchiveError if the last one is cut short."""
    parts: list[bytes]
    parts, pos = [], 0
    while pos < len(payload):
        if pos + 4 > len(payload):
            raise ArchiveError("corrupt_section", f"{codec}: payload ends inside a part's length")
        length = int.from_bytes(payload[pos : pos + 4], "little")
        if pos + 4 + length > len(payload):
            raise ArchiveError("corrupt_section", f"{codec}: part {len(parts)} is cut short")
        parts.append(payload[pos + 4 : pos + 4 + length])
        pos += 4 + length
    return parts
