"""Quantising section codecs: each attribute on a uniform grid, the integer symbols entropy coded (``entropy``).

A codec carries its step; the step, and whatever else decoding needs, is written into the section's ``params``, so
one reader decodes every step a writer chose. The stored set arrives in ``coding_order`` (Morton order of the position
codec's own grid inside each level group), which is what makes position gaps and differences small.

    positions   q = round((x - origin) / step), one step for all three axes (a cube grid in the bounding box); axes
                all on one grid (.spz decodes) use it, origins fitted so the float32 values decode bit for bit;
                stored as the gaps between their Morton codes (``morton``) or as a table, whichever is smaller
    rotations   smallest three: normalise, flip the sign so the largest component is positive, store its index and
                the other three on a grid of ``step`` in [-1/sqrt2, 1/sqrt2]; decoding restores a unit quaternion
                (the pipeline first turns each rotation into its frame closest to the identity, ``frames``, so the
                index is always w and the three span half the range)
    log-scales  q = round((s - origin) / step)
    opacity     quantised as alpha = sigmoid(logit) (what the renderer blends); alpha 0 decodes to the lowest logit
                the PLY reader keeps, which the renderer skips (alpha < 1/255)
    SH DC       q = round((dc - origin) / step) per channel, stored as (G, R - G, B - G) when that codes smaller
Log-scales, opacity and DC colour that already lie on a uniform grid (``native_grid``: scenes decoded from 8-bit
formats) are quantised on that grid, exactly, or on whole multiples of its step when the step asked for is coarser.
Given the neighbours a reader finds by the decoded positions (``neighbours``), the same three sections code their
symbols less their prediction from them where that is smaller (params ``predict``: how many neighbours, 0 none).
    SH rest     one step per band; a Gaussian's degree is the highest band with a non-zero symbol, stored as its own
                column, and only the bands up to it are stored: bands dropped by ``prune.reduce_sh`` cost nothing;
                each band's channels decorrelated as for DC where that codes smaller (measured: 6-14% of SH bytes
                on playbot, 9-27% of DC bytes on four of the real scenes, nothing on the donut)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..ply import OPACITY_LOGIT_MAX, OPACITY_LOGIT_MIN
from .classes import decode_groups, encode_groups, groups_bits, multipliers
from .entropy import CODING_LEVEL, ESTIMATE_LEVEL, PARALLEL_SYMBOLS, decode_table, encode_table, table_bits
from .errors import ArchiveError
from .morton import codes_bits, decode_codes, deinterleave, encode_codes, fits, interleave
from .neighbours import COUNTS, Neighbours, check_count
from .section import MAX_MAGNITUDE, EncodedSection, Estimate, SectionKind, coding_pool, join_parts, split_parts

SQRT1_2 = math.sqrt(0.5)
MAX_LEVELS = 1 << 24  # grid cells per axis: beyond this a step is too fine to be a quantiser
MAX_GRID_LEVELS = 4096  # distinct values up to which an attribute is tested for a grid of its own
GRID_TOLERANCE = 1e-3  # in grid cells: float32 storage of grid values stays far below it
MAX_POSITION_GRID_LEVELS = 1 << 20  # distinct values per axis up to which positions are tested for a grid
GRID_AGREEMENT = 1e-6  # relative difference up to which the three axes' grid steps count as one (float32)


def _number(params: dict[str, Any], key: str, codec: str) -> float:
    value: Any = params.get(key)  # a header's JSON value: the type test below is what checks it
    if type(value) not in (int, float) or not math.isfinite(value):
        raise ArchiveError("bad_header", f"{codec}: parameter {key}={value!r:.60} must be a finite number")
    return float(value)


def _step(params: dict[str, Any], codec: str) -> float:
    """A positive step whose grid of MAX_LEVELS cells stays within +-MAX_MAGNITUDE."""
    step = _number(params, "step", codec)
    if not 0 < step <= MAX_MAGNITUDE / MAX_LEVELS:
        raise ArchiveError("bad_header", f"{codec}: step {step:g} must lie in (0, {MAX_MAGNITUDE / MAX_LEVELS:g}]")
    return step


def _origin(value: Any, codec: str) -> float:
    origin = _number({"origin": value}, "origin", codec)
    if abs(origin) > MAX_MAGNITUDE:
        raise ArchiveError("bad_header", f"{codec}: origin {origin:g} lies beyond +-{MAX_MAGNITUDE:g}")
    return origin


def _keys(params: dict[str, Any], keys: set[str], codec: str) -> None:
    if set(params) != keys:
        raise ArchiveError("bad_header", f"{codec}: parameters {sorted(params)}, expected {sorted(keys)}")


def _raw_length(shape: tuple[int, ...]) -> int:
    return int(np.prod(shape, dtype=np.int64)) * 4


def _check_raw(codec: str, shape: tuple[int, ...], raw_length: int) -> None:
    if raw_length != _raw_length(shape):
        raise ArchiveError("bad_header", f"{codec}: raw length {raw_length} for shape {shape}")


def _check_finite(values: np.ndarray, codec: str) -> None:
    if values.dtype != np.float32:
        raise ValueError(f"{codec} encodes float32 attributes, got {values.dtype}")
    if not np.isfinite(values).all():
        raise ValueError(f"{codec}: attributes must be finite to be quantised")


def _finite(values: np.ndarray, codec: str) -> np.ndarray:
    _check_finite(values, codec)
    return values.astype(np.float64)


def _grid(values: np.ndarray, origin: np.ndarray | float, step: float | np.ndarray, codec: str) -> np.ndarray:
    """Cells of ``values`` on a grid of ``step`` (one, or one per row broadcast against them) from ``origin``."""
    # In float64 (float32 values widen exactly), in one array divided and rounded in place: a million Gaussians'
    # third SH band is 170 MB a copy.
    q = np.subtract(values, origin, dtype=np.float64)
    q /= step
    np.round(q, out=q)
    if q.size and (far := max(float(q.max()), -float(q.min()))) >= MAX_LEVELS:
        raise ValueError(f"{codec}: step {np.min(step):g} puts values {far:.0f} cells from origin")
    return q.astype(np.int64)


def _grid_step(unique: np.ndarray, max_levels: int) -> float | None:
    """Step of the uniform grid that the sorted distinct values ``unique`` [M] (float64) lie on, or None.

    The smallest difference carries the values' float32 rounding: near magnitude 1 on 8000 cells its error adds up to
    half a cell at the far end. It is refined on spans that at most double (a gap in the values excepted), each short
    enough for the cell count to round right, before every value is tested against it.
    """
    if not 2 <= len(unique) <= max_levels:
        return None
    gap, k = float(np.diff(unique).min()), 0
    while k < len(unique) - 1:
        k = max(k + 1, int(np.searchsorted(unique, 2 * unique[k] - unique[0], side="right")) - 1)
        span = float(unique[k] - unique[0])
        gap = span / round(span / gap)
    if span / gap >= MAX_LEVELS:
        return None
    cells = (unique - unique[0]) / gap
    return gap if np.abs(cells - np.round(cells)).max() <= GRID_TOLERANCE else None


def _multiple(gap: float, step: float) -> float:
    """Whole multiples of ``gap`` at or below ``step``: the grid's own step whenever that is less than twice as fine."""
    return gap * max(1, math.floor(step / gap))


