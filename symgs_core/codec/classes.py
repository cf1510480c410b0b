"""Step classes: how much coarser than its sections' steps each stored Gaussian is quantised.

A Gaussian of class c is quantised on steps 2^c times each section's own. The renders depend on the stored Gaussians
very unequally (``pipeline.sensitivity``: on the real scenes the weights of one attribute spread over several orders
of magnitude), and one step per section spends as many bits on a Gaussian the cameras hardly see as on one that
fills the frame. Classes give the Gaussians that matter less coarser steps: on the trained kacytran scene (9k, SH 3)
classes 0..3 code it in 39% fewer bytes than one step per section at the same PSNR on the fitting cameras, 0..1 in
18% fewer; classes up to 5 gain nothing more, and at 6 the renders fall apart (a small Gaussian's log-scale off by
several units is a large one: the sensitivity model is linear, the renders are not).

Each class present is coded as a table of its own (a coarse class's symbols are narrower than a fine one's), in
ascending order of class, so a reader splits a section by the classes it decoded first. The stored set is ordered
by class within each level group (``order.coding_order``): the classes' own section costs a few bytes.

A section may also put every Gaussian on its own step, whatever its class (``OneStep``; the archive's section entry
says ``"classes": false``). Values already on a grid (a scene decoded from a quantised container) are coded exactly
on that grid, and no class can be coarser there without an error no finer step removes: at the fidelity such
scenes are compared at, their positions and log-scales want one step, while rotations, opacity and colour, off
their grids, still gain from classes.

    payload   the classes as an entropy table [N, 1] (``entropy``); params {}; raw length N
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .entropy import decode_table, encode_table
from .errors import ArchiveError
from .section import (
    EncodedSection,
    Estimate,
    RateCodec,
    SectionCodec,
    SectionKind,
    check_params,
    join_parts,
    split_parts,
)

if TYPE_CHECKING:
    from .neighbours import Neighbours

MAX_CLASS = 7  # readers accept classes 0..MAX_CLASS; the pipeline chooses how many it uses


@dataclass(frozen=True)
class StepClassCodec:
    """The classes [N] uint8 as one entropy-coded column (sorted within level groups: runs, a few bytes)."""

    name: str = field(default="classes", init=False)
    kind: SectionKind = field(default="uint8", init=False)

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        if values.ndim != 1 or values.dtype != np.uint8 or (values.size and int(values.max()) > MAX_CLASS):
            raise ValueError(f"{self.name}: classes are uint8 [N] in 0..{MAX_CLASS}, got {values.dtype} {values.shape}")
        return EncodedSection(encode_table(values.astype(np.int64)[:, None]), len(values), {})

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        check_params(self.name, params, {})
        if len(shape) != 1 or raw_length != shape[0]:
            raise ArchiveError("bad_header", f"{self.name}: raw length {raw_length} for shape {shape}")

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        values = decode_table(payload, shape[0], 1, self.name)[:, 0]
        if values.size and (int(values.min()) < 0 or int(values.max()) > MAX_CLASS):
            raise ArchiveError("corrupt_section", f"{self.name}: a class lies outside 0..{MAX_CLASS}")
        return values.astype(np.uint8)


CLASSES = StepClassCodec()


@dataclass(frozen=True)
class OneStep:
    """``codec`` with every Gaussian on the section's own step, its class ignored: what a writer passes for such a
    section (``archive.encode_archive`` writes ``codec`` and marks the section; readers decode it without classes)."""

    codec: RateCodec

    @property
    def name(self) -> str:
        return self.codec.name

    @property
    def kind(self) -> SectionKind:
        return self.codec.kind

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: Neighbours | None = None) -> EncodedSection:  # fmt: skip
        return self.codec.encode(values, neighbours=neighbours)

    def estimate(self, values: np.ndarray, *, classes: np.ndarray | None = None) -> Estimate:
        return self.codec.estimate(values)

    def check(self, shape: tuple[int, ...], params: dict[str, Any], raw_length: int) -> None:
        self.codec.check(shape, params, raw_length)

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict[str, Any], raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: Neighbours | None = None) -> np.ndarray:  # fmt: skip
        return self.codec.decode(payload, shape, params, raw_length, neighbours=neighbours)


def unwrapped(codec: SectionCodec) -> tuple[SectionCodec, bool]:
    """The codec a section is written by, and whether its Gaussians take their step classes."""
    return (codec.codec, False) if isinstance(codec, OneStep) else (codec, True)


def multipliers(classes: np.ndarray | None, n: int) -> np.ndarray:
    """Each Gaussian's step multiplier [N] float64: 2^class (1 without classes)."""
    if classes is None:
        return np.ones(n)
    if classes.shape != (n,):
        raise ValueError(f"classes must have shape ({n},), got {classes.shape}")
    return np.ldexp(1.0, classes.astype(np.int64))


def groups(classes: np.ndarray | None, n: int) -> list[np.ndarray]:
    """Indices of the Gaussians of each class present, ascending class; one group of all without classes."""
    if classes is None or n == 0 or int(classes.min()) == int(classes.max()):
        return [np.arange(n)]
    return [np.flatnonzero(classes == c) for c in np.unique(classes)]


def encode_groups(rows: np.ndarray, classes: np.ndarray | None, code: Callable[[np.ndarray], bytes]) -> bytes:
    """``rows`` [N, ...] coded by ``code`` one class at a time: one stream for one class, else the streams joined."""
    parts = [code(rows[g]) for g in groups(classes, len(rows))]
    return parts[0] if len(parts) == 1 else join_parts(parts)


def groups_bits(rows: np.ndarray, classes: np.ndarray | None, bits: Callable[[np.ndarray], float]) -> float:
    """About the bits of ``encode_groups(rows, classes, code)`` where ``bits`` estimates ``code``."""
    chosen = groups(classes, len(rows))
    return sum(bits(rows[g]) for g in chosen) + (32.0 * len(chosen) if len(chosen) > 1 else 0.0)


def decode_groups(payload: bytes, classes: np.ndarray | None, n: int, read: Callable[[bytes, int], np.ndarray],
                  what: str) -> np.ndarray:  # fmt: skip
    """Inverse of ``encode_groups``: ``read(stream, m)`` gives the [m, ...] rows of one class's stream."""
    chosen = groups(classes, n)
    if len(chosen) == 1:
        return read(payload, n)
    parts = split_parts(payload, len(chosen), what)
    first = read(parts[0], len(chosen[0]))
    out = np.empty((n, *first.shape[1:]), dtype=first.dtype)
    out[chosen[0]] = first
    for g, part in zip(chosen[1:], parts[1:]):
        out[g] = read(part, len(g))
    return out

