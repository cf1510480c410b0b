"""Entropy coding of quantised attribute symbols: integer tables [N, C] to bytes and back.

The encoder tries, and keeps the smallest of:
  * per column, raw values or first differences along the (Morton-ordered) rows, each coded either with a static
    adaptive-free ANS model (``constriction``; the symbol histogram is stored) or with zstandard at the narrowest
    byte width;
  * the whole table row-interleaved in one zstd frame (zstd's matches find repeated tuples, such as RGB triplets,
    that an order-0 model cannot see);
  * every symbol of the table, row after row, as one column coded as a column above (one histogram for all the
    columns: where they share their statistics, as a higher SH band's coefficients nearly do in small tables, that
    saves the columns' histograms; where they do not, each column's own histogram wins: 8-14% of the SH bytes of
    playbot 1M's finer step classes).
Measured on the real scenes (quantised to 16 bits per axis, 8 bits per colour channel): positions cost 157 kB as
ANS-coded differences against 213 kB as zstd-coded differences and 249 kB as zstd-coded values (fox, 50k); DC colour
cost 107 kB as interleaved zstd against 130 kB as per-channel ANS; opacity and scales code within 1% of their
order-0 entropy either way.

Stream layout (varints are the LEB128 of ``masks``; ``zz`` is the zigzag map of a signed integer):
    u8 kind            0: columns, 1: rows, 2: flat
    columns:  per column: u8 coder (0 zstd, 1 ans), u8 transform (0 raw, 1 delta), varint zz(offset), then
              zstd: u8 width, varint L, L bytes (one frame of N unsigned little-endian values of that width)
              ans:  varint K, varint L, L bytes (one zstd frame of K varint counts), varint W, W uint32 words
    rows:     C varints zz(offset), u8 width, varint L, L bytes (one frame of N*C values, row-major)
    flat:     one column as above, of the N*C values row-major (format version 4 on)
Symbols are ``value - offset`` (after the transform), so they are non-negative; a decoder checks every count and
length against the table's known shape before it allocates.
"""

from __future__ import annotations

import math
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from .errors import ArchiveError
from .masks import read_varints, varint, write_varints
from .section import coding_pool, zstd_compress, zstd_decompress_exact

MAX_ALPHABET = 1 << 22  # ANS histograms beyond this go to zstd: the histogram would cost more than it saves
COLUMNS, ROWS, FLAT = 0, 1, 2
ZSTD, ANS = 0, 1
RAW, DELTA = 0, 1
_WIDTHS = {1: np.uint8, 2: np.uint16, 4: np.uint32}
# Tables of at least this many symbols code their columns on every core (``coding_pool``).
PARALLEL_SYMBOLS = 1 << 15
TRANSFORM_MARGIN = 1.1  # a transform whose order-0 entropy exceeds the other's by more is not coded (``_transforms``)
CODING_LEVEL = 9  # zstd level of the streams ``encode_table`` writes
ESTIMATE_LEVEL = 1  # and of those an estimate codes (``table_bits``)


def _zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def _unzigzag(z: int) -> int:
    return z // 2 if z % 2 == 0 else -(z + 1) // 2


def _width(max_symbol: int) -> int:
    for width in (1, 2, 4):
        if max_symbol < 1 << (8 * width):
            return width
    raise ValueError(f"symbols up to {max_symbol} do not fit 32 bits")


def _ans_words(symbols: np.ndarray, counts: np.ndarray) -> np.ndarray:
    import constriction

    model = constriction.stream.model.Categorical(counts / counts.sum(), perfect=False)
    coder = constriction.stream.stack.AnsCoder()
    coder.encode_reverse(symbols.astype(np.int32), model)
    return coder.get_compressed()


@dataclass(frozen=True)
class _Transformed:
    """A column's values as they are or differenced, shifted to non-negative symbols."""

    transform: int
    offset: int
    symbols: np.ndarray
    top: int
    counts: np.ndarray | None  # the histogram, where ANS can code them (two symbols or more, a bounded alphabet)
    bits: float  # their order-0 entropy (inf without a histogram)