def native_grid(values: np.ndarray, step: float, *, through_zero: bool = False) -> tuple[float, float] | None:
    """(step, origin) of a uniform grid ``values`` already lie on, in whole multiples up to ``step``; else None.

    Scenes decoded from other compressed formats hold attributes on such grids (8-bit colours and alphas of `.splat`
    and `.spz`, their 1/16 log-scale steps). Quantising on the same grid keeps those values exact, at the cost of
    their own entropy, where a foreign grid would add error and spend bits on precision the scene never had.
    ``through_zero``: the grid must contain 0 (the origin returned is then 0).
    """
    unique = np.unique(values).astype(np.float64, copy=False)
    gap = _grid_step(unique, MAX_GRID_LEVELS)
    if gap is None:
        return None
    origin = float(unique[0])
    if through_zero:
        if abs(origin / gap - round(origin / gap)) > GRID_TOLERANCE:
            return None
        origin = 0.0
    return _multiple(gap, step), origin


def _fit_grid(columns: list[np.ndarray], gap: float) -> tuple[float, np.ndarray]:
    """One step and an origin per column [3] for the grids the sorted distinct float32 ``columns`` lie on, near ``gap``.

    A float32 value stands for the interval of reals that round to it; a grid whose points origin + q * step (in
    float64, as ``PositionCodec.decode`` computes them) fall inside every value's interval decodes the values exactly.
    The step estimated from the span and the columns' minima fit grids through zero; grids shifted off zero (an .spz
    decode moved by a fraction of a cell) miss their values near zero by far more than those values' float32
    spacing. Then the step is found by bisection, as the worst shortfall between the origins some value needs and
    those another allows is convex in the step, and each origin is the middle of the origins that step allows (the
    column's minimum when that lies inside).
    """
    axes = []
    for u in columns:
        v = u.astype(np.float64)
        lo = (v + np.nextafter(u, -np.inf).astype(np.float64)) / 2
        hi = (v + np.nextafter(u, np.inf).astype(np.float64)) / 2
        axes.append((np.round((v - v[0]) / gap), lo, hi))

    def allowed(step: float) -> list[tuple[float, float, float]]:
        """Per column: the origins its values allow, from low to high, and the slope of low - high in the step."""
        out = []
        for q, lo, hi in axes:
            need, allow = lo - q * step, hi - q * step
            i, j = int(need.argmax()), int(allow.argmin())
            out.append((float(need[i]), float(allow[j]), float(q[j] - q[i])))
        return out

    def shortfall(step: float) -> tuple[float, float]:
        """The worst column's low - high (no origin fits while it is positive) and its slope in the step."""
        return max((need - allow, slope) for need, allow, slope in allowed(step))

    def decodes(step: float, origin: list[float]) -> bool:
        return all(np.array_equal((o + q * step).astype(np.float32), u) for o, (q, *_), u in zip(origin, axes, columns))

    step, origin = gap, [float(u[0]) for u in columns]
    if not decodes(step, origin):
        # The first and last value of each column bound the step; the worst shortfall is least in between.
        low = min((lo[-1] - hi[0]) / q[-1] for q, lo, hi in axes)
        high = max((hi[-1] - lo[0]) / q[-1] for q, lo, hi in axes)
        while low < (step := (low + high) / 2) < high:
            slope = shortfall(step)[1]
            if slope == 0:
                break
            low, high = (low, step) if slope > 0 else (step, high)
        origin = [o if lo < o < hi else (lo + hi) / 2 for o, (lo, hi, _) in zip(origin, allowed(step))]
    return step, np.array(origin)


