"""Niantic's `.spz`: writer and reader of versions 2, 3 (default) and 4, as the format's README documents them.

Packed attributes, in stream order: positions as 24-bit signed fixed point with ``fractional_bits`` (written in the
header; every reader scales by it), alphas u8 = sigmoid(logit) * 255, colours u8 = dc * 0.15 * 255 + 127.5,
log-scales u8 = (s + 10) * 16, rotations (v2: x, y, z of the unit quaternion with w >= 0, u8 each; v3/v4: smallest
three, a 2-bit index and three 1+9-bit sign-magnitude values scaled by 1/sqrt2, packed into a little-endian u32 with
the index on top), SH u8 = round(v * 128) + 128 coefficient-major with the colour channel inner. Axes are RUB: our RDF
scene is stored as (x, -y, -z), with the quaternion's y and z and the SH coefficients odd in y or z negated; readers
flip back.
Containers: v2/v3 gzip one stream, a 16-byte header (magic "NGSP", version, count, degree, fractional bits, flags,
reserved) then the six attribute blocks; v4 a plaintext 32-byte header, a table of (compressed, uncompressed) u64
sizes and one zstd frame per non-empty attribute block.

Where the writer departs from the reference tool's choices, within the format, to keep what our archives decode to:
  * fractional bits: the reference writes 12 (a step of 2^-12 whatever the scene's size), which on a 0.2-unit object
    such as the donut costs more than anything else (49 dB against the decode it was written from). We give
    positions a step of at most 2^-18 of the scene's extent (a quarter of the balanced preset's starting position
    step), never coarser than 2^-12 and within what 24 bits hold at the scene's reach: the donut's export goes to
    21 bits and 53 dB, for 15% more bytes (BENCHMARKS.md, "Exports"). A scene the 24 bits cannot give 2^10 steps
    across (smaller than 2^-14, or small and far from the origin) is refused, as one beyond their reach is, and so
    is one whose Gaussians are mostly smaller than the format's smallest scale (``SMALLEST_LOG_SCALE``).
  * SH at 8 bits: the reference rounds degree 1 to 5 bits and higher bands to 4, a step of 1/8 against the archive's
    SH steps of 1/32 or finer: 41 dB on the kacytran scene (SH 3) where 8 bits give 52 dB for 0.5% more bytes, since
    the decoded SH take few distinct values either way. ``sh1_bits``/``sh_rest_bits`` still choose.
"""

from __future__ import annotations

import gzip
import math
import os
import struct
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..ply import OPACITY_LOGIT_MAX, OPACITY_LOGIT_MIN
from ..scene import SH_REST_COUNT, GaussianScene

MAGIC = 0x5053474E
COLOR_SCALE = 0.15
VERSIONS = (2, 3, 4)
# Log-scales are stored from -10 up: an axis below e^-10 is drawn at that size. A thin axis of a larger Gaussian is
# harmless, but a Gaussian whose largest axis is under ``TINY_FACTOR`` times that is drawn larger and rounder than it
# is, and a scene of such Gaussians renders as blobs. Generated objects against their own renders, by the share of
# such Gaussians: 0% at 48.6 and 54.9 dB, 13% at 44.0, 59% at 33.0, all of them at 13.9 to 31.8 dB (the other
# exports keep 51 to 66 dB). A scene with more than ``MAX_TINY_SHARE`` of them is refused rather than written wrong.
SMALLEST_LOG_SCALE = -10.0
TINY_FACTOR = 3.0
MAX_TINY_SHARE = 0.2
# Sign of each SH rest coefficient (basis index 1..15) under the RDF -> RUB flip of y and z.
SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)
_LEGACY_HEADER = struct.Struct("<IIIBBBB")
_V4_HEADER = struct.Struct("<IIIBBBBI12s")


