"""Gaussian scenes in the graphdeco PLY layout: read by property name, validate, repair what is safe, write.

graphdeco order: ``x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3``, all float32, with
``f_rest`` channel-major: ``f_rest_{c*K + k-1}`` is SH coefficient k (1..K) of colour channel c.

Reading accepts any property order, extra properties (ignored, reported) and float64 values, read as float32; float64
positions that float32 would move by more than ``POSITION_ROUNDING_LIMIT`` of the scene's size are refused
(``out_of_range``: a scene far from the origin for its size loses its detail in float32). The header is
checked against the file size before the body is read, so a header that claims more Gaussians than the file
holds is refused without allocating for them; so is a file with data after the rows its header declares. Repairs,
counted in the report:
  * ``+inf`` / ``-inf`` opacity logits, and finite ones beyond +-88 (whose exp overflows float32 as the infinities'
    does), are clamped to logit(1 - 1/512) / logit(1/512);
  * zero quaternions (norm below 1e-12) become the identity (1, 0, 0, 0).
Unnormalised quaternions are normal in graphdeco files and are kept as stored. NaN anywhere, or an infinity in
any other property, is an error (``non_finite``); so is a finite value the float32 pipeline cannot carry
(``out_of_range``, ``LIMITS``). ``checked_scene`` applies the same rules to a scene built in memory, and to a
PlayCanvas compressed PLY (SuperSplat's export), which is read too.
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from .ply_header import DC, GEOMETRY, NORMALS, ROTATIONS, SCALES, TYPES, PlyError, PlyHeader, read_header
from .scene import SH_REST_COUNT, GaussianScene

# logit(1 - 1/512) and logit(1/512): the opacity range of an 8-bit alpha that avoids 0 and 1.
OPACITY_LOGIT_MAX = float(np.float32(math.log(511.0)))
OPACITY_LOGIT_MIN = -OPACITY_LOGIT_MAX
# Largest magnitude of each attribute (opacity: beyond it, clamped). Log-scales: exp(+-88) is a finite, non-zero
# float32 standard deviation (log of the float32 maximum: 88.7). Positions and rotations: squares of sums of a few
# stay finite in float32 (distances, quaternion norms). Colour coefficients: a thousand times what a renderer can
# show, well inside the codec's colour grids (2^24 cells of its finest steps, about 1/512, reach +-32768).
EXP_LIMIT = 88.0
LIMITS = {"means": 1e18, "quats": 1e18, "scales": EXP_LIMIT, "sh_dc": 4096.0, "sh_rest": 4096.0}
# float64 positions the float32 cast moves by more than this fraction of the scene's largest side are refused: such
# a scene (georeferenced, far from the origin for its size: past about 2,000 times its size) would lose detail the
# codec keeps. The codec's fitted position steps are about 5e-4 of that side, five times more, so a cast below the
# limit stays under the codec's own rounding; a scene a few hundred sizes out, common enough, is read.
POSITION_ROUNDING_LIMIT = 1e-4


@dataclass
class PlyReport:
    """What reading a scene found.

    count       Gaussians read
    sh_degree   0..3, from the number of f_rest properties
    format      the PLY encoding (ascii, binary_little_endian, binary_big_endian)
    layout      "graphdeco" (float properties by name) or "compressed" (PlayCanvas' packed chunks)
    properties  vertex property names in file order
    ignored     properties present but not used (normals, colours, ...)
    repairs     repair name -> number of Gaussians repaired; empty when nothing was changed
    comments    header comments
    """

    count: int
    sh_degree: int
    format: str
    properties: list[str]
    ignored: list[str]
    repairs: dict[str, int] = field(default_factory=dict)
    comments: list[str] = field(default_factory=list)
    layout: str = "graphdeco"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _vertex_rows(path: Path, header: PlyHeader) -> np.ndarray | None:
    """The vertex rows mapped from the file as a structured array (no copy), for binary files whose elements have no
    lists (every row at a fixed size, the file's length already checked by the header); None otherwise."""
    if header.format == "ascii" or any(e.has_lists for e in header.elements):
        return None
    order = "<" if header.format == "binary_little_endian" else ">"
    offset = header.size
    for element in header.elements:
        dtype = np.dtype([(name, f"{order}{TYPES[kind][1]}{TYPES[kind][0]}") for name, kind, _ in element.properties])
        if element is header.vertex:
            if element.count == 0:
                return np.empty(0, dtype)
            return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(element.count,))
        offset += element.count * dtype.itemsize
    raise AssertionError("the header has a vertex element")


class _PlainHeaderStream:
    """The file's body behind ``_plain_header``, for plyfile: it parses the header it is given rather than the file's,
    which it refuses where ``check_header`` is lenient (trailing whitespace on the magic or end_header line, UTF-8
    comments). Every other attribute is the body file's, offsets included: plyfile maps fixed-size elements through
    them. ``readline`` passes over blank lines between ascii rows where no element's rows are empty."""

    def __init__(self, header: bytes, body: IO[Any], skip_blank: bool) -> None:
        self._header, self._body, self._skip_blank = io.BytesIO(header), body, skip_blank

    def read(self, size: int = -1) -> Any:
        # plyfile reads the header up to its end_header line, then the body; read(0) tells it a text body.
        return (size and self._header.read(size)) or self._body.read(size)

    def readline(self) -> Any:
        line = self._body.readline()
        while self._skip_blank and line and not line.strip():
            line = self._body.readline()
        return line

    def __getattr__(self, name: str) -> Any:
        return getattr(self._body, name)


def _plain_header(header: PlyHeader) -> bytes:
    """``header`` as plain PLY: its format and elements, each line as plyfile writes it."""
    lines = ["ply", f"format {header.format} 1.0"]
    for element in header.elements:
        lines.append(f"element {element.name} {element.count}")
        lines += [
            f"property list {length} {kind} {prop}" if length else f"property {kind} {prop}"
            for prop, kind, length in element.properties
        ]
    return "".join(f"{line}\n" for line in [*lines, "end_header"]).encode("ascii")


def _rows_follow(stream: _PlainHeaderStream) -> bool:
    """Whether a non-blank line is left in an ascii ``stream``."""
    try:
        return bool(stream.readline())
    except ValueError:  # not ASCII: something is there
        return True


def _parsed_rows(path: Path, header: PlyHeader) -> np.ndarray:
    """The vertex rows as plyfile parses them (ascii files, files with lists), which stops after the rows the header
    declares: the file must end there (blank space aside, in ascii), as a binary file's length must match. Blank
    lines between ascii rows are passed over (the row count still has to match)."""
    from plyfile import PlyData, PlyParseError

    text = header.format == "ascii"
    with open(path, "rb") as raw:
        raw.seek(header.size)
        body: IO[Any] = io.TextIOWrapper(raw, encoding="ascii") if text else raw
        stream = _PlainHeaderStream(_plain_header(header), body, all(e.properties for e in header.elements))
        try:
            rows = PlyData.read(stream)["vertex"].data
            end = "" if text else b""
            extra = any(chunk.strip() if text else chunk for chunk in iter(lambda: body.read(1 << 16), end))
        except (PlyParseError, ValueError, EOFError) as exc:
            # A short last row is a file cut short; a short row with rows after it is a malformed row.
            cut = "early end-of-file" in str(exc) or isinstance(exc, EOFError)
            if "early end-of-line" in str(exc):
                cut = not _rows_follow(stream)
            code = "truncated" if cut else "malformed"
            raise PlyError(code, f"{path.name}: cannot read the vertex data ({exc})") from None
    if extra:
        raise PlyError(
            "trailing_data",
            f"{path.name}: data follows the rows the header describes: it declares {header.count} Gaussians, "
            "fewer than the file carries",
        )
    return rows


def _float_matrix(rows: np.ndarray) -> np.ndarray | None:
    """The rows as a float32 matrix [N, P] (a view) when every property is a float32; None otherwise."""
    kinds = {rows.dtype.fields[name][0] for name in rows.dtype.names or ()}  # type: ignore[index]
    kind = kinds.pop() if len(kinds) == 1 else None
    if kind is None or kind.kind != "f" or kind.itemsize != 4:
        return None
    return np.ndarray((len(rows), len(rows.dtype.names)), kind, rows, 0, (rows.dtype.itemsize, 4))  # type: ignore[arg-type]


def _fill(out: np.ndarray, rows: np.ndarray, matrix: np.ndarray | None, names: list[str]) -> None:
    """Copy the named properties into the columns of ``out`` [N, len(names)] (a view of the attribute's array)."""
    if not names:
        return
    if matrix is None:
        for j, name in enumerate(names):
            out[:, j] = rows[name]
        return
    index = [rows.dtype.names.index(name) for name in names]  # type: ignore[union-attr]
    if index == list(range(index[0], index[0] + len(index))):
        out[...] = matrix[:, index[0] : index[0] + len(index)]  # one strided block copy: the usual layouts
    else:
        out[...] = matrix[:, index]


def _columns(rest: list[str]) -> dict[str, list[str]]:
    """The property of each column of each attribute's matrix [N, C]; ``sh_rest`` is [N, K, 3] flattened."""
    k = len(rest) // 3
    return {
        "means": list(GEOMETRY), "sh_dc": list(DC), "opacities": ["opacity"], "scales": list(SCALES),
        "quats": list(ROTATIONS), "sh_rest": [rest[c * k + j] for j in range(k) for c in range(3)],
    }  # fmt: skip


def _checked(values: dict[str, np.ndarray], groups: dict[str, list[str]], name: str) -> dict[str, int]:
    """Apply the reader's rules to the float32 attribute matrices ``values`` (``_columns``' layout): PlyError names
    the properties refused; repaired attributes are replaced, never written into (they may be a caller's tensors).
    Returns the repairs made."""
    rest = [f"f_rest_{i}" for i in range(len(groups["sh_rest"]))]
    order = [*GEOMETRY, *DC, *rest, "opacity", *SCALES, *ROTATIONS]
    # min and max carry NaN and the infinities through without a temporary array: the counts only when they hit.
    bounds = {attr: (float(v.min()), float(v.max())) for attr, v in values.items() if v.size}
    counts: dict[str, int] = {}
    for attr, (lo, hi) in bounds.items():
        if not math.isfinite(lo) or not math.isfinite(hi):  # infinite opacities are repaired below
            invalid = np.isnan(values[attr]) if attr == "opacities" else ~np.isfinite(values[attr])
            counts.update(zip(groups[attr], invalid.sum(axis=0).tolist(), strict=True))
    if any(counts.values()):
        where = ", ".join(f"{prop} ({counts[prop]} values)" for prop in order if counts.get(prop))
        raise PlyError("non_finite", f"{name}: NaN or infinite values in {where}")
    limit_of: dict[str, float] = {}
    for attr, limit in LIMITS.items():
        lo, hi = bounds.get(attr, (0.0, 0.0))
        if max(-lo, hi) > limit:
            beyond = (np.abs(values[attr]) > limit).sum(axis=0).tolist()
            counts.update(zip(groups[attr], beyond, strict=True))
            limit_of.update(dict.fromkeys(groups[attr], limit))
    if any(counts.values()):
        where = ", ".join(
            f"{prop} ({counts[prop]} values beyond +-{limit_of[prop]:g})" for prop in order if counts.get(prop)
        )
        raise PlyError("out_of_range", f"{name}: values out of range in {where}")

    repairs: dict[str, int] = {}
    for repair, hit, limit in (
        ("opacity_pos_inf_clamped", values["opacities"] > EXP_LIMIT, OPACITY_LOGIT_MAX),
        ("opacity_neg_inf_clamped", values["opacities"] < -EXP_LIMIT, OPACITY_LOGIT_MIN),
    ):
        if hit.any():
            values["opacities"] = np.where(hit, np.float32(limit), values["opacities"])
            repairs[repair] = int(hit.sum())
    quats = values["quats"]
    # Only rows whose every component is below 1e-12 can have a norm below it: the exact test runs on those alone.
    small = np.flatnonzero((np.abs(quats) < 1e-12).all(axis=1))
    zero = small[np.linalg.norm(quats[small].astype(np.float64), axis=1) < 1e-12]
    if len(zero):
        values["quats"] = quats = quats.copy()
        quats[zero] = (1.0, 0.0, 0.0, 0.0)
        repairs["zero_quaternion_set_to_identity"] = len(zero)
    return repairs


def _check_position_rounding(exact: list[np.ndarray], rounded: np.ndarray, name: str) -> None:
    """PlyError ``out_of_range`` where casting the positions ``exact`` (a column per axis, any float type; checked
    finite) to ``rounded`` [N, 3] float32 moves one by more than POSITION_ROUNDING_LIMIT of the largest side of
    their bounding box. Nothing to do for float32 columns, which the cast keeps."""
    if all(column.dtype.itemsize <= 4 for column in exact) or not len(rounded):
        return
    lows, highs = [float(c.min()) for c in exact], [float(c.max()) for c in exact]
    extent = max(hi - lo for lo, hi in zip(lows, highs, strict=True))
    moved = []
    for j, column in enumerate(exact):  # one axis at a time: a temporary of N values, not 3N
        shift = np.subtract(column, rounded[:, j], dtype=np.float64)
        moved.append(max(float(shift.max()), -float(shift.min())))
    limit = POSITION_ROUNDING_LIMIT * extent
    if extent > 0 and max(moved) > limit:  # all at one point: no detail to lose
        axes = ", ".join(axis for axis, m in zip(GEOMETRY, moved, strict=True) if m > limit)
        magnitude = max(max(-lo, hi) for lo, hi in zip(lows, highs, strict=True))
        raise PlyError(
            "out_of_range",
            f"{name}: float64 positions in {axes} lose their detail in float32: at about {magnitude:.3g} with a "
            f"spread of {extent:.3g}, float32 moves them by up to {max(moved):.3g} (more than "
            f"{POSITION_ROUNDING_LIMIT:g} of the spread); move the scene near the origin",
        )


def _scene(values: dict[str, np.ndarray], n: int, k: int) -> GaussianScene:
    """The scene whose attributes are the matrices ``values`` (``_columns``' layout), sharing their memory."""
    shapes = {"opacities": (n,), "sh_rest": (n, k, 3)}
    return GaussianScene(**{attr: torch.from_numpy(v.reshape(shapes.get(attr, v.shape))) for attr, v in values.items()})


def _to_scene(rows: np.ndarray, rest: list[str], path: Path) -> tuple[GaussianScene, dict[str, int]]:
    """Scene from the structured vertex rows, after the checks and repairs: each attribute is copied once, straight
    into the native float32 array its tensor wraps (float32 input keeps its exact bits)."""
    n, k = len(rows), len(rest) // 3
    groups = _columns(rest)
    matrix = _float_matrix(rows)
    values = {attr: np.empty((n, len(names)), np.float32) for attr, names in groups.items() if attr != "sh_rest"}
    for attr, v in values.items():
        _fill(v, rows, matrix, groups[attr])
    sh_rest = np.empty((n, k, 3), np.float32)
    for c in range(3):  # f_rest is channel-major: f_rest_{c*K + j} is coefficient j+1 of channel c
        _fill(sh_rest[:, :, c], rows, matrix, rest[c * k : (c + 1) * k])
    values["sh_rest"] = sh_rest.reshape(n, 3 * k)
    repairs = _checked(values, groups, path.name)
    _check_position_rounding([rows[axis] for axis in GEOMETRY], values["means"], path.name)
    return _scene(values, n, k), repairs


def checked_scene(scene: GaussianScene, name: str = "scene") -> tuple[GaussianScene, dict[str, int]]:
    """``scene`` under the rules a file's values are read by: float32 on the CPU (other float types converted, as a
    double property is), checked and repaired as ``read_scene`` does; PlyError as for a file. Returns the repairs."""
    n, k = len(scene), scene.sh_rest.shape[1]
    groups = _columns([f"f_rest_{i}" for i in range(3 * k)])
    values: dict[str, np.ndarray] = {}
    for attr, t in scene.tensors().items():
        if not t.is_floating_point():
            raise PlyError("unsupported_format", f"{name}: {attr} is {t.dtype}, expected float")
        values[attr] = t.detach().to("cpu", torch.float32).numpy().reshape(n, len(groups[attr]))
    repairs = _checked(values, groups, name)
    if scene.means.dtype == torch.float64:
        exact = scene.means.detach().cpu().numpy()
        _check_position_rounding([exact[:, j] for j in range(3)], values["means"], name)
    return _scene(values, n, k), repairs


def read_scene(path: str | os.PathLike[str], *, max_gaussians: int | None = None) -> tuple[GaussianScene, PlyReport]:
    """Read a Gaussian scene and a report of what was found and repaired; raises PlyError on bad input.

    Binary files without lists (the usual case, either byte order) are mapped and each attribute copied once from
    the mapping; ascii files and files with list properties are parsed by plyfile. A PlayCanvas compressed PLY
    (SuperSplat's export) is decoded by its format's reader (``export.playcanvas``) and checked by the same rules."""
    path = Path(path)
    header = read_header(path, max_gaussians=max_gaussians)
    names, rest = header.properties, list(header.rest)

    if header.layout == "compressed":
        from .export.playcanvas import decode_compressed  # the format's reader, beside its writer

        scene, repairs = checked_scene(decode_compressed(path.read_bytes(), header), path.name)
    else:
        rows = _vertex_rows(path, header)
        if rows is None:
            rows = _parsed_rows(path, header)
        scene, repairs = _to_scene(rows, rest, path)
        del rows  # unmaps the file
    report = PlyReport(
        count=len(scene),
        sh_degree=scene.sh_degree,
        format=header.format,
        properties=names,
        ignored=[n for n in names if n not in header.used],
        repairs=repairs,
        comments=list(header.comments),
        layout=header.layout,
    )
    return scene, report


def load_scene(path: str | os.PathLike[str]) -> GaussianScene:
    """Read a Gaussian scene (see ``read_scene`` for what is accepted and repaired)."""
    return read_scene(path)[0]


def graphdeco_properties(sh_degree: int) -> list[str]:
    """Property names of the graphdeco layout for ``sh_degree``, in file order."""
    k = SH_REST_COUNT[sh_degree]
    rest = [f"f_rest_{i}" for i in range(3 * k)]
    return [*GEOMETRY, *NORMALS, *DC, *rest, "opacity", *SCALES, *ROTATIONS]


def ply_bytes(scene: GaussianScene, *, comments: tuple[str, ...] = ()) -> bytes:
    """The binary little-endian graphdeco PLY of ``scene`` (float32, zero normals).

    Built as one float32 matrix: a million Gaussians take a fraction of a second, where a structured array per
    property takes seconds.
    """
    n, k = len(scene), scene.sh_rest.shape[1]
    t = {name: v.detach().to("cpu", torch.float32) for name, v in scene.tensors().items()}
    flat = torch.cat(
        [t["means"], torch.zeros(n, 3), t["sh_dc"], t["sh_rest"].transpose(1, 2).reshape(n, 3 * k),
         t["opacities"][:, None], t["scales"], t["quats"]],
        dim=1,
    )  # fmt: skip
    # Refuse what the reader refuses (as the other writers do): NaN, or an infinity other than an opacity's, which the
    # reader clamps (real files hold +inf opacity logits); float64 beyond float32's range became an infinity above.
    properties = graphdeco_properties(scene.sh_degree)
    opacity = properties.index("opacity")
    rows = flat.numpy().astype("<f4", copy=False)
    for start in range(0, n, 1 << 20):  # a mask of a million rows at a time, not one the size of the file
        block = rows[start : start + (1 << 20)]
        finite = np.isfinite(block)  # numpy's: ten times torch's on a CPU, which made the check half the write
        finite[:, opacity] |= np.isinf(block[:, opacity])
        if not finite.all():
            raise ValueError("a PLY stores finite attributes only (an opacity may be infinite), no NaN")
    if any("\n" in c or "\r" in c for c in comments):  # it would end the comment and start a header line of its own
        raise ValueError("a PLY comment is one line: no line breaks")
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {n}"]
    header += [f"property float {name}" for name in properties] + ["end_header"]
    # UTF-8: the reader takes any bytes in a comment, so a comment read from a file is written back as it came
    return b"".join((("\n".join(header) + "\n").encode("utf-8"), rows.data))  # one copy of the rows, not two
