"""Coding of the level bit matrix [N, L+1] (bit l of Gaussian i: left at level l).

Each level's column is stored on its own, as whichever of two blocks zstandard packs smaller:
  mode 0, packed:  ceil(N/8) bytes, bit i of the column at bit 7 - i%8 of byte i//8, padding bits zero;
  mode 1, runs:    a varint R, then R varint run lengths alternating false, true, false, ... from a false run;
                   only the first run may be 0 (when the column starts with true), and the runs sum to N.
Varints are LEB128 (7 bits per byte, low first, at most 5 bytes, no redundant zero byte). The blocks of all levels,
level 0 first, form one zstd frame. Measured on 100k rows (zstd level 9): packed wins on random columns (12.5 kB
against 16.0 kB as runs for p = 0.5; 4.5 kB against 4.8 kB for p = 0.05), runs win once the rows are ordered (runs
of mean length 30: 2.8 kB against 3.7 kB; a column sorted into two runs: 16 bytes), so the encoder picks per level.
Level 19 saved nothing on 1M-row matrices and took 8x longer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ArchiveError
from .section import EncodedSection, SectionKind, check_params, zstd_compress, zstd_decompress_exact

if TYPE_CHECKING:
    from .neighbours import Neighbours

PACKED, RUNS = 0, 1
VARINT_MAX_BYTES = 5
VARINT_LIMIT = 1 << (7 * VARINT_MAX_BYTES)  # exclusive bound of a varint value
MAX_ROWS = (1 << 31) - 1  # keeps run counts within varints and their sums within int64


def write_varints(values: np.ndarray) -> bytes:
    """LEB128 bytes of non-negative integers ``values`` [R] (each below 2^35)."""
    values = np.asarray(values, dtype=np.int64)
    if values.size and (values.min() < 0 or values.max() >= VARINT_LIMIT):
        raise ValueError(f"varints hold 0 <= v < 2^35, got range [{values.min()}, {values.max()}]")
    nbytes = np.ones(values.shape, dtype=np.int64)
    for k in range(1, VARINT_MAX_BYTES):
        nbytes += values >= (1 << (7 * k))
    starts = np.cumsum(nbytes) - nbytes
    out = np.empty(int(nbytes.sum()), dtype=np.uint8)
    for k in range(VARINT_MAX_BYTES):
        has = nbytes > k
        byte = (values[has] >> (7 * k)) & 0x7F
        more = (nbytes[has] > k + 1).astype(np.int64) << 7
        out[starts[has] + k] = byte | more
    return out.tobytes()


def varint(value: int) -> bytes:
    """The LEB128 bytes of one non-negative integer below 2^35, as ``write_varints`` writes it: the headers of the
    entropy coder's columns write tens of thousands of these per encode, too many for an array call each."""
    if not 0 <= value < VARINT_LIMIT:
        raise ValueError(f"varints hold 0 <= v < 2^35, got {value}")
    out = bytearray()
    while value >= 0x80:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def read_varints(buf: np.ndarray, pos: int, count: int) -> tuple[np.ndarray, int]:
    """``count`` varints from ``buf`` [B] uint8 at ``pos`` -> (values [count] int64, position after them)."""
    if count == 0:
        return np.zeros(0, dtype=np.int64), pos
    window = buf[pos : pos + VARINT_MAX_BYTES * count]
    ends = np.flatnonzero(window < 0x80)[:count]
    if len(ends) < count:
        raise ArchiveError(
            "corrupt_section",
            f"mask stream: {len(ends)} of {count} varints end within {len(window)} bytes (cut short or overlong)",
        )
    starts = np.concatenate([[0], ends[:-1] + 1])
    lengths = ends - starts + 1
    if int(lengths.max()) > VARINT_MAX_BYTES:
        raise ArchiveError("corrupt_section", f"mask stream has a varint longer than {VARINT_MAX_BYTES} bytes")
    if bool(((lengths > 1) & (window[ends] == 0)).any()):
        raise ArchiveError("corrupt_section", "mask stream has a varint with a redundant zero byte")
    seg = window[: ends[-1] + 1].astype(np.int64)
    shift = 7 * (np.arange(len(seg)) - np.repeat(starts, lengths))
    values = np.add.reduceat((seg & 0x7F) << shift, starts)
    return values, pos + int(ends[-1]) + 1


def pack_uint(values: np.ndarray, width: int) -> bytes:
    """Non-negative integers [N] below 2^width (width < 64) as N fields of ``width`` bits, most significant first,
    the last byte padded with zeros."""
    shifts = np.arange(width - 1, -1, -1, dtype=np.uint64)
    return np.packbits(((values.astype(np.uint64)[:, None] >> shifts) & 1).astype(np.uint8)).tobytes()


def unpack_uint(data: bytes, count: int, width: int, what: str) -> np.ndarray:
    """Inverse of ``pack_uint``: ``count`` int64 values; ArchiveError unless ``data`` is exactly their bytes."""
    if len(data) != (count * width + 7) // 8:
        raise ArchiveError("corrupt_section", f"{what}: {len(data)} bytes for {count} fields of {width} bits")
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8))[: count * width].reshape(count, width)
    weights = np.uint64(1) << np.arange(width - 1, -1, -1, dtype=np.uint64)
    return (bits.astype(np.uint64) @ weights).astype(np.int64)