class SpzError(ValueError):
    """A file that is not a readable `.spz`."""


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def _pack_rotations(quats: np.ndarray, version: int) -> np.ndarray:
    """Quaternions [N, 4] (x, y, z, w) in RUB -> packed bytes [N, 3] (v2) or [N, 4] (v3, v4) of the unit ones."""
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    # A zero quaternion is the identity, as the PLY reader repairs it and the other exports write it; the smallest
    # three of (0, 0, 0, 0) would name x as the largest and read back as a half turn about x.
    q = np.where(norm < 1e-12, np.array([0.0, 0.0, 0.0, 1.0]), quats / np.maximum(norm, 1e-12))
    if version == 2:
        q = q * np.where(q[:, 3:] < 0, -127.5, 127.5) + 127.5
        return _u8(q[:, :3])
    largest = np.abs(q).argmax(axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        sign = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = (511.0 * np.abs(q[:, i]) / math.sqrt(0.5) + 0.5).astype(np.uint32)
        packed = (comp << np.uint32(10)) | (sign << np.uint32(9)) | np.minimum(mag, 511)
        comp = np.where(largest == i, comp, packed)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_rotations(raw: np.ndarray, version: int) -> np.ndarray:
    """Inverse of ``_pack_rotations``: [N, 4] (x, y, z, w) unit quaternions."""
    if version == 2:
        xyz = raw.astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.clip(1.0 - (xyz**2).sum(axis=1), 0.0, 1.0))
        return np.concatenate([xyz, w[:, None]], axis=1)
    comp = raw.copy().view("<u4")[:, 0].astype(np.int64)
    largest = comp >> 30
    q = np.zeros((len(comp), 4))
    for i in range(3, -1, -1):
        here = largest != i
        mag = (comp & 511).astype(np.float64) * math.sqrt(0.5) / 511.0
        value = np.where((comp >> 9) & 1, -mag, mag)
        q[here, i] = value[here]
        comp = np.where(here, comp >> 10, comp)
    q[np.arange(len(q)), largest] = np.sqrt(np.clip(1.0 - (q**2).sum(axis=1), 0.0, 1.0))
    return q


def _quantize_sh(x: np.ndarray, bits: int) -> np.ndarray:
    bucket = 1 << (8 - bits)
    q = np.round(np.clip(x, -2.0, 2.0) * 128.0).astype(np.int64) + 128  # clipped first: casts stay in range
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


FINEST_RELATIVE_BITS = 18  # the position step is at most 2^-18 of the scene's extent
REFERENCE_BITS = 12  # the reference writer's fixed choice: never coarser than it
MAX_BITS = 24  # readers compute 1 << bits in 32-bit integers: stay well inside
# The scene's extent must span at least 2^10 steps: no coarser than any other export resolves it (the compressed
# PLY's 10-bit axis of a chunk's box). Below that, distinct positions merge into a few points.
MIN_SPAN_BITS = 10


def _fractional_bits(means: np.ndarray) -> int:
    """Fractional bits for ``means`` [N, 3] (RUB): a step of 2^-18 of the extent, at least 12 bits, at most 24, then
    fewer while the scene's reach would not fit 24 signed bits; a scene of no extent the most its reach allows."""
    if not means.size:
        return REFERENCE_BITS
    extent = float(np.ptp(means, axis=0).max())
    # No extent (one Gaussian, or all at one point): every row is the same, so the finest step costs no bytes.
    wanted = FINEST_RELATIVE_BITS - math.floor(math.log2(extent)) if extent > 0 else MAX_BITS
    bits = min(max(wanted, REFERENCE_BITS), MAX_BITS)
    reach = float(np.abs(means).max())
    while bits > 0 and reach * (1 << bits) >= (1 << 23) - 1:
        bits -= 1
    return bits


