"""PlayCanvas SOG (version 2): writer and reader of the `.sog` bundle and of its unbundled folder (``meta.json``
beside lossless WebP images), the layout PlayCanvas' engine and ``splat-transform`` read.

Every attribute is a texture of W x H RGBA texels, one Gaussian per texel in row order (W a multiple of 4 near
sqrt N, H the multiple of 4 that holds N). Gaussians are stored in Morton order of their centres.

    means_l/u.webp   per axis, v = sign(x) * ln(1 + |x|) as 16 bits between that axis' ``mins`` and ``maxs`` of v:
                     low byte in means_l, high byte in means_u (alpha 255)
    quats.webp       unit quaternion (w, x, y, z) as the smallest three, the largest made positive: the other three
                     components in order as bytes of c * sqrt2 / 2 + 1/2, alpha = 252 + index of the largest
    scales.webp      log-scales as indices into ``scales.codebook`` (256 sorted values), alpha 255
    sh0.webp         DC coefficients as indices into ``sh0.codebook``; alpha = sigmoid(opacity logit) as a byte
    shN_*.webp       higher SH (``shN``, when the degree is above 0): a palette of ``count`` vectors, each
                     channel-major (all of red's K coefficients, then green's, then blue's); ``shN_labels`` holds
                     each Gaussian's entry as 16 bits (low byte red, high byte green), ``shN_centroids`` the
                     entries, 64 per row, K texels each, coefficient j of channel c an index into ``shN.codebook``

The codebooks come from a 1-D k-means of the values they stand for, the palette from the k-means of
``codec.palette`` (exactly the distinct vectors when they fit). Textures are lossless WebP with exact RGB under
transparent texels (Pillow), since every byte is data. Axes are those of the PLY (our RDF: x right, y down,
z forward): PlayCanvas reads SOG in the same frame as PLY. The bundle is a zip of the same files, stored without
compression (WebP is compressed already; the engine reads stored entries without an inflater).
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from ..codec.order import morton_codes
from ..files import partial_file
from ..ply import OPACITY_LOGIT_MAX, OPACITY_LOGIT_MIN
from ..scene import SH_REST_COUNT, GaussianScene

VERSION = 2
META = "meta.json"
CODEBOOK = 256
PALETTE_ROW = 64  # palette entries per row of shN_centroids
MAX_PALETTE = 1 << 16  # labels are 16 bits
KMEANS_ENTRIES = 1 << 14  # measured: 16 s of k-means for 200k rows of 24 values on 2 cores
MAX_SIDE = 16383  # WebP's largest width or height
HISTOGRAM_BINS = 8192
LLOYD_STEPS = 24
SQRT2 = math.sqrt(2.0)
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed, so equal scenes give equal bundles


class SogError(ValueError):
    """A file that is not a readable SOG (version 2) scene."""


def sog_order(scene: GaussianScene) -> torch.Tensor:
    """The order [N] in which SOG stores the Gaussians (Morton order of their centres)."""
    return torch.argsort(morton_codes(scene.means.detach().cpu()), stable=True)


def texture_size(n: int) -> tuple[int, int]:
    """(width, height) of the textures that hold ``n`` Gaussians, as PlayCanvas sizes them."""
    width = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    height = max(4, math.ceil(n / width / 4) * 4)
    return width, height


def palette_size(rows: np.ndarray) -> int:
    """Entries of the higher-SH palette for ``rows`` [N, D]: every distinct row when at most 65536 of them (a
    decoded archive's SH is usually on a grid or a palette already: stored exactly, no k-means), else PlayCanvas'
    size (1024 entries per doubling of N past 1024) capped at ``KMEANS_ENTRIES`` for the CPU time of the k-means."""
    distinct = len(np.unique(rows.view(np.dtype((np.void, rows.shape[1] * rows.itemsize)))[:, 0]))
    if distinct <= MAX_PALETTE:
        return max(distinct, 1)
    return min(1024 << max(0, (len(rows) // 1024).bit_length() - 1), KMEANS_ENTRIES)


def _log_transform(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.log1p(np.abs(x))


def _exp_transform(v: np.ndarray) -> np.ndarray:
    return np.sign(v) * np.expm1(np.abs(v))


def _byte(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def fit_codebook(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``CODEBOOK`` sorted float32 values standing for ``values`` [M] (finite), and each value's index [M] uint8.

    The distinct values themselves when they fit; else a deterministic 1-D Lloyd iteration on a histogram whose bins
    weigh by the square root of their counts, so that the sparse tails (the few large or saturated Gaussians that
    show the most) keep entries of their own instead of all going to the dense middle.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        return np.zeros(CODEBOOK, np.float32), np.zeros(0, np.uint8)
    distinct = np.unique(v.astype(np.float32)).astype(np.float64)
    if len(distinct) <= CODEBOOK:
        centres = distinct
    else:
        lo, hi = float(distinct[0]), float(distinct[-1])
        bins = np.minimum(((v - lo) / (hi - lo) * HISTOGRAM_BINS).astype(np.int64), HISTOGRAM_BINS - 1)
        counts = np.bincount(bins, minlength=HISTOGRAM_BINS).astype(np.float64)
        used = counts > 0
        points = (np.bincount(bins, weights=v, minlength=HISTOGRAM_BINS)[used] / counts[used])
        weights = np.sqrt(counts[used])
        cumulative = np.cumsum(weights)
        quantiles = (np.arange(CODEBOOK) + 0.5) / CODEBOOK * cumulative[-1]
        centres = points[np.minimum(np.searchsorted(cumulative, quantiles), len(points) - 1)]
        for _ in range(LLOYD_STEPS):
            centres = np.unique(centres)
            owner = np.searchsorted((centres[1:] + centres[:-1]) / 2, points)
            mass = np.bincount(owner, weights=weights, minlength=len(centres))
            moment = np.bincount(owner, weights=weights * points, minlength=len(centres))
            centres = np.where(mass > 0, moment / np.maximum(mass, 1e-300), centres)
        centres = np.unique(centres)
    codebook = np.concatenate([centres, np.full(CODEBOOK - len(centres), centres[-1])]).astype(np.float32)
    labels = _nearest_entry(codebook[: len(centres)].astype(np.float64), v)
    return codebook, labels.astype(np.uint8)


def _nearest_entry(sorted_entries: np.ndarray, v: np.ndarray) -> np.ndarray:
    right = np.clip(np.searchsorted(sorted_entries, v), 1, max(len(sorted_entries) - 1, 1))
    left = right - 1
    if len(sorted_entries) == 1:
        return np.zeros(len(v), np.int64)
    return np.where(np.abs(v - sorted_entries[left]) <= np.abs(sorted_entries[right] - v), left, right)


def _webp(texels: np.ndarray, width: int, height: int) -> bytes:
    """Lossless WebP of ``texels`` [n, 4] uint8 placed in row order on a ``width`` x ``height`` image."""
    from PIL import Image

    image = np.zeros((width * height, 4), np.uint8)
    image[: len(texels)] = texels
    out = io.BytesIO()
    Image.fromarray(image.reshape(height, width, 4), "RGBA").save(out, "WEBP", lossless=True, exact=True, method=4)
    return out.getvalue()


def _rgba(*channels: np.ndarray, alpha: np.ndarray | int = 255) -> np.ndarray:
    n = len(channels[0])
    out = np.zeros((n, 4), np.uint8)
    for i, channel in enumerate(channels):
        out[:, i] = channel
    out[:, 3] = alpha
    return out


def _pack_quats(wxyz: np.ndarray) -> np.ndarray:
    q = wxyz / np.maximum(np.linalg.norm(wxyz, axis=1, keepdims=True), 1e-12)
    largest = np.abs(q).argmax(axis=1)
    rows = np.arange(len(q))
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]  # [N, 3]
    three = q[rows[:, None], others]
    return _rgba(*_byte((three * (SQRT2 * 0.5) + 0.5) * 255.0).T, alpha=(252 + largest).astype(np.uint8))


def sog_files(scene: GaussianScene, *, sh_palette: int | None = None) -> dict[str, bytes]:
    """The unbundled SOG of ``scene``: file name -> bytes, ``meta.json`` first (stored in ``sog_order``).

    ``sh_palette``: entries of the higher-SH palette (default ``palette_size``), at most 65536."""
    n = len(scene)
    if n == 0:
        raise ValueError("a SOG needs at least one Gaussian")
    width, height = texture_size(n)
    if max(width, height) > MAX_SIDE:
        raise ValueError(f"{n} Gaussians need {width}x{height} textures, beyond WebP's {MAX_SIDE} texels a side")
    if sh_palette is not None and not 1 <= sh_palette <= MAX_PALETTE:
        raise ValueError(f"sh_palette must be in 1..{MAX_PALETTE}, got {sh_palette}")
    s = scene.select(sog_order(scene))
    t = {k: v.detach().cpu().double().numpy() for k, v in s.tensors().items()}
    if not all(np.isfinite(v).all() for v in t.values()):
        raise ValueError("a SOG stores finite attributes only")

    logs = _log_transform(t["means"])
    mins, maxs = logs.min(axis=0), logs.max(axis=0)
    span = np.where(maxs > mins, maxs - mins, 1.0)
    q16 = np.clip(np.round((logs - mins) / span * 65535.0), 0, 65535).astype(np.int64)
    scale_book, scale_idx = fit_codebook(t["scales"])
    dc_book, dc_idx = fit_codebook(t["sh_dc"])
    with np.errstate(over="ignore"):  # exp of a logit below -709 is inf: an alpha of 0, not a warning
        alpha = _byte(255.0 / (1.0 + np.exp(-t["opacities"])))
    files = {
        "means_l.webp": _webp(_rgba(*(q16 & 255).T), width, height),
        "means_u.webp": _webp(_rgba(*(q16 >> 8).T), width, height),
        "quats.webp": _webp(_pack_quats(t["quats"]), width, height),
        "scales.webp": _webp(_rgba(*scale_idx.reshape(n, 3).T), width, height),
        "sh0.webp": _webp(_rgba(*dc_idx.reshape(n, 3).T, alpha=alpha), width, height),
    }
    meta: dict = {
        "version": VERSION,
        "asset": {"generator": "SymGS", "axes": "RDF (x right, y down, z forward), as the PLY"},
        "count": n,
        "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": dc_book.tolist(), "files": ["sh0.webp"]},
    }
    k = s.sh_rest.shape[1]
    if k:
        from ..codec.palette import fit_palette

        rows = np.ascontiguousarray(t["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k), dtype=np.float32)
        entries, labels = fit_palette(rows, palette_size(rows) if sh_palette is None else sh_palette)
        sh_book, sh_idx = fit_codebook(entries)
        m = len(entries)
        # Entry e's coefficient j sits at texel (e % 64) * K + j of row e // 64, its three channels in R, G, B.
        per_texel = sh_idx.reshape(m, 3, k).transpose(0, 2, 1).reshape(m * k, 3)
        files["shN_centroids.webp"] = _webp(_rgba(*per_texel.T), PALETTE_ROW * k, math.ceil(m / PALETTE_ROW))
        files["shN_labels.webp"] = _webp(_rgba(labels & 255, labels >> 8), width, height)
        meta["shN"] = {
            "count": m, "bands": s.sh_degree, "codebook": sh_book.tolist(),
            "files": ["shN_centroids.webp", "shN_labels.webp"],
        }  # fmt: skip
    return {META: json.dumps(meta).encode("utf-8"), **files}


def write_sog(scene: GaussianScene, *, sh_palette: int | None = None) -> bytes:
    """The `.sog` bundle of ``scene``: a zip of ``sog_files`` stored without compression."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as bundle:
        for name, data in sog_files(scene, sh_palette=sh_palette).items():
            bundle.writestr(zipfile.ZipInfo(name, date_time=_ZIP_TIME), data)
    return out.getvalue()


def save_sog_folder(scene: GaussianScene, meta_path: str | os.PathLike[str], **options: int | None) -> None:
    """Write the unbundled SOG: ``meta_path`` (a ``meta.json``) and its images beside it.

    Every file is written under a temporary name first and only then moved into place, ``meta.json`` last: a write
    that fails (a full disk) leaves the folder's previous export whole, and a viewer never reads a ``meta.json``
    that names images not written yet (the reader takes the first ``count`` texels of each, so images of another
    export beside it would read as a wrong scene, not as an error)."""
    folder = Path(meta_path).parent
    folder.mkdir(parents=True, exist_ok=True)
    files = sog_files(scene, **options)
    targets = [folder / (Path(meta_path).name if name == META else name) for name in files]
    staged: list[Path] = []
    try:
        for target, data in zip(targets, files.values()):
            with partial_file(target) as (out, partial):
                staged.append(partial)
                out.write(data)
        for path, target in list(zip(staged, targets))[::-1]:  # meta.json is first in ``files``: moved last
            os.replace(path, target)
    finally:
        for path in staged:
            path.unlink(missing_ok=True)


def _texels(files: Mapping[str, bytes], name: str, min_texels: int) -> tuple[np.ndarray, int]:
    """The RGBA texels [W * H, 4] of image ``name`` and its width; SogError when absent, unreadable or too small."""
    from PIL import Image, UnidentifiedImageError

    if name not in files:
        raise SogError(f"SOG: {name} is missing")
    try:
        with Image.open(io.BytesIO(files[name]), formats=["WEBP"]) as image:
            if max(image.size) > MAX_SIDE:
                raise SogError(f"SOG: {name} is {image.size[0]}x{image.size[1]}, over {MAX_SIDE} texels a side")
            pixels = np.asarray(image.convert("RGBA"))
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise SogError(f"SOG: {name} is not a readable WebP image ({exc})") from exc
    texels = pixels.reshape(-1, 4)
    if len(texels) < min_texels:
        raise SogError(f"SOG: {name} holds {len(texels)} texels, fewer than the {min_texels} needed")
    return texels, pixels.shape[1]


def _codebook(meta: dict, key: str) -> np.ndarray:
    book = np.asarray(meta[key].get("codebook", []), dtype=np.float64)
    if book.shape != (CODEBOOK,) or not np.isfinite(book).all():
        raise SogError(f"SOG: {key}.codebook must be {CODEBOOK} finite numbers")
    return book


def _files_of(meta: dict, key: str, count: int) -> list[str]:
    names = meta.get(key, {}).get("files") if isinstance(meta.get(key), dict) else None
    if not isinstance(names, list) or len(names) != count or not all(isinstance(f, str) for f in names):
        raise SogError(f"SOG: {key}.files must name {count} image(s)")
    return names


def read_sog_files(files: Mapping[str, bytes]) -> GaussianScene:
    """The scene in an unbundled SOG (file name -> bytes, with ``meta.json``), in file order."""
    if META not in files:
        raise SogError("SOG: meta.json is missing")
    try:
        meta = json.loads(files[META])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SogError(f"SOG: meta.json is not JSON ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("version") != VERSION:
        raise SogError(f"SOG: version {meta.get('version') if isinstance(meta, dict) else None}, expected {VERSION}")
    n = meta.get("count")
    if not isinstance(n, int) or not 0 < n <= MAX_SIDE * MAX_SIDE:
        raise SogError(f"SOG: count {n!r} is not a positive number of Gaussians")
    try:
        mins = np.asarray(meta["means"]["mins"], dtype=np.float64)
        maxs = np.asarray(meta["means"]["maxs"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise SogError("SOG: means.mins and means.maxs must be three numbers each") from exc
    if mins.shape != (3,) or maxs.shape != (3,) or not np.isfinite([mins, maxs]).all():
        raise SogError("SOG: means.mins and means.maxs must be three finite numbers each")

    low, _ = _texels(files, _files_of(meta, "means", 2)[0], n)
    high, _ = _texels(files, _files_of(meta, "means", 2)[1], n)
    q16 = low[:n, :3].astype(np.int64) | (high[:n, :3].astype(np.int64) << 8)
    span = np.where(maxs != mins, maxs - mins, 1.0)
    means = _exp_transform(mins + span * (q16 / 65535.0))

    quats_px, _ = _texels(files, _files_of(meta, "quats", 1)[0], n)
    tag = quats_px[:n, 3].astype(np.int64)
    if ((tag < 252) | (tag > 255)).any():
        raise SogError("SOG: quats.webp has alpha outside 252..255")
    three = (quats_px[:n, :3] / 255.0 * 2.0 - 1.0) / SQRT2
    largest = tag - 252
    quats = np.zeros((n, 4))
    mask = np.eye(4, dtype=bool)[largest]
    quats[~mask] = three.reshape(-1)
    quats[mask] = np.sqrt(np.clip(1.0 - (three**2).sum(axis=1), 0.0, 1.0))

    scales_px, _ = _texels(files, _files_of(meta, "scales", 1)[0], n)
    scales = _codebook(meta, "scales")[scales_px[:n, :3]]
    sh0_px, _ = _texels(files, _files_of(meta, "sh0", 1)[0], n)
    dc = _codebook(meta, "sh0")[sh0_px[:n, :3]]
    alpha = np.clip(sh0_px[:n, 3] / 255.0, 1e-6, 1 - 1e-6)
    # Alpha 0 and 255 clamp to the opacity range the PLY reader repairs infinities to, as the other readers do.
    logits = np.clip(np.log(alpha / (1 - alpha)), OPACITY_LOGIT_MIN, OPACITY_LOGIT_MAX)

    rest = np.zeros((n, 0, 3))
    if "shN" in meta:
        sh = meta["shN"]
        bands, count = sh.get("bands"), sh.get("count")
        if bands not in (1, 2, 3) or not isinstance(count, int) or not 0 < count <= MAX_PALETTE:
            raise SogError(f"SOG: shN with {bands!r} bands and {count!r} entries")
        k = SH_REST_COUNT[bands]
        book = _codebook(meta, "shN")
        names = _files_of(meta, "shN", 2)
        centroids, row_width = _texels(files, names[0], 0)
        if row_width != PALETTE_ROW * k or len(centroids) < count * k:
            raise SogError(
                f"SOG: {names[0]} is {row_width} texels wide and holds {len(centroids)}; {count} entries of {bands} "
                f"bands need rows {PALETTE_ROW * k} texels wide"
            )
        labels_px, _ = _texels(files, names[1], n)
        labels = labels_px[:n, 0].astype(np.int64) | (labels_px[:n, 1].astype(np.int64) << 8)
        if (labels >= count).any():
            raise SogError(f"SOG: a Gaussian names palette entry {int(labels.max())} of {count}")
        entries = book[centroids[: count * k, :3]].reshape(count, k, 3)  # [entry, coefficient, channel]
        rest = entries[labels]

    def f32(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return GaussianScene(
        means=f32(means), quats=f32(quats), scales=f32(scales), opacities=f32(logits), sh_dc=f32(dc),
        sh_rest=f32(rest),
    )  # fmt: skip


def read_sog(data: bytes) -> GaussianScene:
    """The scene in a `.sog` bundle, in file order."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as bundle:
            infos = bundle.infolist()
            if sum(info.file_size for info in infos) > 1 << 32:
                raise SogError("SOG: the bundle claims more than 4 GiB of files")
            files = {info.filename: bundle.read(info) for info in infos if not info.is_dir()}
    except (zipfile.BadZipFile, zipfile.LargeZipFile, NotImplementedError, EOFError) as exc:
        raise SogError(f"SOG: not a zip bundle ({exc})") from exc
    return read_sog_files(files)


def load_sog(path: str | os.PathLike[str]) -> GaussianScene:
    """The scene at ``path``: a `.sog` bundle, or the ``meta.json`` of an unbundled SOG (images beside it)."""
    path = Path(path)
    if path.name.lower().endswith(".sog"):
        return read_sog(path.read_bytes())
    meta = path.read_bytes()
    try:
        names = json.loads(meta)
        wanted = [f for key in ("means", "quats", "scales", "sh0", "shN") for f in names.get(key, {}).get("files", [])]
    except (UnicodeDecodeError, json.JSONDecodeError, AttributeError) as exc:
        raise SogError(f"SOG: {path.name} is not a SOG meta.json ({exc})") from exc
    files = {META: meta}
    for name in wanted:
        image = path.parent / str(name)
        if Path(str(name)).name != str(name) or not image.is_file():
            raise SogError(f"SOG: {name!r} is not an image beside {path.name}")
        files[str(name)] = image.read_bytes()
    return read_sog_files(files)
