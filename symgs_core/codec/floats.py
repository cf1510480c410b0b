"""Float attribute codecs: the values' bytes, rearranged in whichever layout zstandard packs best.

Trained 3DGS attributes are near-random in their low mantissa bytes but share signs and exponents, so splitting the
float's bytes into planes usually wins; values already quantised on a grid (a scene that went through SOG, for
example) repeat whole 4-byte words and compress better left in rows. Measured on real scenes, the best layout
differs per attribute and per scene, so the encoder tries each and keeps the smallest.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .errors import ArchiveError
from .section import EncodedSection, SectionKind, check_params, coding_pool, zstd_compress, zstd_decompress_exact

if TYPE_CHECKING:
    from .neighbours import Neighbours

# rows: as stored, [N, C]; columns: [C, N]; bytes: byte planes of the row-major values [W, N*C];
# column-bytes: byte planes of each column [W, C, N] (W bytes per value).
LAYOUTS = ("rows", "columns", "bytes", "column-bytes")
PARALLEL_VALUES = 1 << 15  # sections of at least this many values try the layouts on every core (``coding_pool``)


def _arrange(values: np.ndarray, layout: str) -> np.ndarray:
    """``values`` [N, C] -> the array whose C-order bytes are stored for ``layout``."""
    n, c = values.shape
    width = values.dtype.itemsize
    if layout == "rows":
        return values
    if layout == "columns":
        return values.T
    as_bytes = values.view(np.uint8).reshape(n, c, width)
    if layout == "bytes":
        return as_bytes.reshape(n * c, width).T
    return as_bytes.transpose(2, 1, 0)


def _restore(raw: bytes, n: int, c: int, dtype: np.dtype, layout: str) -> np.ndarray:
    """Inverse of ``_arrange``: stored bytes -> a fresh, writable [N, C] array of ``dtype``."""
    width = dtype.itemsize
    stored = np.frombuffer(raw, dtype=np.uint8)
    planes: np.ndarray  # the two layouts below give it different shapes
    if layout == "rows":
        return stored.copy().view(dtype).reshape(n, c)
    if layout == "columns":
        return np.ascontiguousarray(stored.view(dtype).reshape(c, n).T)
    if layout == "bytes":
        planes = stored.reshape(width, n * c)
        return np.ascontiguousarray(planes.T).view(dtype).reshape(n, c)
    planes = stored.reshape(width, c, n)
    return np.ascontiguousarray(planes.transpose(2, 1, 0)).view(dtype).reshape(n, c)


@dataclass(frozen=True)
class FloatZstd:
    """Float attribute values at ``dtype`` precision + zstd in the best of ``LAYOUTS``.

    float32 is bit-exact (signed zeros and subnormals included); float16 rounds and refuses values it would turn
    into infinities. ``level`` only affects encoding. The archive admits finite values only (``MAX_MAGNITUDE``).
    """

    dtype: Literal["float32", "float16"]
    level: int = 9
    kind: SectionKind = field(default="float32", init=False)

    def __post_init__(self) -> None:
        if self.dtype not in ("float32", "float16"):
            raise ValueError(f"float codecs store float32 or float16, got {self.dtype!r}")

    @property
    def name(self) -> str:
        """One name per stored precision, so a name alone tells a reader how to decode."""
        return f"f{np.dtype(self.dtype).itemsize * 8}-zstd"

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        if values.dtype != np.float32:
            raise ValueError(f"{self.name} encodes float32 attributes, got {values.dtype}")
        if values.ndim < 1:
            raise ValueError(f"{self.name} needs values with a leading Gaussian axis, got shape {values.shape}")
        columns = int(np.prod(values.shape[1:], dtype=np.int64))
        flat = np.ascontiguousarray(values.reshape(values.shape[0], columns))
        if self.dtype == "float16":
            finite = flat[np.isfinite(flat)]
            if finite.size and float(np.abs(finite).max()) > float(np.finfo(np.float16).max):
                raise ValueError(
                    f"{self.name}: values up to {float(np.abs(finite).max())!r} exceed the float16 range "
                    f"(+-{float(np.finfo(np.float16).max)})"
                )
            flat = flat.astype(np.float16)

        def packed(layout: str) -> bytes:
            return zstd_compress(np.ascontiguousarray(_arrange(flat, layout)), self.level)

        # min() over the lazy results holds only the smallest so far: four payloads of a large section outweigh it.
        payloads = coding_pool().map(packed, LAYOUTS) if flat.size >= PARALLEL_VALUES else map(packed, LAYOUTS)
        layout, best = min(zip(LAYOUTS, payloads), key=lambda pair: len(pair[1]))  # the first of equals, as in LAYOUTS
        return EncodedSection(best, flat.nbytes, {"layout": layout})

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        check_params(self.name, params, {"layout": LAYOUTS})
        expected = int(np.prod(shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize
        if raw_length != expected:
            raise ArchiveError(
                "bad_header", f"{self.name}: raw length {raw_length} for shape {shape}, expected {expected}"
            )

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        raw = zstd_decompress_exact(payload, raw_length, self.name)
        n = shape[0]
        c = int(np.prod(shape[1:], dtype=np.int64))
        values = _restore(raw, n, c, np.dtype(self.dtype), params["layout"])
        return values.astype(np.float32, copy=False).reshape(shape)


FLOAT32 = FloatZstd("float32")
FLOAT16 = FloatZstd("float16")