def _position_grid(values: np.ndarray, step: float) -> tuple[float, np.ndarray] | None:
    """(step, origin [3]) of one grid that every axis of ``values`` [N, 3] (float32) already lies on, in whole
    multiples up to ``step``, each origin the grid point at its axis' minimum; None unless the axes' grids agree.

    Positions of scenes decoded from .spz sit on a grid of 1/4096 (or another power of two) per axis, each possibly
    shifted off zero. An axis holding a single value has no grid of its own: such positions keep the step asked for.
    """
    columns = [np.unique(values[:, a]) for a in range(3)]
    gaps = [_grid_step(c.astype(np.float64), MAX_POSITION_GRID_LEVELS) for c in columns]
    steps = [g for g in gaps if g is not None]
    if len(steps) < 3 or max(steps) - min(steps) > GRID_AGREEMENT * min(steps):
        return None
    gap, origin = _fit_grid(columns, sum(steps) / 3)
    return _multiple(gap, step), origin


def _decorrelate(q: np.ndarray) -> np.ndarray:
    """RGB symbols [..., 3] -> (G, R - G, B - G): an exact integer transform; colour channels move together."""
    return np.stack([q[..., 1], q[..., 0] - q[..., 1], q[..., 2] - q[..., 1]], axis=-1)


def _correlate(d: np.ndarray) -> np.ndarray:
    """Inverse of ``_decorrelate``."""
    return np.stack([d[..., 1] + d[..., 0], d[..., 0], d[..., 2] + d[..., 0]], axis=-1)


def _table(rows: np.ndarray) -> np.ndarray:
    """Symbol rows [M, ..., 3] as an entropy table, one row each (``entropy`` also tries every symbol as one
    column)."""
    return rows.reshape(len(rows), math.prod(rows.shape[1:]))  # -1 cannot stand for the width of no rows


def _smaller(q: np.ndarray, classes: np.ndarray | None) -> tuple[bytes, bool]:
    """The smaller coding of RGB symbol rows ``q`` [N, ..., 3], a table per class (``_table``): as they are, or
    decorrelated (``_smallest``), and whether decorrelated."""
    payload, params = _smallest([({"decorrelate": mixed}, way) for mixed, way in zip((False, True), _both_ways(q))],
                                classes)  # fmt: skip
    return payload, params["decorrelate"]