def _delta(column: np.ndarray) -> np.ndarray:
    """Each value less the one before it (the first less 0), as ``np.diff`` with a 0 prepended, in one array the
    column's size (``np.diff`` first copies the column with the 0 in front)."""
    out = np.empty(column.shape, dtype=np.result_type(column.dtype, np.int64))
    if len(column):
        out[0] = column[0]
        np.subtract(column[1:], column[:-1], out=out[1:], dtype=out.dtype)
    return out


def _transforms(column: np.ndarray) -> list[_Transformed]:
    """The column raw and differenced, less the one whose order-0 entropy is more than ``TRANSFORM_MARGIN`` above
    the other's: neither coder makes up such a gap (on the shared scenes' tables the transform that coded smallest
    never had an entropy more than 3% above the other's), and it halves the coding of most columns."""
    out = []
    for transform in (RAW, DELTA):
        values = column if transform == RAW else _delta(column)
        offset = int(values.min()) if len(values) else 0
        if transform == RAW:
            symbols = values - offset
        else:
            symbols = values
            symbols -= offset
        del values  # else the delta's int64 array outlives its narrowed symbols
        top = int(symbols.max()) if len(symbols) else 0
        if top < 1 << 32:
            # Kept at the width their stream has: a flat SH table of a million Gaussians is 21M symbols, 168 MB a
            # transform as int64, and both transforms of both ways of a table are held at once.
            symbols = symbols.astype(_WIDTHS[_width(top)])
        counts, bits = None, math.inf
        if 0 < top < MAX_ALPHABET:  # constriction needs two symbols or more
            counts = np.bincount(symbols, minlength=top + 1)
            used = counts[counts > 0].astype(np.float64)
            bits = float((used * np.log2(len(symbols) / used)).sum())
        out.append(_Transformed(transform, offset, symbols, top, counts, bits))
    least = min(t.bits for t in out)  # a transform without a histogram (a constant column, huge alphabets) stays
    return [t for t in out if t.counts is None or t.bits <= TRANSFORM_MARGIN * least]


def _column(column: np.ndarray, level: int, raw_zstd: bool = True) -> bytes:
    """The smallest stream of one column: raw or differenced values, each by zstd or ANS (raw values by zstd only
    with ``raw_zstd``: a table of one column has that stream already, two bytes shorter, as its rows)."""
    out = []
    for t in _transforms(column):
        head = bytes([t.transform]) + varint(_zigzag(t.offset))
        if raw_zstd or t.transform != RAW:
            frame = zstd_compress(t.symbols.astype(_WIDTHS[_width(t.top)], copy=False), level)
            out.append(bytes([ZSTD]) + head + bytes([_width(t.top)]) + varint(len(frame)) + frame)
        if t.counts is not None:
            hist = zstd_compress(write_varints(t.counts), level)
            words = _ans_words(t.symbols, t.counts.astype(np.float64))
            sizes = varint(t.top + 1) + varint(len(hist))
            out.append(bytes([ANS]) + head + sizes + hist + varint(len(words)) + words.tobytes())
    return min(out, key=len)


def _rows(table: np.ndarray, level: int) -> bytes:
    offsets = table.min(axis=0) if len(table) else np.zeros(table.shape[1], dtype=np.int64)
    symbols = table - offsets
    width = _width(int(symbols.max()) if symbols.size else 0)
    frame = zstd_compress(np.ascontiguousarray(symbols.astype(_WIDTHS[width])), level)
    return (
        bytes([ROWS])
        + write_varints(np.array([_zigzag(int(o)) for o in offsets], dtype=np.int64))
        + bytes([width])
        + varint(len(frame))
        + frame
    )


def _checked(table: np.ndarray) -> np.ndarray:
    if table.ndim != 2 or table.dtype.kind not in "iu":
        raise ValueError(f"entropy tables are integer tables [N, C], got {table.dtype} of shape {table.shape}")
    table = table.astype(np.int64, copy=False)
    if table.size and (magnitude := max(-int(table.min()), int(table.max()))) >= 1 << 30:
        raise ValueError(f"symbols must stay within +-2^30, got magnitude {magnitude}")
    return table


def _flat(table: np.ndarray, level: int) -> bytes:
    # Its raw values by zstd differ from the rows' stream by the columns' offsets: one offset for all keeps equal
    # values in different columns equal, which zstd's matches find (3% smaller on kacytran's small SH tables).
    return bytes([FLAT]) + _column(table.reshape(-1), level)