def write_spz(scene: GaussianScene, *, version: int = 3, sh1_bits: int = 8, sh_rest_bits: int = 8) -> bytes:
    """The `.spz` bytes of ``scene`` (version 2, 3 or 4)."""
    if version not in VERSIONS:
        raise ValueError(f"spz version must be one of {VERSIONS}, got {version}")
    if not (1 <= sh1_bits <= 8 and 1 <= sh_rest_bits <= 8):
        raise ValueError(f"SH bits must be in 1..8, got sh1_bits={sh1_bits} sh_rest_bits={sh_rest_bits}")
    t = {k: v.detach().cpu().double().numpy() for k, v in scene.tensors().items()}
    if not all(np.isfinite(v).all() for v in t.values()):  # NaN would cast to arbitrary bytes, an infinity raise
        raise ValueError("spz: the format stores finite attributes only")
    n, k = len(scene), scene.sh_rest.shape[1]
    flip = np.array([1.0, -1.0, -1.0])
    means = t["means"] * flip
    frac = _fractional_bits(means)
    if means.size and float(np.abs(means).max()) >= (1 << 23) - 1:
        raise ValueError(f"spz: positions up to {float(np.abs(means).max()):g} do not fit its 24-bit fixed point")
    extent = float(np.ptp(means, axis=0).max()) if means.size else 0.0
    if 0 < extent * (1 << frac) < 1 << MIN_SPAN_BITS:
        step = 2.0**-frac
        raise ValueError(f"spz: positions spanning {extent:g} do not fit its 24-bit fixed point (a step of {step:g})")
    below = SMALLEST_LOG_SCALE + math.log(TINY_FACTOR)
    tiny = float((t["scales"].max(axis=1) < below).mean()) if n else 0.0
    if tiny > MAX_TINY_SHARE:
        raise ValueError(
            f"spz: {tiny:.0%} of the Gaussians are under {TINY_FACTOR:g} times its smallest scale "
            f"({math.exp(SMALLEST_LOG_SCALE):.2g}) across, so it would draw them larger and rounder than they are; "
            f"scale the scene up (it spans {extent:g})"
        )
    fixed = np.round(means * (1 << frac)).astype(np.int64) & 0xFFFFFF
    positions = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], axis=-1).astype(np.uint8)  # [N, 3, 3]
    alphas = _u8(255.0 * (0.5 + 0.5 * np.tanh(0.5 * t["opacities"])))  # the sigmoid, without overflow
    colors = _u8(t["sh_dc"] * (COLOR_SCALE * 255.0) + 127.5)
    scales = _u8((t["scales"] + 10.0) * 16.0)
    wxyz = t["quats"]
    xyzw = np.stack([wxyz[:, 1], -wxyz[:, 2], -wxyz[:, 3], wxyz[:, 0]], axis=1)
    rotations = _pack_rotations(xyzw, version)
    rest = t["sh_rest"] * SH_FLIP[:k, None]  # [N, K, 3]: coefficient-major, channel inner
    band1 = min(k, 3)  # widths spelt out: reshape(n, -1) cannot infer them for an empty scene
    sh = np.concatenate(
        [_quantize_sh(rest[:, :3], sh1_bits).reshape(n, 3 * band1),
         _quantize_sh(rest[:, 3:], sh_rest_bits).reshape(n, 3 * (k - band1))],
        axis=1,
    )  # fmt: skip
    blocks = [positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), rotations.tobytes(),
              sh.tobytes()]  # fmt: skip
    degree = scene.sh_degree
    if version < 4:
        header = _LEGACY_HEADER.pack(MAGIC, version, n, degree, frac, 0, 0)
        return gzip.compress(header + b"".join(blocks), compresslevel=6, mtime=0)
    import zstandard

    # Level 19: on the position stream at 21 fractional bits level 12 gives 260 kB where 19 gives 171 kB (gzip: 193).
    coder = zstandard.ZstdCompressor(level=19, threads=-1)
    streams = [(coder.compress(b), len(b)) for b in blocks if b]
    header = _V4_HEADER.pack(MAGIC, 4, n, degree, frac, 0, len(streams), _V4_HEADER.size, bytes(12))
    toc = b"".join(struct.pack("<QQ", len(c), u) for c, u in streams)
    return header + toc + b"".join(c for c, _ in streams)