def column_runs(column: np.ndarray) -> np.ndarray:
    """Run lengths [R] of a bool column [N], alternating false/true from a false run (0 if it starts true)."""
    n = len(column)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    edges = np.flatnonzero(column[1:] != column[:-1]) + 1
    runs = np.diff(np.concatenate([[0], edges, [n]])).astype(np.int64)
    if column[0]:
        runs = np.concatenate([[0], runs])
    return runs


def _runs_block(column: np.ndarray) -> bytes:
    runs = column_runs(column)
    return bytes([RUNS]) + write_varints(np.array([len(runs)])) + write_varints(runs)


def _packed_block(column: np.ndarray) -> bytes:
    return bytes([PACKED]) + np.packbits(column).tobytes()


def encode_masks(bits: np.ndarray, level: int = 9) -> bytes:
    """The decoded byte stream (before zstd) of a bool matrix [N, L+1]: per level, the smaller block."""
    if bits.dtype != np.bool_ or bits.ndim != 2:
        raise ValueError(f"masks are a bool matrix [N, L+1], got {bits.dtype} of shape {bits.shape}")
    if bits.shape[0] > MAX_ROWS:
        raise ValueError(f"masks hold at most {MAX_ROWS} rows, got {bits.shape[0]}")
    blocks = []
    for lvl in range(bits.shape[1]):
        column = np.ascontiguousarray(bits[:, lvl])
        candidates = [_packed_block(column), _runs_block(column)]
        blocks.append(min(candidates, key=lambda b: len(zstd_compress(b, level))))
    return b"".join(blocks)


def decode_masks(raw: bytes, n: int, levels: int) -> np.ndarray:
    """Inverse of ``encode_masks``: the bool matrix [n, levels]; ArchiveError("corrupt_section") if malformed."""
    buf = np.frombuffer(raw, dtype=np.uint8)
    bits = np.zeros((n, levels), dtype=np.bool_)
    pos = 0
    for lvl in range(levels):
        if pos >= len(buf):
            raise ArchiveError("corrupt_section", f"mask stream ends before level {lvl}")
        mode = int(buf[pos])
        pos += 1
        if mode == PACKED:
            size = (n + 7) // 8
            packed = buf[pos : pos + size]
            if len(packed) != size:
                raise ArchiveError("corrupt_section", f"mask level {lvl}: {len(packed)} packed bytes of {size}")
            column = np.unpackbits(packed)
            if bool(column[n:].any()):
                raise ArchiveError("corrupt_section", f"mask level {lvl}: padding bits set")
            bits[:, lvl] = column[:n].astype(np.bool_)
            pos += size
        elif mode == RUNS:
            (count,), pos = read_varints(buf, pos, 1)
            if count > n + 1:
                raise ArchiveError("corrupt_section", f"mask level {lvl}: {count} runs for {n} rows")
            runs, pos = read_varints(buf, pos, int(count))
            if count and (int(runs[1:].min(initial=1)) == 0 or (count == 1 and runs[0] == 0)):
                raise ArchiveError("corrupt_section", f"mask level {lvl}: an empty run other than a leading one")
            if bool((runs > n).any()) or int(runs.sum()) != n:
                raise ArchiveError("corrupt_section", f"mask level {lvl}: runs sum to {int(runs.sum())}, not {n}")
            bits[:, lvl] = np.repeat(np.arange(count) % 2 == 1, runs)
        else:
            raise ArchiveError("corrupt_section", f"mask level {lvl}: unknown block mode {mode}")
    if pos != len(buf):
        raise ArchiveError("corrupt_section", f"mask stream has {len(buf) - pos} bytes after the last level")
    return bits


def max_raw_length(n: int, levels: int) -> int:
    """The longest stream ``encode_masks`` can write for [n, levels] (so larger claims are rejected unread)."""
    runs_bound = VARINT_MAX_BYTES * (n + 2)
    return levels * (1 + max((n + 7) // 8, runs_bound))


@dataclass(frozen=True)
class MaskZstd:
    """The level bit matrix as per-level packed-or-runs blocks in one zstd frame."""

    level: int = 9
    name: str = field(default="mask-zstd", init=False)
    kind: SectionKind = field(default="bool", init=False)

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        raw = encode_masks(values, self.level)
        return EncodedSection(zstd_compress(raw, self.level), len(raw), {})

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        check_params(self.name, params, {})
        n, levels = shape
        if n > MAX_ROWS:
            raise ArchiveError("bad_header", f"{self.name}: {n} rows, at most {MAX_ROWS}")
        if not levels <= raw_length <= max_raw_length(n, levels):
            raise ArchiveError(
                "bad_header",
                f"{self.name}: raw length {raw_length} impossible for {levels} levels of {n} rows "
                f"(between {levels} and {max_raw_length(n, levels)})",
            )

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n, levels = shape
        return decode_masks(zstd_decompress_exact(payload, raw_length, self.name), n, levels)


MASKS = MaskZstd()
