"""Whether a scene is as a trainer wrote it or was decoded from a quantised container, told by its own values.

A trainer writes float32 values on no grid: nearly every Gaussian holds a value of each field no other holds. The
containers the web serves store fields on grids: SOG keeps scales and colours as indices into 256-entry codebooks,
`.spz` and `.splat` keep colours, opacities and (in `.splat`) rotations in 8 bits, and compressed PLY keeps every
field on a lattice of 2^8-2^11 steps between each chunk of 256 Gaussians' own minimum and maximum. A scene decoded
from one of them keeps those grids, which the same formats re-encode almost losslessly; a codec benchmark reports
the two kinds apart.
"""

from __future__ import annotations

import numpy as np

from ..scene import GaussianScene

FIELDS = ("scales", "sh_dc", "opacities", "quats", "means")
GRID_VALUES = 4096  # the most distinct values a container's global grid (12 bits) gives a field
CHUNK = 256  # compressed PLY's chunk of Gaussians
CHUNK_BITS = (8, 10, 11)  # the lattices compressed PLY puts between a chunk's minimum and maximum
ON_LATTICE = 0.02  # how near a lattice point, in steps, a decoded float32 value lies
LATTICE_SHARE = 0.5  # share of a field's values on a chunk lattice that names it (off a grid: about 4%)


def container_grid(scene: GaussianScene) -> str | None:
    """The evidence that ``scene`` was decoded from a quantised container (a field on a grid), or None when every
    field holds values on no grid, as a trainer writes them."""
    n = len(scene)
    for name in FIELDS:
        values = getattr(scene, name).detach().to("cpu").double().reshape(n, -1).numpy()
        for c in range(values.shape[1]):
            column = values[:, c]
            distinct = len(np.unique(column))
            if n >= 2 * CHUNK and distinct <= min(GRID_VALUES, n // 4):
                return f"{name}[{c}]: {distinct:,} distinct values among {n:,} Gaussians"
            for bits in CHUNK_BITS:
                share = chunk_lattice_share(column, bits)
                if share >= LATTICE_SHARE:
                    return f"{name}[{c}]: {share:.0%} of values on a {bits}-bit lattice per chunk of {CHUNK}"
    return None


def chunk_lattice_share(column: np.ndarray, bits: int) -> float:
    """The share of ``column``'s values [N] (whole chunks of ``CHUNK`` in file order) that lie on the lattice of
    2^bits - 1 steps between their chunk's minimum and maximum."""
    whole = len(column) // CHUNK * CHUNK
    if whole == 0:
        return 0.0
    chunks = column[:whole].astype(np.float64).reshape(-1, CHUNK)
    low, high = chunks.min(axis=1, keepdims=True), chunks.max(axis=1, keepdims=True)
    steps = (chunks - low) / np.where(high > low, high - low, 1.0) * (2**bits - 1)
    return float(np.mean(np.abs(steps - np.rint(steps)) < ON_LATTICE))
