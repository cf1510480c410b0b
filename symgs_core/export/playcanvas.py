"""PlayCanvas compressed PLY (`.compressed.ply`): writer and reader of the layout PlayCanvas tools write and read.

Gaussians in chunks of 256 (``compressed_ply_order``). Element ``chunk`` (float32 each): min/max of x, y, z, of
the three log-scales (clamped to +-20) and of the three colours r, g, b = dc * C0 + 0.5.

Element ``vertex`` (uint32 each): ``packed_position`` and ``packed_scale`` as 11-10-11 bit unorms in the chunk's
box (x in the top bits), ``packed_rotation`` as the largest component's index (top 2 bits) and the other three
components of the unit quaternion (w, x, y, z order, sign flipped so the largest is positive) as 10-bit unorms of
q * sqrt2/2 + 0.5, ``packed_color`` as 8-bit unorms of r, g, b in the chunk's range and of the opacity, top byte
first. Optional element ``sh`` (uchar ``f_rest_i``, channel-major as in graphdeco PLY): trunc((v / 8 + 0.5) * 256),
clamped.
No entropy coding; axes as the graphdeco PLY (RDF). The reader takes what PlayCanvas' writers have written: the
elements' properties in any order, and chunks without colour ranges (earlier writers: the colours in 0..1 as they
are); ``ply.read_scene`` reads uploads in this layout through it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..ply import OPACITY_LOGIT_MAX, OPACITY_LOGIT_MIN
from ..ply_header import (
    CHUNK,
    CHUNK_COLOURS,
    CHUNK_RANGES,
    MAX_HEADER_BYTES,
    PACKED,
    PlyError,
    PlyHeader,
    check_header,
)
from ..scene import GaussianScene

C0 = 0.28209479177387814


def compressed_ply_order(scene: GaussianScene) -> torch.Tensor:
    """The order [N] in which ``write_compressed_ply`` stores the Gaussians: the leaves of a binary split of their
    centres into runs of ``CHUNK`` (the last one shorter), so that each chunk's box, and with it the step of its
    positions, is small.

    Each split cuts one axis's sorted centres at a multiple of ``CHUNK`` in the middle half (so the depth stays
    logarithmic) where the two sides' Gaussians times their boxes' summed extents is least: a position's error is its
    chunk's extent over 2^11 per axis. PlayCanvas' writers store Morton order instead, whose chunks straddle jumps
    of the curve: at the same bytes this order's exports are up to 1.4 dB closer to the scene (BENCHMARKS.md,
    "Exports"), for about 2 s per million Gaussians where Morton order takes 0.1 s. A far outlier still widens the
    box of the chunk it shares with 255 others (the format's chunking)."""
    means = scene.means.detach().cpu().float().numpy()  # only to compare boxes
    left_side = np.zeros(len(means), dtype=bool)
    # Each node: per axis, its Gaussians in that axis's order and their centres in the same order, so that a split
    # reads and partitions them in sequence instead of gathering from the whole scene.
    by_axis = [np.argsort(means[:, a], kind="stable") for a in range(3)]
    leaves, todo = [], [[(order, means[order]) for order in by_axis]]
    while todo:
        node = todo.pop()
        count = len(node[0][0])
        if count <= CHUNK:
            leaves.append(node[0][0])
            continue
        chunks = -(-count // CHUNK)
        # The left side's count in chunks, within the middle half: 1 .. chunks - 1, so both sides hold some.
        cuts = np.arange(max(1, chunks // 4), max(2, 3 * chunks // 4 + 1))
        starts = np.arange(0, count, CHUNK)
        choices = []
        for axis, (_, p) in enumerate(node):
            low, high = np.minimum.reduceat(p, starts), np.maximum.reduceat(p, starts)  # per chunk-sized run
            lo, hi = np.minimum.accumulate(low), np.maximum.accumulate(high)
            rlo, rhi = np.minimum.accumulate(low[::-1])[::-1], np.maximum.accumulate(high[::-1])[::-1]
            left = cuts * CHUNK
            cost = (hi[cuts - 1] - lo[cuts - 1]).sum(1) * left + (rhi[cuts] - rlo[cuts]).sum(1) * (count - left)
            i = int(cost.argmin())
            choices.append((float(cost[i]), axis, int(left[i])))
        _, axis, cut = min(choices)
        left_side[node[axis][0][:cut]] = True
        masks = [left_side[order] for order, _ in node]
        left_side[node[axis][0][:cut]] = False
        # The left side is taken first, so only the last leaf may be short.
        todo.append([(order[~m], p[~m]) for (order, p), m in zip(node, masks)])
        todo.append([(order[m], p[m]) for (order, p), m in zip(node, masks)])
    return torch.from_numpy(np.concatenate(leaves))


def _unorm(x: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(x * top + 0.5), 0, top).astype(np.uint32)


def _chunk_bounds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max [C, D] of ``values`` [N, D], the last chunk padded with its last row."""
    n = len(values)
    chunks = -(-n // CHUNK)
    padded = np.concatenate([values, np.repeat(values[-1:], chunks * CHUNK - n, axis=0)]) if n else values
    blocks = padded.reshape(chunks, CHUNK, -1)
    return blocks.min(axis=1), blocks.max(axis=1)


def _normalize(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``values`` [N, D] in their chunk's [lo, hi] [C, D] as 0..1 (0 for degenerate ranges)."""
    idx = np.arange(len(values)) // CHUNK
    lo, hi = lo[idx], hi[idx]
    span = hi - lo
    # Only an empty range is degenerate: the float32 bounds hold any other, so a scene in tiny units keeps its
    # shape (PlayCanvas' writers store 0 below a span of 1e-5, collapsing such a scene to one point per chunk).
    t = np.where(span > 0, (values - lo) / np.where(span > 0, span, 1.0), 0.0)
    return np.clip(t, 0.0, 1.0)


def write_compressed_ply(scene: GaussianScene) -> bytes:
    """The `.compressed.ply` bytes of ``scene`` (stored in ``compressed_ply_order``)."""
    if len(scene) == 0:
        raise ValueError("a compressed PLY needs at least one Gaussian")
    if not all(torch.isfinite(v).all() for v in scene.tensors().values()):  # NaN would write arbitrary bytes
        raise ValueError("a compressed PLY stores finite attributes only")
    s = scene.select(compressed_ply_order(scene))
    t = {k: v.detach().cpu().double().numpy() for k, v in s.tensors().items()}
    n, k = len(s), s.sh_rest.shape[1]
    means, scales = t["means"], np.clip(t["scales"], -20.0, 20.0)
    colors = t["sh_dc"] * C0 + 0.5
    (pmin, pmax), (smin, smax), (cmin, cmax) = _chunk_bounds(means), _chunk_bounds(scales), _chunk_bounds(colors)

    def pack111011(unit: np.ndarray) -> np.ndarray:
        return (_unorm(unit[:, 0], 11) << 21) | (_unorm(unit[:, 1], 10) << 11) | _unorm(unit[:, 2], 11)

    q = t["quats"] / np.maximum(np.linalg.norm(t["quats"], axis=1, keepdims=True), 1e-12)
    largest = np.abs(q).argmax(axis=1)
    q = q * np.where(q[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    rotation = largest.astype(np.uint32)
    for i in range(4):
        packed = (rotation << np.uint32(10)) | _unorm(q[:, i] * (np.sqrt(2.0) * 0.5) + 0.5, 10)
        rotation = np.where(largest == i, rotation, packed)
    c = _normalize(colors, cmin, cmax)
    alpha = 0.5 + 0.5 * np.tanh(0.5 * t["opacities"])  # the sigmoid, without overflow for huge logits
    color = (_unorm(c[:, 0], 8) << 24) | (_unorm(c[:, 1], 8) << 16) | (_unorm(c[:, 2], 8) << 8) | _unorm(alpha, 8)
    vertex = np.stack(
        [pack111011(_normalize(means, pmin, pmax)), rotation, pack111011(_normalize(scales, smin, smax)), color], axis=1
    ).astype("<u4")
    chunks = np.concatenate([pmin, pmax, smin, smax, cmin, cmax], axis=1).astype("<f4")
    lines = ["ply", "format binary_little_endian 1.0", "comment Generated by SymGS", f"element chunk {len(chunks)}"]
    lines += [f"property float {p}" for p in CHUNK_RANGES + CHUNK_COLOURS]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in PACKED]
    body = chunks.tobytes() + vertex.tobytes()
    if k:
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * k)]
        rest = t["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k)  # [N, K, 3] -> channel-major
        body += np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8).tobytes()
    return ("\n".join(lines + ["end_header"]) + "\n").encode("ascii") + body


def read_compressed_ply(data: bytes | memoryview, name: str = "scene.compressed.ply") -> GaussianScene:
    """The scene in a `.compressed.ply` file, in file order; PlyError (``ply_header``'s codes) for anything else."""
    header = check_header(bytes(data[:MAX_HEADER_BYTES]), len(data), name=name)
    if header.layout != "compressed":
        raise PlyError("unsupported_format", f"{name}: not a PlayCanvas compressed PLY (no packed properties)")
    return decode_compressed(data, header)


def decode_compressed(data: bytes | memoryview, header: PlyHeader) -> GaussianScene:
    """The scene of a compressed PLY's bytes ``data`` under its checked ``header`` (``layout == "compressed"``):
    each element read by property name, so any order of them, with or without the chunks' colour ranges."""
    rows, pos = {}, header.size
    for e in header.elements:
        kind = {"chunk": "<f4", "vertex": "<u4", "sh": "u1"}[e.name]
        dtype = np.dtype([(prop, kind) for prop, _, _ in e.properties])
        rows[e.name] = np.frombuffer(data, dtype=dtype, count=e.count, offset=pos)
        pos += e.count * dtype.itemsize
    chunk, vertex, n = rows["chunk"], rows["vertex"], header.count
    idx = np.arange(n) // CHUNK

    def ranged(names: tuple[str, ...], unit: np.ndarray) -> np.ndarray:
        """``unit`` [N, 3] in 0..1 placed in each Gaussian's chunk range of the three ``min_*`` then ``max_*``."""
        lo = np.stack([chunk[p] for p in names[:3]], axis=1).astype(np.float64)[idx]
        hi = np.stack([chunk[p] for p in names[3:]], axis=1).astype(np.float64)[idx]
        return lo * (1 - unit) + hi * unit

    def unorm(v: np.ndarray, bits: int) -> np.ndarray:
        return (v & ((1 << bits) - 1)) / float((1 << bits) - 1)

    def unpack111011(v: np.ndarray) -> np.ndarray:
        return np.stack([unorm(v >> 21, 11), unorm(v >> 11, 10), unorm(v, 11)], axis=1)

    means = ranged(CHUNK_RANGES[:6], unpack111011(vertex["packed_position"].astype(np.int64)))
    scales = ranged(CHUNK_RANGES[6:], unpack111011(vertex["packed_scale"].astype(np.int64)))
    packed = vertex["packed_color"].astype(np.int64)
    colour = np.stack([unorm(packed >> s, 8) for s in (24, 16, 8)], axis=1)
    # Writers before the chunks held colour ranges stored the colours themselves in 0..1.
    colors = ranged(CHUNK_COLOURS, colour) if "min_r" in (chunk.dtype.names or ()) else colour
    alpha = np.clip(unorm(packed, 8), 1e-6, 1 - 1e-6)
    rot = vertex["packed_rotation"].astype(np.int64)
    three = np.stack([(unorm(rot >> s, 10) - 0.5) / (np.sqrt(2.0) * 0.5) for s in (20, 10, 0)], axis=1)
    largest = rot >> 30
    quats = np.zeros((n, 4))
    mask = np.eye(4, dtype=bool)[largest]
    quats[~mask] = three.reshape(-1)
    quats[mask] = np.sqrt(np.clip(1.0 - (three**2).sum(axis=1), 0.0, 1.0))
    k = len(header.rest) // 3
    rest = np.zeros((n, k, 3))
    if k:
        u = np.stack([rows["sh"][p] for p in header.rest], axis=1).astype(np.float64)
        unit = np.where(u == 0, 0.0, np.where(u == 255, 1.0, (u + 0.5) / 256.0))
        rest = ((unit - 0.5) * 8.0).reshape(n, 3, k).transpose(0, 2, 1)

    # Alpha 0 and 255 clamp to the opacity range the PLY reader repairs infinities to, as splat-transform's do.
    logits = np.clip(np.log(alpha / (1 - alpha)), OPACITY_LOGIT_MIN, OPACITY_LOGIT_MAX)

    def f32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return GaussianScene(
        means=f32(means), quats=f32(quats), scales=f32(scales), opacities=f32(logits),
        sh_dc=f32((colors - 0.5) / C0), sh_rest=f32(rest),
    )  # fmt: skip


def load_compressed_ply(path: str | os.PathLike[str]) -> GaussianScene:
    """``read_compressed_ply`` of the file at ``path``."""
    return read_compressed_ply(Path(path).read_bytes())