def _smaller_bits(q: np.ndarray, classes: np.ndarray | None, level: int = ESTIMATE_LEVEL) -> float:
    """About the bits of ``_smaller(q, classes)``'s coding (its zstd streams at ``level``); a large table's two
    ways side by side (``table_bits`` codes on one thread)."""
    def bits(rows: np.ndarray) -> float:
        return groups_bits(rows, classes, lambda r: table_bits(_table(r), level))

    both = _both_ways(q)
    return min(coding_pool().map(bits, both) if q.size >= PARALLEL_SYMBOLS else map(bits, both))


def _smallest(options: list[tuple[dict[str, Any], np.ndarray]],
              classes: np.ndarray | None) -> tuple[bytes, dict[str, Any]]:  # fmt: skip
    """The smallest coding (``_grid_payload``) of symbol rows [N, ...] among ``options`` (each with the params that
    undo its transform)."""
    best: tuple[bytes, dict[str, Any]] | None = None
    for params, q in options:
        payload = _grid_payload(q, classes)
        if best is None or len(payload) < len(best[0]):
            best = (payload, params)
    assert best is not None
    return best


def _predictions(q: np.ndarray, neighbours: Neighbours | None) -> list[tuple[dict[str, Any], np.ndarray]]:
    """Symbol rows ``q`` [N, C] as they are, and less their predictions from the neighbours an encoder tries."""
    plain: list[tuple[dict[str, Any], np.ndarray]] = [({"predict": 0}, q)]
    return plain if neighbours is None else plain + [({"predict": c}, neighbours.residuals(q, c)) for c in COUNTS]


def _unpredicted(q: np.ndarray, params: dict[str, Any], neighbours: Neighbours | None, codec: str) -> np.ndarray:
    """Inverse of ``_predictions``' transform named by ``params`` (absent in archives before format version 5)."""
    count = params.get("predict", 0)
    if not count:
        return q
    if neighbours is None:
        raise ArchiveError("bad_header", f"{codec}: symbols predicted from neighbours, but no positions to find them")
    return neighbours.restore(q, count, MAX_LEVELS, codec)


def _predict_keys(params: dict[str, Any], keys: set[str], codec: str) -> None:
    """``_keys`` with ``predict`` optional, and checked where present."""
    _keys(params, keys | ({"predict"} if "predict" in params else set()), codec)
    if "predict" in params:
        check_count(params["predict"], codec)


