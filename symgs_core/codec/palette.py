"""Vector-quantised higher SH: a palette of SH vectors and one index per Gaussian (as PlayCanvas SOG stores them).

Entry 0 of the palette is the zero vector, so Gaussians whose bands ``prune.reduce_sh`` dropped cost only their index
and decode to exact zeros. The other entries are the distinct non-zero rows when they fit, else the centroids of a
k-means (Lloyd) fit. Entries are then quantised per band on the scalar codec's grid (``ShRestCodec``), entries that
land on one grid point merged, and the palette sorted by decreasing use so the index histogram codes compactly.

    payload   u32 length + indices (an [N, 1] table), then per band u32 length + that band's entry symbols
              (an [entries - 1, 3 * band width] table, channels decorrelated as for DC where that codes smaller)
    params    {"size": entries including the zero one, "steps": [band step, ...], "decorrelate": [bool, ...]}

The fit is deterministic (fixed seed) and memoised per array and palette size, since the step search encodes the
same SH many times with different steps and only the quantisation depends on those.
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .entropy import decode_table, encode_table, table_bits
from .errors import ArchiveError
from .masks import pack_uint, unpack_uint
from .quantize import (
    _check_raw,
    _correlate,
    _decorrelate,
    _finite,
    _flag,
    _grid,
    _keys,
    _raw_length,
    _symbols,
    band_slices,
    check_bands,
)
from .section import EncodedSection, Estimate, SectionKind, join_parts, split_all, split_parts

if TYPE_CHECKING:
    from .neighbours import Neighbours

MAX_PALETTE = 1 << 20
FIT_ROWS = 1 << 16  # k-means fits a random subsample of at most this many rows, then assigns every row once
ITERATIONS = 8
SEED = 0
CHUNK_ELEMENTS = 1 << 21  # distances held at once (rows x entries): a few MB, so a chunk stays in cache
CACHED_FITS = 4
SH_DEGREES = {0: 0, 3: 1, 8: 2, 15: 3}  # rows of sh_rest -> SH degree

_fits: OrderedDict[tuple[bytes, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
# ShPaletteCodec._fit, by the rows' digest, the size and the weights' identity; the weights are held weakly, so that a
# worker's cache does not keep a finished job's (a million rows' keys) alive.
_row_fits: OrderedDict[tuple[bytes, int, int], tuple[weakref.ref | None, _Fit]] = OrderedDict()
_fits_lock = threading.Lock()


def _nearest(rows: torch.Tensor, entries: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """For each row [R, D]: the index of its nearest entry [M, D] and ||c||^2 - 2 x.c for it; chunked matmuls."""
    labels = np.empty(len(rows), dtype=np.int64)
    best = np.empty(len(rows), dtype=np.float32)
    if len(entries) == 0:
        return labels, best
    norms = (entries * entries).sum(dim=1)
    chunk = max(1, CHUNK_ELEMENTS // len(entries))
    buffer = rows.new_empty(min(chunk, len(rows)), len(entries))
    for start in range(0, len(rows), chunk):
        block = rows[start : start + chunk]
        distances = torch.addmm(norms, block, entries.T, alpha=-2.0, out=buffer[: len(block)]).numpy()
        # numpy's argmin is vectorised along a row; torch's is several times slower on CPU.
        nearest = distances.argmin(axis=1)
        labels[start : start + len(block)] = nearest
        best[start : start + len(block)] = distances[np.arange(len(block)), nearest]
    return labels, best


def _means(rows: torch.Tensor, labels: np.ndarray, entries: torch.Tensor, moved: np.ndarray) -> torch.Tensor:
    """Entries whose rows changed (``moved`` [M] bool) moved to the mean of their rows; an empty one stays."""
    index = torch.from_numpy(labels)
    sums = torch.zeros_like(entries).index_add_(0, index, rows)
    counts = torch.bincount(index, minlength=len(entries)).to(entries.dtype)[:, None]
    update = torch.from_numpy(moved)[:, None] & (counts > 0)
    return torch.where(update, sums / counts.clamp(min=1.0), entries)


def _reassign(rows: torch.Tensor, entries: torch.Tensor, labels: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """Nearest entries after only the ``moved`` entries changed, ``labels`` being the nearest before: exact.

    A row whose entry stayed keeps it against every other entry that stayed (their distances did not change), so
    it is compared with the moved entries alone; only rows of moved entries search them all. After the first few
    Lloyd steps few entries move, and a step costs a fraction of a full search.
    """
    labels = labels.copy()
    search = moved[labels]
    if search.any():
        labels[search] = _nearest(rows[torch.from_numpy(search)], entries)[0]
    stay = np.flatnonzero(~search)
    candidates = np.flatnonzero(moved)
    if len(stay) and len(candidates):
        x = rows[torch.from_numpy(stay)]
        own = entries[torch.from_numpy(labels[stay])]
        distance = ((own * own).sum(dim=1) - 2.0 * (x * own).sum(dim=1)).numpy()
        nearest, best = _nearest(x, entries[torch.from_numpy(candidates)])
        closer = best < distance
        labels[stay[closer]] = candidates[nearest[closer]]
    return labels


def _kmeans(rows: np.ndarray, distinct: np.ndarray, inverse: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means of ``rows`` [R, D] to ``count`` entries seeded with a random sample of ``distinct`` rows
    (rows[i] == distinct[inverse[i]])."""
    rng = np.random.default_rng(SEED)
    fitted = np.arange(len(rows))
    if len(rows) > FIT_ROWS:
        fitted = np.sort(rng.choice(len(rows), FIT_ROWS, replace=False))
    entries = torch.from_numpy(distinct[np.sort(rng.choice(len(distinct), count, replace=False))].copy())
    every = torch.from_numpy(rows)
    sample = every[torch.from_numpy(fitted)]
    labels = _nearest(sample, entries)[0]
    moved = np.ones(count, dtype=bool)
    for _ in range(ITERATIONS):
        entries = _means(sample, labels, entries, moved)
        before, labels = labels, _reassign(sample, entries, labels, moved)
        changed = before != labels
        moved = np.zeros(count, dtype=bool)
        moved[before[changed]] = moved[labels[changed]] = True
        if not moved.any():
            break
    entries = _means(sample, labels, entries, moved)
    # Every row is assigned as its distinct row is, each distinct row searched once: scenes decoded from a palette
    # repeat their rows (playbot at 1M: 131k distinct rows of 1M), and the search over every entry costs the most.
    sampled = inverse[fitted]
    label_of = np.empty(len(distinct), dtype=np.int64)
    label_of[sampled] = _reassign(sample, entries, labels, moved)
    rest = np.ones(len(distinct), dtype=bool)
    rest[sampled] = False
    label_of[rest] = _nearest(torch.from_numpy(distinct[rest]), entries)[0]
    every_label = label_of[inverse]
    # One last update on every row: the entries become the means of the rows that use them.
    return _means(every, every_label, entries, np.ones(count, dtype=bool)).numpy(), every_label