def encode_table(table: np.ndarray, level: int = CODING_LEVEL) -> bytes:
    """The smallest stream for an integer table [N, C] (values within +-2^31 after differencing)."""
    table = _checked(table)
    wide = table.shape[1] > 1
    if table.size >= PARALLEL_SYMBOLS and wide:
        whole: list[Future[bytes]] = [coding_pool().submit(f, table, level) for f in (_rows, _flat)]
        parts = list(coding_pool().map(_column, table.T, [level] * table.shape[1]))
        others = [f.result() for f in whole]
    else:
        parts = [_column(table[:, c], level, raw_zstd=wide) for c in range(table.shape[1])]
        others = [_rows(table, level)] + ([_flat(table, level)] if wide else [])
    return min(bytes([COLUMNS]) + b"".join(parts), *others, key=len)


def _column_bits(column: np.ndarray, level: int, raw_zstd: bool = True) -> float:
    """About the bits of ``_column(column, raw_zstd=raw_zstd)``: its zstd streams coded for real, its ANS streams
    priced at their order-0 entropy plus their histograms' frames (coding them is what takes the time)."""
    best = math.inf
    for t in _transforms(column):
        if raw_zstd or t.transform != RAW:
            frame = zstd_compress(t.symbols.astype(_WIDTHS[_width(t.top)], copy=False), level)
            best = min(best, 8.0 * (len(frame) + _HEAD))
        if t.counts is not None:
            hist = _histogram_bytes(t.counts, level)
            # words are whole 32-bit units; the head is a few varints
            best = min(best, 32.0 * math.ceil(t.bits / 32.0 + 1e-9) + 8.0 * (hist + _HEAD))
    return best


def _histogram_bytes(counts: np.ndarray, level: int) -> int:
    """About the bytes of a histogram's frame (zstd of its varints): coded for real up to ``DENSE_ALPHABET``
    symbols; past it (fine steps: millions of counts, mostly zero) as the frames of its non-zero counts and of the
    gaps between them, which is what zstd's matches make of the zero runs, at a fraction of the time."""
    if len(counts) <= DENSE_ALPHABET:
        return len(zstd_compress(write_varints(counts), level))
    used = np.flatnonzero(counts)
    gaps = np.diff(used, prepend=np.int64(0))
    return len(zstd_compress(write_varints(counts[used]), level)) + len(zstd_compress(write_varints(gaps), level))


DENSE_ALPHABET = 1 << 16
_HEAD = 10  # bytes of a column's coder, transform, offset and lengths, about


def table_bits(table: np.ndarray, level: int = ESTIMATE_LEVEL) -> float:
    """About the bits ``encode_table(table)`` takes, without coding it: each ANS stream priced by its order-0
    entropy (what a static model reaches, within a few bytes) and its histogram's frame, each zstd stream coded at
    ``level``. At the fast ``ESTIMATE_LEVEL`` zstd takes a quarter of the time of ``CODING_LEVEL`` and its frames
    come out within 2% of the encoder's, but where its matches count most (flat columns of SH coefficients: 6-36%
    more). ``tests/unit/test_rate_estimate.py`` holds the figures to the real streams."""
    table = _checked(table)
    wide = table.shape[1] > 1
    columns = 8.0 + sum(_column_bits(table[:, c], level, raw_zstd=wide) for c in range(table.shape[1]))
    flat = 8.0 + _column_bits(table.reshape(-1), level) if wide else math.inf
    return min(columns, flat, 8.0 * len(_rows(table, level)))


class _Reader:
    """Bounded reads from a stream; every shortfall is a corrupt section."""

    def __init__(self, data: bytes) -> None:
        self.buf = np.frombuffer(data, dtype=np.uint8)
        self.pos = 0

    def byte(self) -> int:
        if self.pos >= len(self.buf):
            raise ArchiveError("corrupt_section", "symbol stream ends early")
        self.pos += 1
        return int(self.buf[self.pos - 1])

    def varints(self, count: int) -> list[int]:
        values, self.pos = read_varints(self.buf, self.pos, count)
        return [int(v) for v in values]

    def take(self, length: int) -> bytes:
        if self.pos + length > len(self.buf):
            raise ArchiveError("corrupt_section", f"symbol stream needs {length} bytes at {self.pos}, has fewer")
        self.pos += length
        return self.buf[self.pos - length : self.pos].tobytes()

    def done(self) -> None:
        if self.pos != len(self.buf):
            raise ArchiveError("corrupt_section", f"symbol stream has {len(self.buf) - self.pos} trailing bytes")


