"""The plainest peer: the graphdeco PLY with every value as a 16-bit float (IEEE binary16), in one zstd frame.

What a platform gets with no codec at all beyond halving the floats and a general-purpose compressor. The PLY inside
declares its properties as type ``half`` (no normals: they are always zero); ``symgs decompress`` reads these files
(``.ply.zst``). Values beyond float16's range are clamped to it (+-65504), never turned into infinities.
"""

from __future__ import annotations

import numpy as np
import torch
import zstandard

from ..ply_header import DC, GEOMETRY, ROTATIONS, SCALES
from ..scene import SH_REST_COUNT, GaussianScene, sh_degree_for_rest

EXTENSION = ".ply.zst"
LEVEL = 19
_MAGIC = b"ply\nformat binary_little_endian 1.0\n"
_HALF_MAX = float(np.finfo(np.float16).max)
MAX_HEADER_BYTES = 1 << 16


class HalfPlyError(ValueError):
    """A file that is not a float16 PLY in a zstd frame as ``write_half_ply`` writes it."""


def _properties(sh_degree: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * SH_REST_COUNT[sh_degree])]
    return [*GEOMETRY, *DC, *rest, "opacity", *SCALES, *ROTATIONS]


def write_half_ply(scene: GaussianScene, level: int = LEVEL) -> bytes:
    """``scene`` as float16 graphdeco properties (graphdeco order, normals left out), zstd-compressed at ``level``."""
    n, k = len(scene), scene.sh_rest.shape[1]
    t = {name: v.detach().to("cpu", torch.float32) for name, v in scene.tensors().items()}
    flat = torch.cat(
        [t["means"], t["sh_dc"], t["sh_rest"].transpose(1, 2).reshape(n, 3 * k), t["opacities"][:, None],
         t["scales"], t["quats"]],
        dim=1,
    ).clamp(-_HALF_MAX, _HALF_MAX)  # fmt: skip
    header = [*_MAGIC.decode().splitlines(), f"element vertex {n}"]
    header += [f"property half {name}" for name in _properties(scene.sh_degree)] + ["end_header"]
    body = flat.numpy().astype("<f2").tobytes()
    return zstandard.ZstdCompressor(level=level).compress(("\n".join(header) + "\n").encode("ascii") + body)


def read_half_ply(data: bytes, *, max_bytes: int = 1 << 33) -> GaussianScene:
    """The scene of a ``write_half_ply`` file; HalfPlyError names what is wrong. ``max_bytes`` caps the PLY inside."""
    try:
        size = zstandard.frame_content_size(data)
    except zstandard.ZstdError as exc:
        raise HalfPlyError(f"not a zstd frame: {exc}") from None
    if size < 0 or size > max_bytes:
        raise HalfPlyError(f"the zstd frame must state its size, at most {max_bytes} bytes (states {size})")
    try:
        ply = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    except zstandard.ZstdError as exc:
        raise HalfPlyError(f"corrupt zstd frame: {exc}") from None
    end = ply.find(b"end_header\n", 0, MAX_HEADER_BYTES)
    if not ply.startswith(_MAGIC) or end < 0:
        raise HalfPlyError("not a binary little-endian PLY with an end_header line")
    lines = ply[len(_MAGIC) : end].decode("ascii", errors="replace").splitlines()
    if not lines or not lines[0].startswith("element vertex "):
        raise HalfPlyError("the PLY must hold one vertex element")
    try:
        n = int(lines[0].split()[2])
    except ValueError:
        raise HalfPlyError(f"bad vertex count in {lines[0]!r}") from None
    names = []
    for line in lines[1:]:
        parts = line.split()
        if len(parts) != 3 or parts[:2] != ["property", "half"]:
            raise HalfPlyError(f"expected 'property half NAME', got {line!r}")
        names.append(parts[2])
    rest = len(names) - len(_properties(0))
    try:
        degree = sh_degree_for_rest(rest // 3) if rest >= 0 and rest % 3 == 0 else -1
    except ValueError:
        degree = -1
    if degree < 0 or names != _properties(degree):
        raise HalfPlyError(f"properties are not the graphdeco ones of any SH degree: {names}")
    body = ply[end + len(b"end_header\n") :]
    if n < 0 or len(body) != 2 * n * len(names):
        raise HalfPlyError(f"{n} Gaussians of {len(names)} halves need {2 * n * len(names)} bytes, got {len(body)}")
    flat = torch.from_numpy(np.frombuffer(body, dtype="<f2").reshape(n, len(names)).astype(np.float32))
    k = SH_REST_COUNT[degree]
    return GaussianScene(
        means=flat[:, 0:3].contiguous(),
        sh_dc=flat[:, 3:6].contiguous(),
        sh_rest=flat[:, 6 : 6 + 3 * k].reshape(n, 3, k).transpose(1, 2).contiguous(),
        opacities=flat[:, 6 + 3 * k].contiguous(),
        scales=flat[:, 7 + 3 * k : 10 + 3 * k].contiguous(),
        quats=flat[:, 10 + 3 * k : 14 + 3 * k].contiguous(),
    )