def fit_palette(rows: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``size`` entries [M, D] for ``rows`` [R, D] float32, and each row's entry [R] (int64).

    The distinct rows, exactly, when at most ``size`` of them; else k-means: deterministic, fitted on a random
    subsample of ``FIT_ROWS`` rows, ``ITERATIONS`` Lloyd steps, every row then assigned to its nearest centroid.
    Entries no row uses may remain.
    """
    if rows.ndim != 2 or rows.dtype != np.float32:
        raise ValueError(f"fit_palette takes float32 rows [R, D], got {rows.dtype} of shape {rows.shape}")
    if size < 1:
        raise ValueError(f"palette size must be at least 1, got {size}")
    rows = np.ascontiguousarray(rows + np.float32(0.0))  # -0.0 becomes 0.0: equal rows get equal bytes
    if rows.shape[1] == 0 or len(rows) == 0:
        return np.zeros((min(len(rows), 1), rows.shape[1]), np.float32), np.zeros(len(rows), np.int64)
    keys = rows.view(np.dtype((np.void, rows.shape[1] * 4)))[:, 0]
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    distinct = rows[first]
    if len(distinct) <= size:
        return distinct, inverse.reshape(-1).astype(np.int64)
    return _kmeans(rows, distinct, inverse.reshape(-1), size)


def _digest(rows: np.ndarray) -> bytes:
    # SHA-256 runs in the CPU's SHA instructions where it has them: twice blake2b's speed on a million SH rows.
    digest = hashlib.sha256(np.ascontiguousarray(rows).reshape(-1).view(np.uint8).data)  # no copy
    digest.update(repr((rows.shape, rows.dtype.str)).encode())
    return digest.digest()


def _cached_fit(rows: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``fit_palette``, memoised on the rows' bytes and the size for the last ``CACHED_FITS`` calls."""
    key = (_digest(rows), size)
    with _fits_lock:
        if key in _fits:
            _fits.move_to_end(key)
            return _fits[key]
    entries, labels = fit_palette(rows, size)
    entries.setflags(write=False)
    labels.setflags(write=False)
    with _fits_lock:
        _fits[key] = (entries, labels)
        while len(_fits) > CACHED_FITS:
            _fits.popitem(last=False)
    return entries, labels


ZERO, NEW, SEEN = 0, 1, 2  # kinds of index in the first-use order


def _encode_first_use(index: np.ndarray) -> bytes:
    """Indices [N] of a palette numbered by first use (0 the zero entry): each row's kind (``ZERO``; ``NEW``, the next
    entry, which costs nothing more; ``SEEN``), then each seen entry's number among the ``m`` seen so far on
    ceil(log2 m) bits, grouped by that width. Where most entries serve one or two rows, as in scenes decoded from
    SOG, this is nearly half the bytes of an entropy-coded index: playbot 125k, 64k entries, 245 kB against 132 kB.
    """
    seen = np.maximum.accumulate(np.concatenate([[0], index[:-1]])) if len(index) else index
    kinds = np.where(index == 0, ZERO, np.where(index > seen, NEW, SEEN))
    old = kinds == SEEN
    widths = _widths(seen[old])
    parts = [encode_table(kinds[:, None])]
    parts += [pack_uint(index[old][widths == w] - 1, w) for w in range(int(widths.max()) + 1 if len(widths) else 0)]
    return join_parts(parts[:1]) + b"".join(parts[1:])


def _first_use_bits(index: np.ndarray) -> float:
    """About the bits of ``_encode_first_use(index)``: the kinds' table estimated, the seen numbers exact."""
    seen = np.maximum.accumulate(np.concatenate([[0], index[:-1]])) if len(index) else index
    kinds = np.where(index == 0, ZERO, np.where(index > seen, NEW, SEEN))
    widths = np.bincount(_widths(seen[kinds == SEEN]))
    return table_bits(kinds[:, None]) + 32.0 + sum(8.0 * ((int(c) * w + 7) // 8) for w, c in enumerate(widths))


def _widths(seen: np.ndarray) -> np.ndarray:
    """Bits of a seen entry's number when ``seen`` entries came before: the bit length of seen - 1."""
    out = np.zeros(len(seen), dtype=np.int64)
    many = seen > 1
    out[many] = np.floor(np.log2((seen[many] - 1).astype(np.float64))).astype(np.int64) + 1
    return out


def _decode_first_use(payload: bytes, n: int, size: int, what: str) -> np.ndarray:
    """Inverse of ``_encode_first_use`` for ``n`` rows of a palette of ``size`` entries."""
    (kinds_part,) = split_parts(payload[: 4 + int.from_bytes(payload[:4], "little")], 1, what)
    kinds = decode_table(kinds_part, n, 1, what)[:, 0]
    if n and (kinds.min() < ZERO or kinds.max() > SEEN):
        raise ArchiveError("corrupt_section", f"{what}: an index kind lies outside 0..2")
    new = kinds == NEW
    seen = np.cumsum(new) - new  # entries met before each row
    if int(new.sum()) != size - 1:
        raise ArchiveError("corrupt_section", f"{what}: {int(new.sum())} entries met, palette of {size - 1}")
    old = kinds == SEEN
    if (seen[old] < 1).any():
        raise ArchiveError("corrupt_section", f"{what}: a row refers back before any entry was met")
    index = np.where(new, seen + 1, 0)
    widths = _widths(seen[old])
    rest, pos = payload[4 + len(kinds_part) :], 0
    numbers = np.zeros(int(old.sum()), dtype=np.int64)
    for w in range(int(widths.max()) + 1 if len(widths) else 0):
        chosen = widths == w
        length = (int(chosen.sum()) * w + 7) // 8
        numbers[chosen] = unpack_uint(rest[pos : pos + length], int(chosen.sum()), w, what)
        pos += length
    if pos != len(rest):
        raise ArchiveError("corrupt_section", f"{what}: {len(rest) - pos} bytes after the seen entries' numbers")
    if (numbers >= seen[old]).any():
        raise ArchiveError("corrupt_section", f"{what}: a row refers to an entry not yet met")
    index[old] = numbers + 1
    return index


MAX_CLASS = 3  # an entry's step is the band's step times 2^class, class 0..MAX_CLASS
CLASS_OFFSET = 0.0  # fitted archives on playbot 31k: 383.5 kB at offset 0, 385.9 at 0.25, 393 at 0.5 and at -0.5


def entry_classes(weights: np.ndarray) -> np.ndarray:
    """Step class [E] of palette entries of render weights [E]: the step that spends equal error per unit of weight
    grows as weight^-1/2, in powers of two from the mean entry's (class 0 at and above it)."""
    mean = float(weights.mean()) if len(weights) else 0.0
    if mean <= 0:
        return np.zeros(len(weights), dtype=np.int64)
    ratio = mean / np.maximum(weights, mean * 4.0**-MAX_CLASS)
    return np.clip(np.round(0.5 * np.log2(ratio) + CLASS_OFFSET), 0, MAX_CLASS).astype(np.int64)


def _band_tables(symbols: np.ndarray, classes: np.ndarray, mixed: bool) -> list[bytes]:
    """One table per class present (ascending) of a band's entry symbols [E, width, 3], channels decorrelated."""
    symbols = _decorrelate(symbols) if mixed else symbols
    width = symbols.shape[1] * 3
    return [encode_table(symbols[classes == c].reshape(-1, width)) for c in np.unique(classes)]


def _band_bits(symbols: np.ndarray, classes: np.ndarray, mixed: bool) -> list[float]:
    """About the bits of each of ``_band_tables``' tables."""
    symbols = _decorrelate(symbols) if mixed else symbols
    width = symbols.shape[1] * 3
    return [table_bits(symbols[classes == c].reshape(-1, width)) for c in np.unique(classes)]


@dataclass(frozen=True)
class _Fit:
    """What a palette of one size makes of a set of rows [N, K, 3], whatever its steps: the fitted entries [E, K, 3]
    (float64), each entry's step class [E], and each row's entry [N] counted from 1 (0: the zero entry)."""

    entries: np.ndarray
    classes: np.ndarray
    index: np.ndarray


@dataclass(frozen=True)
class _Layout:
    """A palette as ``ShPaletteCodec`` stores it: its distinct grid points [P, K, 3] in units of each band's step
    (point 0 the zero one, where dropped rows go), each point's step class [P], each fitted entry's point [E + 1]
    (``merged``, the zero entry first), each row's point [N], and the entry orders tried (``use``: by decreasing use;
    ``first``: by first use), each [P'] of the points some row uses."""

    fit: _Fit
    points: np.ndarray
    point_class: np.ndarray
    merged: np.ndarray
    index: np.ndarray
    orders: dict[str, np.ndarray]


@dataclass(frozen=True)
class RowWeights:
    """Render weight of each distinct SH row of a stored set (summed over the Gaussians that hold it), looked up by
    the row's bytes, so a codec finds the weight of rows in any order."""

    keys: np.ndarray  # [M] sorted void keys of float32 rows
    weights: np.ndarray  # [M]
    # The step search encodes the same rows at every rung: their shares are worked out once (rows' digest -> shares).
    _shares: dict[bytes, np.ndarray] = field(default_factory=dict, compare=False, repr=False)

    @staticmethod
    def of(sh_rest: np.ndarray, weights: np.ndarray) -> RowWeights:
        """From ``sh_rest`` [N, K, 3] float32 and each Gaussian's weight [N]."""
        keys = _row_keys(sh_rest.reshape(len(sh_rest), -1))
        unique, inverse = np.unique(keys, return_inverse=True)
        return RowWeights(unique, np.bincount(inverse.reshape(-1), weights=weights, minlength=len(unique)))

    def lookup(self, rows: np.ndarray) -> np.ndarray:
        """Weight [R] of each row [R, D] (float32 or float64 holding float32 values); 0 for rows not seen."""
        keys = _row_keys(rows.astype(np.float32))
        at = np.clip(np.searchsorted(self.keys, keys), 0, max(len(self.keys) - 1, 0))
        found = (self.keys[at] == keys) if len(self.keys) else np.zeros(len(keys), dtype=bool)
        return np.where(found, self.weights[at] if len(self.keys) else 0.0, 0.0)


    def per_row(self, rows: np.ndarray) -> np.ndarray:
        """Each row's [R] share of its weight: a row that ``rows`` holds m times gets 1/m of it each time."""
        rows = rows.astype(np.float32)
        digest = _digest(rows)
        shares = self._shares.get(digest)
        if shares is None:
            _, inverse, counts = np.unique(_row_keys(rows), return_inverse=True, return_counts=True)
            shares = self.lookup(rows) / counts[inverse.reshape(-1)]
            shares.setflags(write=False)
            self._shares.clear()  # one set of rows at a time: the ladder of one section
            self._shares[digest] = shares
        return shares


def distinct_rows(rows: np.ndarray) -> int:
    """How many distinct rows [R, D] there are (-0.0 and 0.0 one value, as in ``fit_palette``)."""
    return len(np.unique(_row_keys(rows))) if rows.shape[1] else min(len(rows), 1)


def _row_keys(rows: np.ndarray) -> np.ndarray:
    rows = np.ascontiguousarray(rows + np.float32(0.0))  # -0.0 becomes 0.0, as in ``fit_palette``
    return rows.view(np.dtype((np.void, rows.shape[1] * rows.itemsize)))[:, 0]


@dataclass(frozen=True)
class ShPaletteCodec:
    """Higher SH [N, K, 3] as a palette of at most ``size`` vectors (the zero vector first) and an index per row.

    ``steps`` lists the grid step of band 1, 2, 3 for the palette's entries; a scene of lower degree uses the first.
    ``weights``: the render weight of the rows; entries that little of the image depends on then take coarser steps
    (``entry_classes``), their class stored once per entry. The Gaussians' step classes play no part: an entry
    serves Gaussians of every class.
    """

    size: int
    steps: tuple[float, ...]
    weights: RowWeights | None = field(default=None, compare=False, repr=False)
    name: str = field(default="vq-sh", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _fit(self, values: np.ndarray) -> _Fit:
        """The steps' search asks for one set of rows at every rung: its fit is kept (``_cached_fit``'s key)."""
        key = (_digest(values), self.size, id(self.weights))
        with _fits_lock:
            held = _row_fits.get(key)
            if held is not None and (held[0]() if held[0] is not None else None) is self.weights:
                _row_fits.move_to_end(key)
                return held[1]
        n, k, _ = values.shape
        x = _finite(values, self.name).reshape(n, 3 * k)
        index = np.zeros(n, dtype=np.int64)
        entries = np.zeros((0, 3 * k), dtype=np.float32)
        if self.size > 1:  # a palette of one entry maps every row to zero
            nonzero = np.flatnonzero(x.any(axis=1))
            entries, labels = _cached_fit(values.reshape(n, 3 * k)[nonzero], self.size - 1)
            index[nonzero] = labels + 1
        classes = np.zeros(len(entries), dtype=np.int64)
        if self.weights is not None and len(entries):
            classes = entry_classes(np.bincount(index, weights=self.weights.per_row(x), minlength=len(entries) + 1)[1:])
        fit = _Fit(entries.reshape(len(entries), k, 3).astype(np.float64), classes, index)
        for array in (fit.entries, fit.classes, fit.index):
            array.setflags(write=False)
        with _fits_lock:
            _row_fits[key] = (None if self.weights is None else weakref.ref(self.weights), fit)
            while len(_row_fits) > CACHED_FITS:
                _row_fits.popitem(last=False)
        return fit

    def _layout(self, values: np.ndarray) -> _Layout:
        if values.ndim != 3 or values.shape[1] not in SH_DEGREES or values.shape[2] != 3:
            raise ValueError(f"{self.name} encodes sh_rest [N, K, 3] with K in 0, 3, 8, 15, got {values.shape}")
        if not 1 <= self.size <= MAX_PALETTE:
            raise ValueError(f"{self.name}: palette size {self.size} outside 1..{MAX_PALETTE}")
        n, k, _ = values.shape
        degree = SH_DEGREES[k]
        if len(self.steps) < degree:
            raise ValueError(f"{self.name}: {len(self.steps)} band steps for SH degree {degree}")
        fit = self._fit(values)
        palette, classes = fit.entries, fit.classes
        # Symbols in units of each band's step; an entry of class c lies on multiples of 2^c of them.
        scale = (2.0 ** classes)[:, None, None]
        bands = [_grid(palette[:, s, :] / scale, 0.0, st, self.name) << classes[:, None, None]
                 for s, st in zip(band_slices(degree), self.steps)]  # fmt: skip
        q = np.concatenate([np.zeros((len(palette), 0, 3), dtype=np.int64), *bands], axis=1)
        q = q.reshape(len(palette), 3 * k)
        q = np.concatenate([np.zeros((1, q.shape[1]), dtype=np.int64), q])
        classes = np.concatenate([[0], classes])
        # Entries that land on one grid point become one, of the finest class among them; the zero entry leads.
        # Rows compared as bytes: a third of the time of numpy's row-wise unique, in another (but fixed) order.
        keys: np.ndarray = np.zeros(len(q), np.int64)
        if k:
            keys = np.ascontiguousarray(q).view(np.dtype((np.void, q.shape[1] * q.itemsize)))[:, 0]
        _, first_of, merged = np.unique(keys, return_index=True, return_inverse=True)
        points, merged = q[first_of], merged.reshape(-1)
        point_class = np.full(len(points), MAX_CLASS, dtype=np.int64)
        np.minimum.at(point_class, merged, classes)
        index = merged[fit.index]
        uses = np.bincount(index, minlength=len(points)).astype(np.float64)
        uses[merged[0]] = np.inf
        by_use = np.argsort(-uses, kind="stable")
        by_use = by_use[uses[by_use] > 0]
        first = np.full(len(points), len(index))
        np.minimum.at(first, index, np.arange(len(index)))
        first[merged[0]] = -1
        by_first = np.argsort(first, kind="stable")[: len(by_use)]
        return _Layout(fit, points.reshape(len(points), k, 3), point_class, merged, index,
                       {"use": by_use, "first": by_first})  # fmt: skip

    def _orders(self, layout: _Layout) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray, bool]]:
        """Per entry order: its name, each row's rank [N], the entries in that order [E - 1, K, 3] shifted down to
        their class and their classes [E - 1], and whether any class is above 0."""
        with_classes = bool(layout.point_class[layout.orders["use"][1:]].any())
        for name, order in layout.orders.items():
            rank = np.empty(len(layout.points), dtype=np.int64)
            rank[order] = np.arange(len(order))
            cls = layout.point_class[order[1:]]
            yield name, rank[layout.index], layout.points[order[1:]] >> cls[:, None, None], cls, with_classes

    def _plan(self, layout: _Layout, degree: int) -> tuple[float, str, list[bool]]:
        """The estimated bits of the smaller entry order, its name, and per band whether its channels go
        decorrelated: each choice made on estimates, so that an encode codes one layout, not all eight."""
        orders = list(self._orders(layout))
        # The entries' tables are priced once: the two orders hold the same rows, and their statistics are alike.
        _, _, stored, cls, with_classes = orders[0]
        bands = [[sum(_band_bits(stored[:, s, :], cls, flag)) for flag in (False, True)] for s in band_slices(degree)]
        entries = sum(min(b) for b in bands) + 32.0 * (1 + with_classes + degree * len(np.unique(cls)))
        costs = {name: (table_bits(ranks[:, None]) if name == "use" else _first_use_bits(ranks))
                 + (table_bits(cls[:, None]) if with_classes else 0.0) for name, ranks, _, cls, with_classes in orders}
        order = min(costs, key=lambda name: costs[name])
        return costs[order] + entries, order, [mixed < plain for plain, mixed in bands]

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        layout = self._layout(values)
        degree = SH_DEGREES[values.shape[1]]
        _, order, mixed = self._plan(layout, degree)
        name, ranks, stored, cls, with_classes = next(o for o in self._orders(layout) if o[0] == order)
        parts = [encode_table(ranks[:, None]) if name == "use" else _encode_first_use(ranks)]
        parts += [encode_table(cls[:, None])] if with_classes else []
        for s, flag in zip(band_slices(degree), mixed):
            parts += _band_tables(stored[:, s, :], cls, flag)
        params = {"size": len(stored) + 1, "steps": [float(s) for s in self.steps[:degree]], "decorrelate": mixed,
                  "order": name, "classes": with_classes}  # fmt: skip
        return EncodedSection(join_parts(parts), _raw_length(values.shape), params)

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        layout = self._layout(values)
        degree = SH_DEGREES[values.shape[1]]
        bits = self._plan(layout, degree)[0]
        palette = np.zeros(layout.points.shape, dtype=np.float32)
        for band, step in zip(band_slices(degree), self.steps):
            palette[:, band, :] = layout.points[:, band, :].astype(np.float32) * np.float32(step)
        return Estimate(bits, palette[layout.merged], index=layout.fit.index)

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        # Archives written before the first-use order and the classes carry neither key: ordered by use, no classes.
        later = {key for key in ("order", "classes") if key in params}
        _keys(params, {"size", "steps", "decorrelate"} | later, self.name)
        if "classes" in params:
            _flag(params, "classes", self.name)
        if params.get("order", "use") not in ("use", "first"):
            raise ArchiveError("bad_header", f"{self.name}: entry order {params['order']!r:.40}, expected use or first")
        if len(shape) != 3 or shape[1] not in SH_DEGREES or shape[2] != 3:
            raise ArchiveError("bad_header", f"{self.name}: cannot hold an array of shape {shape}")
        degree = SH_DEGREES[shape[1]]
        size = params["size"]
        if type(size) is not int or not 1 <= size <= min(MAX_PALETTE, shape[0] + 1):
            raise ArchiveError("bad_header", f"{self.name}: palette size {size!r:.40} for {shape[0]} rows")
        check_bands(params, degree, self.name)
        _check_raw(self.name, shape, raw_length)

    def parts(self, payload: bytes, params: dict[str, Any]) -> dict[str, int]:
        """Bytes of a checked payload's parts: the rows' index (with the entries' classes), then each band's entries."""
        parts = [4 + len(p) for p in split_all(payload, self.name)]
        head, degree = 2 if params.get("classes") else 1, len(params["steps"])
        per_band = (len(parts) - head) // max(degree, 1)
        bands = {f"sh_band_{b + 1}": sum(parts[head + b * per_band : head + (b + 1) * per_band]) for b in range(degree)}
        return {"sh_index": sum(parts[:head])} | bands

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n, k, _ = shape
        size, degree = params["size"], len(params["steps"])
        parts = split_all(payload, self.name)
        if not parts:
            raise ArchiveError("corrupt_section", f"{self.name}: no palette index")
        if params.get("order", "use") == "first":
            index = _decode_first_use(parts[0], n, size, self.name)
        else:
            index = decode_table(parts[0], n, 1, self.name)[:, 0]
        if n and (index.min() < 0 or index.max() >= size):
            raise ArchiveError("corrupt_section", f"{self.name}: a palette index lies outside 0..{size - 1}")
        cls = np.zeros(size - 1, dtype=np.int64)
        if params.get("classes"):
            if len(parts) < 2:
                raise ArchiveError("corrupt_section", f"{self.name}: no entry classes")
            cls = decode_table(parts[1], size - 1, 1, self.name)[:, 0]
            if size > 1 and (cls.min() < 0 or cls.max() > MAX_CLASS):
                raise ArchiveError("corrupt_section", f"{self.name}: an entry class lies outside 0..{MAX_CLASS}")
        present = np.unique(cls)
        tables = parts[2:] if params.get("classes") else parts[1:]
        if len(tables) != degree * len(present):
            raise ArchiveError("corrupt_section", f"{self.name}: {len(tables)} entry tables for {degree} bands")
        palette = np.zeros((size, k, 3), dtype=np.float32)
        for lvl, (rows, step) in enumerate(zip(band_slices(degree), params["steps"]), start=1):
            width = rows.stop - rows.start
            q = np.zeros((size - 1, width, 3), dtype=np.int64)
            for part, c in zip(tables[(lvl - 1) * len(present) : lvl * len(present)], present):
                chosen = cls == c
                group = _symbols(part, int(chosen.sum()), 3 * width, self.name).reshape(-1, width, 3)
                q[chosen] = (_correlate(group) if params["decorrelate"][lvl - 1] else group) << c
            palette[1:, rows, :] = q.astype(np.float32) * np.float32(step)
        return palette[index]