def _read_fixed(reader: _Reader, count: int, what: str) -> np.ndarray:
    width = reader.byte()
    if width not in _WIDTHS:
        raise ArchiveError("corrupt_section", f"{what}: symbol width {width}, expected 1, 2 or 4")
    (length,) = reader.varints(1)
    raw = zstd_decompress_exact(reader.take(length), count * width, what)
    return np.frombuffer(raw, dtype=_WIDTHS[width]).astype(np.int64)


def _read_ans(reader: _Reader, n: int, what: str) -> np.ndarray:
    import constriction

    alphabet, length = reader.varints(2)
    if not 1 < alphabet <= MAX_ALPHABET:
        raise ArchiveError("corrupt_section", f"{what}: alphabet of {alphabet} symbols")
    # Each count is a varint of at most 5 bytes: bound the histogram before inflating it.
    raw = zstandard_bounded(reader.take(length), 5 * alphabet, what)
    counts, end = read_varints(np.frombuffer(raw, dtype=np.uint8), 0, alphabet)
    if end != len(raw) or int(counts.sum()) != n:
        raise ArchiveError("corrupt_section", f"{what}: histogram counts {int(counts.sum())} symbols, expected {n}")
    (words,) = reader.varints(1)
    data = np.frombuffer(reader.take(4 * words), dtype="<u4").astype(np.uint32)
    model = constriction.stream.model.Categorical(counts.astype(np.float64) / n, perfect=False)
    coder = constriction.stream.stack.AnsCoder(data)
    symbols = np.asarray(coder.decode(model, n), dtype=np.int64)
    if not coder.is_empty():
        raise ArchiveError("corrupt_section", f"{what}: ANS words left after {n} symbols")
    return symbols


def zstandard_bounded(payload: bytes, max_length: int, what: str) -> bytes:
    """A zstd frame whose declared size is at most ``max_length``."""
    import zstandard

    try:
        declared = zstandard.frame_content_size(payload)
    except zstandard.ZstdError as exc:
        raise ArchiveError("corrupt_section", f"{what}: not a zstd frame ({exc})") from exc
    if not 0 <= declared <= max_length:
        raise ArchiveError("corrupt_section", f"{what}: zstd frame declares {declared} bytes, at most {max_length}")
    return zstd_decompress_exact(payload, declared, what)


def _read_column(reader: _Reader, n: int, what: str, col: int) -> np.ndarray:
    coder, transform = reader.byte(), reader.byte()
    if coder not in (ZSTD, ANS) or transform not in (RAW, DELTA):
        raise ArchiveError("corrupt_section", f"{what}: column {col} has coder {coder} transform {transform}")
    (offset,) = reader.varints(1)
    values = _read_fixed(reader, n, what) if coder == ZSTD else _read_ans(reader, n, what)
    values += _unzigzag(offset)
    return np.cumsum(values, out=values) if transform == DELTA else values


def decode_table(data: bytes, n: int, c: int, what: str) -> np.ndarray:
    """Inverse of ``encode_table``: the int64 table [n, c]; ArchiveError("corrupt_section") if malformed."""
    reader = _Reader(data)
    kind = reader.byte()
    if kind == ROWS:
        offsets = np.array([_unzigzag(z) for z in reader.varints(c)], dtype=np.int64)
        table = _read_fixed(reader, n * c, what).reshape(n, c) + offsets
    elif kind == COLUMNS:
        columns = [_read_column(reader, n, what, col) for col in range(c)]
        # One column (millions of rows) is returned as it is, without a copy.
        table = columns[0][:, None] if c == 1 else np.stack(columns, axis=1)
    elif kind == FLAT:
        table = _read_column(reader, n * c, what, 0).reshape(n, c)
    else:
        raise ArchiveError("corrupt_section", f"{what}: unknown table kind {kind}")
    reader.done()
    return table
