"""The plane accumulator: a 3-D grid over (normal, offset) with the hemisphere seam handled.

A plane and its flipped twin (-n, -offset) are the same plane, so normals live on one hemisphere (n_z >= 0). The
hemisphere is flattened by Lambert's equal-area projection from the pole, (u, v) = n_xy sqrt(2 / (1 + n_z)): every
normal cell covers the same solid angle and there is no singular pole. The equator (the disc's rim, radius sqrt 2) is
the seam, where n and -n sit at opposite ends of the disc and the votes of one plane would split in two. So the grid
extends a few cells past the rim, and every vote within that band of the equator is cast twice: as itself and as its
flipped twin, which lands just outside the rim next to the votes that came in flipped. Around the seam each plane
then has one contiguous cloud of votes, and the rim cell (cells are centred on the grid's axes) holds them all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..compiled import compiled

_SEAM_CELLS = 3  # width of the band past the equator, in cells; above the smoothing and refinement windows


@dataclass(frozen=True)
class GridSpec:
    cell: float  # side of a normal cell in Lambert units (about radians)
    depth: float  # offset cell, normalised units
    max_offset: float  # offsets beyond +-max_offset are not voted for

    @property
    def seam_z(self) -> float:
        """Votes with n_z below this are also cast flipped."""
        return math.sin(_SEAM_CELLS * self.cell)

    @property
    def half_uv(self) -> int:
        rim = 2.0 * math.sin((math.pi / 2 + _SEAM_CELLS * self.cell) / 2.0)
        return int(math.ceil(rim / self.cell)) + 1

    @property
    def half_g(self) -> int:
        return int(math.ceil(self.max_offset / self.depth))

    @property
    def shape(self) -> tuple[int, int, int]:
        return (2 * self.half_uv + 1, 2 * self.half_uv + 1, 2 * self.half_g + 1)

    def cells(self, normals: Tensor, offsets: Tensor) -> tuple[Tensor, Tensor]:
        """Flat cells [V] of the votes of unit ``normals`` [P, 3] and ``offsets`` [P], and the vote each came from.

        Each plane is canonicalised to n_z >= 0; those near the seam get a second cell for (-n, -offset). Votes
        outside the offset range are dropped.
        """
        sign = torch.where(normals[:, 2] < 0, -1.0, 1.0).to(normals.dtype)
        n = normals * sign[:, None]
        g = offsets * sign
        flat, ok = self._flat(n, g)
        near = torch.nonzero(n[:, 2] < self.seam_z)[:, 0]
        flat_twin, ok_twin = self._flat(-n[near], -g[near])
        source = torch.cat([torch.nonzero(ok)[:, 0], near[ok_twin]])
        return torch.cat([flat[ok], flat_twin[ok_twin]]), source

    def _flat(self, n: Tensor, g: Tensor) -> tuple[Tensor, Tensor]:
        """Flat cells [P] of planes (unit n [P, 3] with n_z > -1, offsets [P]) and whether each is in the grid."""
        iu, iv, ig = self.coords(n, g)
        su, sv, sg = self.shape
        ok = (ig >= 0) & (ig < sg) & (iu >= 0) & (iu < su) & (iv >= 0) & (iv < sv)
        return (iu * sv + iv) * sg + ig, ok

    def coords(self, n: Tensor, g: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Integer cell coordinates of planes (unit n [P, 3] with n_z > -1, offsets [P]), not range-checked."""
        k = torch.rsqrt((0.5 + 0.5 * n[:, 2]).clamp_min(1e-12)) / self.cell  # Lambert: sqrt(2 / (1 + n_z))
        iu = torch.round(n[:, 0] * k).long() + self.half_uv
        iv = torch.round(n[:, 1] * k).long() + self.half_uv
        ig = torch.round(g / self.depth).long() + self.half_g
        return iu, iv, ig

    def unravel(self, flat: Tensor) -> Tensor:
        """Cell coordinates [V, 3] of flat cells [V]."""
        _, sv, sg = self.shape
        return torch.stack([flat // (sv * sg), (flat // sg) % sv, flat % sg], dim=-1)

    def plane(self, coord: Tensor) -> tuple[Tensor, float]:
        """Unit normal [3] (float64) and offset at the centre of cell ``coord`` [3]."""
        c = coord.to(torch.float64).cpu()
        u = (c[0] - self.half_uv) * self.cell
        v = (c[1] - self.half_uv) * self.cell
        r2 = min(float(u * u + v * v), 4.0)
        s = math.sqrt(max(1.0 - r2 / 4.0, 0.0))
        n = torch.stack([u * s, v * s, torch.tensor(1.0 - r2 / 2.0, dtype=torch.float64, device=c.device)])
        return n / n.norm(), float((c[2] - self.half_g) * self.depth)


def smooth(grid: Tensor) -> Tensor:
    """3x3x3 box sum of ``grid`` [A, B, C] (zero outside), as three separable passes."""
    out = grid
    for dim in range(3):
        src = out
        out = src.clone()
        n = src.shape[dim]
        out.narrow(dim, 1, n - 1).add_(src.narrow(dim, 0, n - 1))
        out.narrow(dim, 0, n - 1).add_(src.narrow(dim, 1, n - 1))
    return out


def suppress(grid: Tensor, coord: Tensor, radius: int) -> None:
    """Zero the cells of ``grid`` [A, B, C] within ``radius`` cells of ``coord`` [3] (in place)."""
    lo = [max(int(c) - radius, 0) for c in coord]
    hi = [min(int(c) + radius + 1, s) for c, s in zip(coord, grid.shape, strict=True)]
    grid[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = 0


_SPARSE_RATIO = 64  # below one vote per this many cells, the peaks are found on the occupied cells alone


class VoteIndex:
    """The votes grouped by 2x2x2 block of accumulator cells (a counting sort): the votes of a box of blocks are a
    few slices, found without a pass over all of them, and the per-block counts are the coarse accumulator."""

    def __init__(self, cells: Tensor, spec: GridSpec) -> None:
        self.spec = spec
        self.blocks = tuple((s + 1) // 2 for s in spec.shape)
        self.cells = cells.to(torch.int32).cpu().contiguous().numpy()  # [V] flat cells
        _, sv, sg = spec.shape
        self.starts = np.zeros(math.prod(self.blocks) + 1, dtype=np.int64)  # votes of block b: starts[b]:starts[b+1]
        self.order = np.empty(len(self.cells), dtype=np.int32)  # vote ids, block after block, in vote order
        _block_sort(self.cells, sv, sg, self.blocks[1], self.blocks[2], self.starts, self.order)

    def block_counts(self) -> Tensor:
        """Votes per block [A, B, C] (float32)."""
        return torch.from_numpy(np.diff(self.starts).astype(np.float32).reshape(self.blocks))

    def in_blocks(self, lo: Sequence[int] | np.ndarray, hi: Sequence[int] | np.ndarray) -> np.ndarray:
        """Ids [M] (int32) of the votes in blocks lo..hi (coordinates [3], inclusive, clipped to the grid)."""
        lo = np.clip(np.asarray(lo, dtype=np.int64), 0, None)
        hi = np.minimum(np.asarray(hi, dtype=np.int64), np.asarray(self.blocks) - 1)
        return _gather_blocks(self.starts, self.order, lo, hi, self.blocks[1], self.blocks[2])

    def near(self, coord: Tensor, radius: int) -> Tensor:
        """Ids [M] (int64, ascending) of the votes whose cell is within ``radius`` cells of ``coord`` [3] in every
        coordinate."""
        c = [int(v) for v in coord]
        ids: np.ndarray | Tensor
        ids = np.sort(self.in_blocks([(v - radius) // 2 for v in c], [(v + radius) // 2 for v in c]))
        ids = torch.from_numpy(ids.astype(np.int64))
        cells = self.spec.unravel(torch.from_numpy(self.cells)[ids].long())
        return ids[(cells - torch.tensor(c, device=cells.device)).abs().amax(dim=1) <= radius]


def top_peaks(
    cells: Tensor, spec: GridSpec, count: int, radius: int, index: VoteIndex | None = None
) -> list[tuple[Tensor, int]]:
    """Up to ``count`` peaks of the 3x3x3-smoothed vote counts, strongest first: (cell coordinates [3], votes).

    ``cells`` [V] are flat vote cells (``index``, when given, their ``VoteIndex``). After each peak, the cells within
    ``radius`` of it and of its seam twin (the same plane written as (-n, -offset)) are cleared, so one plane yields
    one peak. Few votes are counted on their occupied cells alone. Many are counted per 2x2x2 block of cells, whose
    smoothed maxima point to where the fine peaks are; each is then found among the votes of its neighbourhood.
    Either way the peak is the maximum of the fine grid's 3x3x3 sums there.
    """
    if cells.numel() == 0 or count <= 0:
        return []
    if cells.numel() * _SPARSE_RATIO < math.prod(spec.shape):
        return _sparse_peaks(cells, spec, count, radius)
    return _blocked_peaks(cells, index or VoteIndex(cells, spec), count, radius)


def _twins(spec: GridSpec, coord: Tensor) -> list[Tensor]:
    """Coordinates of every cell the plane of cell ``coord`` is voted into (two near the seam)."""
    n, g = spec.plane(coord)
    flat, _ = spec.cells(n.float()[None], torch.tensor([g], dtype=torch.float32, device=n.device))
    return [coord.cpu(), *spec.unravel(flat).cpu()]


def _blocked_peaks(cells: Tensor, index: VoteIndex, count: int, radius: int) -> list[tuple[Tensor, int]]:
    spec, shape = index.spec, index.blocks
    smoothed = smooth(index.block_counts())
    block_radius = (radius + 1) // 2
    peaks: list[tuple[Tensor, int]] = []
    for _ in range(4 * count):  # neighbouring blocks may lead to the same fine peak
        flat = int(torch.argmax(smoothed))
        if float(smoothed.view(-1)[flat]) <= 0 or len(peaks) == count:
            break
        block = torch.tensor([flat // (shape[1] * shape[2]), (flat // shape[2]) % shape[1], flat % shape[2]],
                             device=smoothed.device)  # fmt: skip
        near = torch.from_numpy(index.in_blocks((block - 1).tolist(), (block + 1).tolist()).astype(np.int64))
        coord, votes = _sparse_peaks(cells.cpu()[near], spec, 1, radius)[0]
        if all((coord - c).abs().max() > radius for c, _ in peaks):
            peaks.append((coord, votes))
        suppress(smoothed, block, 1)
        for twin in _twins(spec, coord):
            suppress(smoothed, twin // 2, block_radius)
    return sorted(peaks, key=lambda p: -p[1])


@compiled
def _block_sort(cells, sv, sg, bv, bg, starts, order):  # noqa: ANN001, ANN202
    """Counting sort of the votes (flat cells [V]) by 2x2x2 block: starts [blocks + 1] (zeros in), order [V]."""
    block = np.empty(cells.shape[0], dtype=np.int32)
    for r in range(cells.shape[0]):
        c = cells[r]
        b = ((c // (sv * sg)) // 2 * bv + (c // sg) % sv // 2) * bg + c % sg // 2
        block[r] = b
        starts[b + 1] += 1
    for b in range(1, starts.shape[0]):
        starts[b] += starts[b - 1]
    fill = starts[:-1].copy()
    for r in range(cells.shape[0]):
        order[fill[block[r]]] = r
        fill[block[r]] += 1


@compiled
def _gather_blocks(starts, order, lo, hi, bv, bg):  # noqa: ANN001, ANN202
    """The ids of the votes of blocks lo..hi [3] (inclusive, inside the grid), block after block."""
    total = 0
    for a in range(lo[0], hi[0] + 1):
        for b in range(lo[1], hi[1] + 1):
            first = (a * bv + b) * bg
            total += starts[first + hi[2] + 1] - starts[first + lo[2]]
    out = np.empty(total, dtype=np.int32)
    k = 0
    for a in range(lo[0], hi[0] + 1):
        for b in range(lo[1], hi[1] + 1):
            first = (a * bv + b) * bg
            for r in range(starts[first + lo[2]], starts[first + hi[2] + 1]):
                out[k] = order[r]
                k += 1
    return out


def _sparse_peaks(cells: Tensor, spec: GridSpec, count: int, radius: int) -> list[tuple[Tensor, int]]:
    occupied, counts = torch.unique(cells.long(), return_counts=True)  # sorted
    coords = spec.unravel(occupied)  # [K, 3]
    device = cells.device
    _, sv, sg = spec.shape
    step = torch.tensor([-1, 0, 1], device=device)
    offsets = torch.cartesian_prod(step, step, step)  # [27, 3]
    neighbour = coords[None] + offsets[:, None]  # [27, K, 3]
    inside = ((neighbour >= 0) & (neighbour < torch.tensor(spec.shape, device=device))).all(dim=-1)
    flat = occupied[None] + ((offsets[:, 0] * sv + offsets[:, 1]) * sg + offsets[:, 2])[:, None]  # [27, K]
    pos = torch.searchsorted(occupied, flat.reshape(-1)).clamp_max(occupied.numel() - 1).reshape(flat.shape)
    hit = inside & (occupied[pos] == flat)
    smoothed = torch.where(hit, counts[pos], torch.zeros_like(pos)).sum(dim=0)
    peaks = []
    for _ in range(count):
        best = int(torch.argmax(smoothed))
        votes = int(smoothed[best])
        if votes <= 0:
            break
        coord = coords[best]
        peaks.append((coord.cpu(), votes))
        for c in _twins(spec, coord):
            near = (coords - c.to(device)).abs().amax(dim=1) <= radius
            smoothed[near] = 0
    return peaks