def _blocks(data: bytes) -> tuple[int, int, int, int, list[bytes]]:
    """(version, count, degree, fractional bits, the six attribute blocks) of a `.spz` file."""
    if data[:4] == struct.pack("<I", MAGIC):
        if len(data) < _V4_HEADER.size:
            raise SpzError(f"spz: {len(data)} bytes, shorter than the v4 header")
        magic, version, n, degree, frac, _flags, count, toc, _ = _V4_HEADER.unpack_from(data)
        if version != 4 or degree not in SH_REST_COUNT or not 0 <= toc <= len(data) - 16 * count:
            raise SpzError(f"spz: version {version}, SH degree {degree}, {count} streams at {toc}: not readable")
        import zstandard

        # One name, two shapes: (compressed, uncompressed) pairs here, the legacy layout's block sizes below.
        sizes: list[Any] = [struct.unpack_from("<QQ", data, toc + 16 * i) for i in range(count)]
        pos, raw = toc + 16 * count, []
        for compressed, uncompressed in sizes:
            frame = data[pos : pos + compressed]
            if len(frame) != compressed or uncompressed > 1 << 34:
                raise SpzError("spz: a stream is cut short or claims too much")
            raw.append(zstandard.ZstdDecompressor().decompress(frame, max_output_size=uncompressed))
            pos += compressed
        raw += [b""] * (6 - len(raw))
        return version, n, degree, frac, raw
    try:
        body = gzip.decompress(data)
    except (OSError, EOFError) as exc:
        raise SpzError(f"spz: neither an NGSP header nor a gzip stream ({exc})") from exc
    if len(body) < _LEGACY_HEADER.size:
        raise SpzError("spz: gzip stream shorter than the header")
    magic, version, n, degree, frac, _flags, _ = _LEGACY_HEADER.unpack_from(body)
    if magic != MAGIC or version not in (2, 3) or degree not in SH_REST_COUNT:
        raise SpzError(f"spz: magic {magic:#x}, version {version}, SH degree {degree}: not readable")
    k = SH_REST_COUNT[degree]
    sizes = [9 * n, n, 3 * n, 3 * n, (3 if version == 2 else 4) * n, 3 * k * n]
    if len(body) < _LEGACY_HEADER.size + sum(sizes):
        raise SpzError(f"spz: {len(body)} bytes decoded, {n} Gaussians need {_LEGACY_HEADER.size + sum(sizes)}")
    pos, raw = _LEGACY_HEADER.size, []
    for size in sizes:
        raw.append(body[pos : pos + size])
        pos += size
    return version, n, degree, frac, raw


def read_spz(data: bytes) -> GaussianScene:
    """The scene in a `.spz` file (any of versions 2-4), back in our RDF axes."""
    version, n, degree, frac, raw = _blocks(data)
    k = SH_REST_COUNT[degree]
    expected = [9 * n, n, 3 * n, 3 * n, (3 if version == 2 else 4) * n, 3 * k * n]
    if [len(b) for b in raw] != expected:
        raise SpzError(f"spz: attribute blocks of {[len(b) for b in raw]} bytes, expected {expected}")
    pos = np.frombuffer(raw[0], dtype=np.uint8).reshape(n, 3, 3).astype(np.int64)
    fixed = pos[..., 0] | (pos[..., 1] << 8) | (pos[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed / float(1 << frac) * np.array([1.0, -1.0, -1.0])
    alpha = np.clip(np.frombuffer(raw[1], dtype=np.uint8) / 255.0, 1e-6, 1 - 1e-6)
    colors = (np.frombuffer(raw[2], dtype=np.uint8).reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
    scales = np.frombuffer(raw[3], dtype=np.uint8).reshape(n, 3) / 16.0 - 10.0
    xyzw = _unpack_rotations(np.frombuffer(raw[4], dtype=np.uint8).reshape(n, 3 if version == 2 else 4), version)
    wxyz = np.stack([xyzw[:, 3], xyzw[:, 0], -xyzw[:, 1], -xyzw[:, 2]], axis=1)
    sh = (np.frombuffer(raw[5], dtype=np.uint8).reshape(n, k, 3) - 128.0) / 128.0 * SH_FLIP[:k, None]

    # Alpha 0 and 255 clamp to the opacity range the PLY reader repairs infinities to, as splat-transform's do.
    logits = np.clip(np.log(alpha / (1 - alpha)), OPACITY_LOGIT_MIN, OPACITY_LOGIT_MAX)

    def f32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return GaussianScene(
        means=f32(means), quats=f32(wxyz), scales=f32(scales), opacities=f32(logits),
        sh_dc=f32(colors), sh_rest=f32(sh),
    )  # fmt: skip


def load_spz(path: str | os.PathLike[str]) -> GaussianScene:
    """``read_spz`` of the file at ``path``."""
    return read_spz(Path(path).read_bytes())