def _both_ways(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The symbol rows ``q`` as they are and decorrelated."""
    return q, _decorrelate(q)


def _read(codec: str, c: int) -> Callable[[bytes, int], np.ndarray]:
    """A reader of one class's table of ``c`` columns (``classes.decode_groups``)."""
    return lambda part, m: _symbols(part, m, c, codec)


def _grid_bits(q: np.ndarray, classes: np.ndarray | None) -> float:
    return groups_bits(q, classes, table_bits)


def _grid_payload(q: np.ndarray, classes: np.ndarray | None) -> bytes:
    """Symbol rows ``q`` [N, ...] coded, a table per class (``_table``)."""
    return encode_groups(q, classes, lambda rows: encode_table(_table(rows)))


def _flag(params: dict[str, Any], key: str, codec: str) -> None:
    if type(params.get(key)) is not bool:
        raise ArchiveError("bad_header", f"{codec}: parameter {key}={params.get(key)!r:.40} must be true or false")


def _symbols(payload: bytes, n: int, c: int, codec: str) -> np.ndarray:
    table = decode_table(payload, n, c, codec)
    if table.size and max(-int(table.min()), int(table.max())) >= MAX_LEVELS:
        raise ArchiveError("corrupt_section", f"{codec}: a symbol lies beyond {MAX_LEVELS} grid cells")
    return table


@dataclass(frozen=True)
class PositionCodec:
    """Positions [N, 3] on a cube grid of ``step`` world units from the bounding box's low corner, or on the grid all
    three axes already lie on (``_position_grid``), in whole multiples up to ``step``."""

    step: float
    name: str = field(default="q-pos", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _quantise(self, values: np.ndarray, classes: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float]:
        x = _finite(values, self.name)
        step, origin = _position_grid(values, self.step) or (self.step, x.min(axis=0) if len(x) else np.zeros(3))
        cells = _grid(x, origin, step * multipliers(classes, len(x))[:, None], self.name)
        return cells, np.asarray(origin, dtype=np.float64), float(step)

    def cells(self, values: np.ndarray, classes: np.ndarray | None = None) -> np.ndarray:
        """The grid cells [N, 3] int64 ``encode`` puts ``values`` [N, 3] in, each on its class's grid
        (``order.coding_order`` sorts by them)."""
        return self._quantise(values, classes)[0]

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        q, origin, step = self._quantise(values, classes)
        payload, morton = _grid_payload(q, classes), False
        if fits(q):
            gaps = encode_groups(q, classes, lambda cells: encode_codes(interleave(cells)))
            payload, morton = (gaps, True) if len(gaps) < len(payload) else (payload, False)
        params = {"origin": [float(o) for o in origin], "step": step, "morton": morton}
        return EncodedSection(payload, _raw_length(values.shape), params)

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        q, origin, step = self._quantise(values, classes)
        bits = _grid_bits(q, classes)
        if fits(q):
            bits = min(bits, groups_bits(q, classes, lambda cells: codes_bits(interleave(cells))))
        return Estimate(bits, _positions(q, origin, step * multipliers(classes, len(q))[:, None]))

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        # Archives written before Morton gap coding carry no "morton" flag: their positions are a table.
        _keys(params, {"origin", "step", "morton"} if "morton" in params else {"origin", "step"}, self.name)
        if "morton" in params:
            _flag(params, "morton", self.name)
        _step(params, self.name)
        origin = params["origin"]
        if not isinstance(origin, list) or len(origin) != 3:
            raise ArchiveError("bad_header", f"{self.name}: origin must be 3 numbers, got {origin!r:.60}")
        for value in origin:
            _origin(value, self.name)
        _check_raw(self.name, shape, raw_length)

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n = shape[0]
        if params.get("morton"):
            q = decode_groups(payload, classes, n, lambda part, m: deinterleave(decode_codes(part, m, self.name)),
                              self.name)  # fmt: skip
        else:
            q = decode_groups(payload, classes, n, _read(self.name, 3), self.name)
        return _positions(q, params["origin"], params["step"] * multipliers(classes, n)[:, None])


def _positions(q: np.ndarray, origin: Any, step: float | np.ndarray) -> np.ndarray:
    """Positions [N, 3] float32 of grid cells ``q`` [N, 3] (``origin`` [3]; ``step`` one, or [N, 1])."""
    return (np.asarray(origin) + q * step).astype(np.float32)


@dataclass(frozen=True)
class RotationCodec:
    """Quaternions [N, 4] (w, x, y, z) as the largest component's index and the other three on a ``step`` grid."""

    step: float
    name: str = field(default="q-rot", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _table(self, values: np.ndarray, classes: np.ndarray | None) -> np.ndarray:
        """[N, 4]: each quaternion's largest component's index and the other three's grid cells."""
        q = _finite(values, self.name)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
        largest = np.abs(q).argmax(axis=1)
        q *= np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
        others = q[~np.eye(4, dtype=bool)[largest]].reshape(len(q), 3)
        steps = self.step * multipliers(classes, len(q))[:, None]
        return np.concatenate([largest[:, None], _grid(others, 0.0, steps, self.name)], axis=1)

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        payload = _grid_payload(self._table(values, classes), classes)
        return EncodedSection(payload, _raw_length(values.shape), {"step": float(self.step)})

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        table = self._table(values, classes)
        steps = self.step * multipliers(classes, len(table))[:, None]
        return Estimate(_grid_bits(table, classes), _quaternions(table, steps))

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        _keys(params, {"step"}, self.name)
        _step(params, self.name)
        _check_raw(self.name, shape, raw_length)

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n = shape[0]
        table = decode_groups(payload, classes, n, _read(self.name, 4), self.name)
        largest = table[:, 0]
        if n and (largest.min() < 0 or largest.max() > 3):
            raise ArchiveError("corrupt_section", f"{self.name}: largest-component index outside 0..3")
        return _quaternions(table, params["step"] * multipliers(classes, n)[:, None])


def _quaternions(table: np.ndarray, step: float | np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] float32 of a ``RotationCodec`` table [N, 4] (largest index in 0..3; ``step`` one, or
    [N, 1])."""
    n, largest = len(table), table[:, 0]
    others = np.clip(table[:, 1:] * step, -SQRT1_2, SQRT1_2)
    squares = (others**2).sum(axis=1)
    # Rounding can push the three past unit length: rescale them so the quaternion stays unit.
    scale = np.where(squares > 1.0, 1.0 / np.sqrt(np.maximum(squares, 1e-30)), 1.0)
    others *= scale[:, None]
    q = np.empty((n, 4))
    mask = np.eye(4, dtype=bool)[largest]
    q[~mask] = others.reshape(-1)
    q[mask] = np.sqrt(np.clip(1.0 - (others**2).sum(axis=1), 0.0, 1.0))
    return q.astype(np.float32)


@dataclass(frozen=True)
class ScalarGridCodec:
    """Any float attribute [N, ...] on a ``step`` grid from its minimum (log-scales)."""

    step: float
    name: str = field(default="q-grid", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _quantise(self, values: np.ndarray, classes: np.ndarray | None) -> tuple[np.ndarray, float, float, np.ndarray]:
        """Cells [N, C], origin, step, and each Gaussian's step [N, 1]."""
        x = _finite(values, self.name).reshape(len(values), -1)
        step, origin = native_grid(x, self.step) or (self.step, float(x.min()) if x.size else 0.0)
        steps = step * multipliers(classes, len(x))[:, None]
        return _grid(x, origin, steps, self.name), origin, step, steps

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        q, origin, step, _ = self._quantise(values, classes)
        payload, predict = _smallest(_predictions(q, neighbours), classes)
        return EncodedSection(payload, _raw_length(values.shape), {"origin": origin, "step": step} | predict)

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        q, origin, _, steps = self._quantise(values, classes)
        return Estimate(_grid_bits(q, classes), _on_grid(q, origin, steps).reshape(values.shape))

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        _predict_keys(params, {"origin", "step"}, self.name)
        _step(params, self.name)
        _origin(params.get("origin"), self.name)
        _check_raw(self.name, shape, raw_length)

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n, c = shape[0], int(np.prod(shape[1:], dtype=np.int64))
        q = _unpredicted(decode_groups(payload, classes, n, _read(self.name, c), self.name), params, neighbours,
                         self.name)  # fmt: skip
        return _on_grid(q, params["origin"], params["step"] * multipliers(classes, n)[:, None]).reshape(shape)


def _on_grid(q: np.ndarray, origin: float, step: float | np.ndarray) -> np.ndarray:
    """float32 values of grid cells ``q`` [N, ...] (``step`` one, or one per row [N, 1])."""
    return (origin + q * step).astype(np.float32)


@dataclass(frozen=True)
class OpacityCodec:
    """Opacity logits [N] quantised as alpha = sigmoid(logit) on a ``step`` grid in [0, 1]."""

    step: float
    name: str = field(default="q-alpha", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _quantise(self, values: np.ndarray, classes: np.ndarray | None) -> tuple[np.ndarray, float, np.ndarray]:
        """Alpha cells [N, 1], the step, and each Gaussian's step [N]."""
        alpha = 1.0 / (1.0 + np.exp(-_finite(values, self.name)))
        step, _ = native_grid(alpha, self.step, through_zero=True) or (self.step, 0.0)
        steps = step * multipliers(classes, len(alpha))
        return _grid(alpha[:, None], 0.0, steps[:, None], self.name), step, steps

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        q, step, _ = self._quantise(values, classes)
        payload, predict = _smallest(_predictions(q, neighbours), classes)
        return EncodedSection(payload, _raw_length(values.shape), {"step": step} | predict)

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        q, _, steps = self._quantise(values, classes)
        return Estimate(_grid_bits(q, classes), _logits(q[:, 0], steps))

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        _predict_keys(params, {"step"}, self.name)
        if not 0 < _step(params, self.name) <= 1:
            raise ArchiveError("bad_header", f"{self.name}: step {params['step']} outside (0, 1]")
        _check_raw(self.name, shape, raw_length)

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n = shape[0]
        q = _unpredicted(decode_groups(payload, classes, n, _read(self.name, 1), self.name), params, neighbours,
                         self.name)[:, 0]  # fmt: skip
        return _logits(q, params["step"] * multipliers(classes, n))


def _logits(q: np.ndarray, step: float | np.ndarray) -> np.ndarray:
    """Opacity logits [N] float32 of alpha cells ``q`` [N] (``step`` one, or [N]), within what the PLY reader keeps."""
    lo, hi = 1.0 / (1.0 + math.exp(-OPACITY_LOGIT_MIN)), 1.0 / (1.0 + math.exp(-OPACITY_LOGIT_MAX))
    alpha = np.clip(q * step, lo, hi)
    return np.log(alpha / (1.0 - alpha)).astype(np.float32)


@dataclass(frozen=True)
class ShDcCodec:
    """DC colour coefficients [N, 3] on a ``step`` grid (around zero, or on the grid they already lie on)."""

    step: float
    name: str = field(default="q-dc", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _quantise(self, values: np.ndarray, classes: np.ndarray | None) -> tuple[np.ndarray, float, float, np.ndarray]:
        """Cells [N, 3], origin, step, and each Gaussian's step [N, 1]."""
        x = _finite(values, self.name)
        step, origin = native_grid(x, self.step) or (self.step, 0.0)
        steps = step * multipliers(classes, len(x))[:, None]
        return _grid(x, origin, steps, self.name), origin, step, steps

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        q, origin, step, _ = self._quantise(values, classes)
        options = [({"decorrelate": mixed} | predict, rows) for mixed, way in zip((False, True), _both_ways(q))
                   for predict, rows in _predictions(way, neighbours)]  # fmt: skip
        payload, params = _smallest(options, classes)
        return EncodedSection(payload, _raw_length(values.shape), {"origin": origin, "step": step} | params)

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        q, origin, _, steps = self._quantise(values, classes)
        return Estimate(_smaller_bits(q, classes), _on_grid(q, origin, steps))

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        _predict_keys(params, {"origin", "step", "decorrelate"}, self.name)
        _step(params, self.name)
        _origin(params.get("origin"), self.name)
        _flag(params, "decorrelate", self.name)
        _check_raw(self.name, shape, raw_length)

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n = shape[0]
        q = decode_groups(payload, classes, n, _read(self.name, 3), self.name)
        q = _unpredicted(q, params, neighbours, self.name)
        q = _correlate(q) if params["decorrelate"] else q
        return _on_grid(q, params["origin"], params["step"] * multipliers(classes, n)[:, None])


def check_bands(params: dict[str, Any], degree: int, codec: str) -> None:
    """ArchiveError unless ``params`` hold a positive step and a decorrelation flag for each of ``degree`` SH bands."""
    steps, mixed = params["steps"], params["decorrelate"]
    if not isinstance(steps, list) or len(steps) != degree or not isinstance(mixed, list) or len(mixed) != degree:
        raise ArchiveError("bad_header", f"{codec}: steps {steps!r:.60} and decorrelate for SH degree {degree}")
    for s, m in zip(steps, mixed):
        _step({"step": s}, codec)
        _flag({"decorrelate": m}, "decorrelate", codec)


def band_slices(degree: int) -> list[slice]:
    """Rows of ``sh_rest`` [N, K, 3] that hold band l = 1..degree."""
    return [slice(lvl * lvl - 1, (lvl + 1) * (lvl + 1) - 1) for lvl in range(1, degree + 1)]


@dataclass(frozen=True)
class ShRestCodec:
    """Higher SH [N, K, 3]: one grid step per band, a per-Gaussian degree, only the bands up to it stored.

    ``steps`` lists the step of band 1, 2, 3; a scene of lower degree uses the first ones. Each band's symbols are
    a table of one row per Gaussian (params ``layout`` "rows"), so its coefficients can each take a histogram of
    their own; archives before format version 4 hold a band's symbols as one column, and are read as such.
    """

    steps: tuple[float, ...]
    name: str = field(default="q-sh", init=False)
    kind: SectionKind = field(default="float32", init=False)

    def _quantise(self, values: np.ndarray, classes: np.ndarray | None) -> tuple[list[np.ndarray], np.ndarray]:
        """Each band's symbols [N, width, 3] and each Gaussian's degree [N]: its highest band with a non-zero one."""
        n, k, _ = values.shape
        degree = {0: 0, 3: 1, 8: 2, 15: 3}[k]
        _check_finite(values, self.name)  # each band widens to float64 on its own (``_grid``), not all at once
        if len(self.steps) < degree:
            raise ValueError(f"{self.name}: {len(self.steps)} band steps for SH degree {degree}")
        scale = multipliers(classes, n)[:, None, None]
        bands = [_grid(values[:, s, :], 0.0, st * scale, self.name) for s, st in zip(band_slices(degree), self.steps)]
        present = np.stack([b.any(axis=(1, 2)) for b in bands], axis=1) if bands else np.zeros((n, 0), dtype=bool)
        per = np.zeros(n, dtype=np.int64)
        if degree:
            per = np.where(present.any(axis=1), degree - np.argmax(present[:, ::-1], axis=1), 0)
        return bands, per

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        bands, per = self._quantise(values, classes)
        bits = table_bits(per[:, None]) + 32.0 * (len(bands) + 1)
        decoded = np.zeros(values.shape, dtype=np.float32)
        for lvl, (band, rows, step) in enumerate(zip(bands, band_slices(len(bands)), self.steps), start=1):
            keep = per >= lvl
            # zstd's matches find much of what a band's coefficients hold: coded at its own level
            bits += _smaller_bits(band[keep], None if classes is None else classes[keep], CODING_LEVEL)
            decoded[:, rows, :] = _sh_values(band, step, classes)
        return Estimate(bits, decoded)

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        bands, per = self._quantise(values, classes)
        degree = len(bands)
        parts, mixed = [encode_table(per[:, None])], []
        for lvl, band in enumerate(bands, start=1):
            keep = per >= lvl
            coded, flag = _smaller(band[keep], None if classes is None else classes[keep])
            parts.append(coded)
            mixed.append(flag)
        payload = join_parts(parts)
        params = {"steps": [float(s) for s in self.steps[:degree]], "decorrelate": mixed, "layout": "rows"}
        return EncodedSection(payload, _raw_length(values.shape), params)

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        _keys(params, {"steps", "decorrelate"} | ({"layout"} if "layout" in params else set()), self.name)
        if params.get("layout", "rows") != "rows":  # absent: written before format version 4
            raise ArchiveError("bad_header", f"{self.name}: layout {params['layout']!r:.40}, expected 'rows'")
        check_bands(params, {0: 0, 3: 1, 8: 2, 15: 3}[shape[1]], self.name)
        _check_raw(self.name, shape, raw_length)

    def parts(self, payload: bytes, params: dict[str, Any]) -> dict[str, int]:
        """Bytes of a checked payload's parts: the Gaussians' degrees, then each band."""
        parts = split_parts(payload, len(params["steps"]) + 1, self.name)
        return {"sh_degrees": 4 + len(parts[0])} | {f"sh_band_{b}": 4 + len(p) for b, p in enumerate(parts[1:], 1)}

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        n, k, _ = shape
        degree = len(params["steps"])
        parts = split_parts(payload, degree + 1, self.name)
        per = decode_table(parts[0], n, 1, self.name)[:, 0]
        rows_layout = params.get("layout") == "rows"  # before format version 4: each band's symbols in one column
        if n and (per.min() < 0 or per.max() > degree):
            raise ArchiveError("corrupt_section", f"{self.name}: a Gaussian's degree lies outside 0..{degree}")
        out = np.zeros((n, k, 3), dtype=np.float32)
        for lvl, (rows, step) in enumerate(zip(band_slices(degree), params["steps"]), start=1):
            keep = per >= lvl
            width = rows.stop - rows.start
            kept = None if classes is None else classes[keep]

            def read(part: bytes, m: int, w: int = width) -> np.ndarray:
                shape = (m, w * 3) if rows_layout else (m * w * 3, 1)
                return _symbols(part, *shape, self.name).reshape(m, w, 3)

            q = decode_groups(parts[lvl], kept, int(keep.sum()), read, self.name)
            values = _sh_values(_correlate(q) if params["decorrelate"][lvl - 1] else q, step, kept)
            if len(values) == n:  # every Gaussian keeps this band: a slice, not a masked scatter
                out[:, rows, :] = values
            else:
                out[keep, rows, :] = values
        return out


def _sh_values(q: np.ndarray, step: float, classes: np.ndarray | None) -> np.ndarray:
    """float32 coefficients of one band's symbols [M, width, 3] on ``step`` times each row's 2^class."""
    if classes is not None:
        q = q << classes.astype(np.int64)[:, None, None]
    return q.astype(np.float32) * np.float32(step)
