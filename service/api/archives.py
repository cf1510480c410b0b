"""Safe extraction of an uploaded dataset archive (zip or tar) and a check of what it holds.

Nothing in an archive may write outside the destination or cost more than the limits. Before anything is written,
every entry is read from the zip's central directory or the tar's headers: absolute paths, ``..`` components, links
and special files are refused, entries counted, declared sizes summed against the cap, and the dataset's layout
found by name. While extracting, the bytes actually written are counted against the same cap (a zip entry whose
data inflates past its declared size is cut there and fails its CRC). The cap is the smaller of the configured
limit and ``MAX_RATIO`` times the archive's own size: images, most of any dataset, barely compress, so a bomb is
refused from its directory having written nothing. What tarfile reads whole before a member reaches those checks (a
long name, a pax record, a sparse map) is capped at ``TAR_HEADERS_MAX`` bytes a member.
"""

from __future__ import annotations

import re
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Literal

from worker.gateway import stored_name_problem

from .errors import ApiError

CHUNK = 1 << 20
MAX_RATIO = 50  # extracted bytes per archive byte; PNG and JPEG images inflate about 1x, JSON and text about 5x
RATIO_FLOOR = 8 << 20  # a small archive may extract to this much whatever its ratio
SPLITS = ("train", "val", "test")
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}
# What tarfile may read to learn one member: its header, and the long names, long links, pax records and sparse maps
# before it; a real one holds a path or a few keys. A few keys, too, in the pax records that apply to every member.
TAR_HEADERS_MAX = 64 << 10
TAR_GLOBAL_KEYS = 64
Layout = Literal["nerf_synthetic", "colmap"]
_DRIVE = re.compile(r"^[A-Za-z]:")


@dataclass(frozen=True)
class ArchiveLimits:
    max_entries: int
    max_bytes: int  # extracted bytes, all entries together
    max_images: int
    max_image_pixels: int


@dataclass(frozen=True)
class Dataset:
    layout: Layout
    root: str  # the dataset folder, relative to the extraction folder ("." for the folder itself)
    images: int
    bytes: int


def _too_large(code: str, message: str) -> ApiError:
    return ApiError(413, code, message)


def _invalid(code: str, message: str) -> ApiError:
    return ApiError(422, code, message)


def safe_parts(name: str) -> list[str]:
    """The path components of an archive entry name; ApiError when the name could escape the destination."""
    if "\x00" in name:
        raise _invalid("unsafe_entry", f"archive entry {name[:80]!r} has a NUL character in its name")
    unified = name.replace("\\", "/")
    if unified.startswith("/") or _DRIVE.match(unified):
        raise _invalid("unsafe_entry", f"archive entry {name[:80]!r} is an absolute path")
    parts = [p for p in unified.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise _invalid("unsafe_entry", f"archive entry {name[:80]!r} leaves the archive folder ('..')")
    return parts


@dataclass(frozen=True)
class Entry:
    name: str
    parts: tuple[str, ...]  # safe path components; empty for the archive's top folder
    is_dir: bool
    size: int  # declared, in bytes


def _entry(name: str, *, is_dir: bool, is_file: bool, size: int) -> Entry:
    parts = tuple(safe_parts(name))
    # Each file is stored under its name (an object key on S3): the storage's one rule for names, at the door.
    if parts and (problem := stored_name_problem("/".join(parts))) is not None:
        raise _invalid("bad_name", f"archive entry {name[:80]!r} {problem}; rename it")
    if not (is_dir or is_file):
        raise _invalid("unsafe_entry", f"archive entry {name[:80]!r} is a link or a special file")
    return Entry(name, parts, is_dir, 0 if is_dir else size)


class _Budget:
    """Counts entries and bytes against the limits; ``cap`` is the byte budget of this archive."""

    def __init__(self, limits: ArchiveLimits, cap: int) -> None:
        self.limits, self.cap = limits, cap
        self.entries = 0
        self.bytes = 0

    def count(self, declared: int) -> None:
        self.entries += 1
        if self.entries > self.limits.max_entries:
            raise _too_large("too_many_entries", f"the archive has more than {self.limits.max_entries} entries")
        self.add(declared)

    def add(self, size: int) -> None:
        self.bytes += size
        if self.bytes > self.cap:
            raise self.over()

    def over(self) -> ApiError:
        if self.cap < self.limits.max_bytes:
            return _too_large(
                "archive_too_large",
                f"the archive extracts to more than {self.cap} bytes, {MAX_RATIO} times its own size (a dataset's "
                "images barely compress)",
            )
        return _too_large("archive_too_large", f"the archive extracts to more than {self.limits.max_bytes} bytes")


def _zip_entries(zf: zipfile.ZipFile, budget: _Budget) -> list[Entry]:
    infos = zf.infolist()
    if len(infos) > budget.limits.max_entries:
        raise _too_large(
            "too_many_entries", f"the archive has {len(infos)} entries, above {budget.limits.max_entries}"
        )
    entries = []
    for info in infos:
        kind = stat.S_IFMT(info.external_attr >> 16)
        is_dir = info.is_dir() and kind in (0, stat.S_IFDIR)
        entry = _entry(info.filename, is_dir=is_dir, is_file=not is_dir and kind in (0, stat.S_IFREG),
                       size=info.file_size)  # fmt: skip
        if info.flag_bits & 0x1:
            raise _invalid("bad_archive", f"archive entry {info.filename[:80]!r} is encrypted")
        budget.count(entry.size)
        entries.append(entry)
    return entries


class _HeaderReads:
    """The tar stream while tarfile reads one member's headers: a read past ``TAR_HEADERS_MAX`` bytes is refused
    before it is made. tarfile reads a long name, a long link, a pax record or a sparse map whole, the size the header
    declares, before the member they belong to reaches the budget."""

    def __init__(self, stream: tarfile._Fileobj) -> None:
        self.stream, self.left = stream, TAR_HEADERS_MAX

    def read(self, size: int, /) -> bytes:
        if size > self.left:
            raise _invalid("bad_archive", f"images: a tar member's headers (long names, pax records, sparse maps) "
                           f"exceed {TAR_HEADERS_MAX} bytes")  # fmt: skip
        self.left -= size
        return self.stream.read(size)

    def tell(self) -> int:
        return self.stream.tell()


class _TarMember(tarfile.TarInfo):
    """A tar member whose headers are read through ``_HeaderReads``."""

    def _proc_member(self, archive: tarfile.TarFile) -> tarfile.TarInfo:  # tarfile's hook for TarInfo subclasses
        stream = archive.fileobj
        if isinstance(stream, _HeaderReads):  # the header after a long name or pax record: the same cap holds both
            return super()._proc_member(archive)  # type: ignore[misc]
        archive.fileobj = _HeaderReads(stream)  # type: ignore[assignment]
        try:
            member: tarfile.TarInfo = super()._proc_member(archive)  # type: ignore[misc]
        finally:
            archive.fileobj = stream
        if len(archive.pax_headers) > TAR_GLOBAL_KEYS:  # they pile up, member after member
            raise _invalid("bad_archive", f"images: the tar's global pax records hold more than {TAR_GLOBAL_KEYS} keys")
        return member


def _tar_entries(tf: tarfile.TarFile, budget: _Budget) -> Iterator[tuple[Entry, tarfile.TarInfo]]:
    # Stream mode reads members in order, without seeking or building the member list first; member sizes in tar
    # headers are exact, so the budget stops a bomb at the header that would pass the cap.
    for member in tf:
        entry = _entry(member.name, is_dir=member.isdir(), is_file=member.isreg(), size=member.size)
        budget.count(entry.size)
        yield entry, member


def read_entries(archive: Path, limits: ArchiveLimits) -> list[Entry]:
    """Every entry of a zip or tar, from its directory or headers, checked before anything is written: names,
    kinds, count and declared sizes."""
    budget = _Budget(limits, byte_cap(archive, limits))
    with _Opened(archive) as opened:
        if isinstance(opened, zipfile.ZipFile):
            return _zip_entries(opened, budget)
        return [entry for entry, _ in _tar_entries(opened, budget)]


def byte_cap(archive: Path, limits: ArchiveLimits) -> int:
    """The most an archive may extract to: the configured limit, or ``MAX_RATIO`` times its size if less."""
    return min(limits.max_bytes, max(RATIO_FLOOR, MAX_RATIO * archive.stat().st_size))


class _Opened:
    """The archive opened as a ZipFile or a streaming TarFile; its errors become 422 ``bad_archive``."""

    def __init__(self, archive: Path) -> None:
        self.archive = archive
        self.handle: zipfile.ZipFile | tarfile.TarFile | None = None

    def __enter__(self) -> zipfile.ZipFile | tarfile.TarFile:
        with open(self.archive, "rb") as f:
            magic = f.read(4)
        try:
            self.handle = zipfile.ZipFile(self.archive) if magic[:2] == b"PK" else _open_tar(self.archive)
        except BaseException as exc:
            self.__exit__(type(exc), exc, None)
            raise
        return self.handle

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, _tb: object) -> None:
        if self.handle is not None:
            self.handle.close()
        if isinstance(exc, (zipfile.BadZipFile, tarfile.TarError, zlib.error, EOFError, NotImplementedError)):
            raise _invalid("bad_archive", f"images: the archive is damaged ({exc})") from None
        if isinstance(exc, OSError):  # a gzip/xz stream that is not one, or a file where a folder goes
            raise _invalid("bad_archive", f"images: cannot extract the archive ({exc.strerror or exc})") from None


def _open_tar(archive: Path) -> tarfile.TarFile:
    # Not tarfile.is_tarfile first: it reads the first member with the plain TarInfo, long name and all.
    try:
        return tarfile.open(archive, mode="r|*", tarinfo=_TarMember)
    except tarfile.ReadError:
        raise _invalid("bad_archive", "images: not a zip or tar archive") from None


class _Writer:
    """Writes entries under ``dest``, counting the bytes actually written against the budget."""

    def __init__(self, dest: Path, budget: _Budget) -> None:
        self.dest, self.budget = dest.resolve(), budget

    def target(self, entry: Entry) -> Path | None:
        if not entry.parts:
            return None
        path = self.dest.joinpath(*entry.parts)
        if not path.resolve().is_relative_to(self.dest):  # belt and braces: a link planted by an earlier entry
            raise _invalid("unsafe_entry", f"archive entry {entry.name[:80]!r} leaves the archive folder")
        return path

    def write(self, entry: Entry, source: IO[bytes] | None) -> None:
        path = self.target(entry)
        if path is None:
            return
        if entry.is_dir:
            path.mkdir(parents=True, exist_ok=True)
            return
        if path.exists():
            raise _invalid("duplicate_entry", f"archive entry {entry.name[:80]!r} appears twice")
        path.parent.mkdir(parents=True, exist_ok=True)
        assert source is not None  # regular entries always have data
        with open(path, "xb") as out:
            while chunk := source.read(CHUNK):
                self.budget.add(len(chunk))
                out.write(chunk)


def _write_all(archive: Path, entries: list[Entry], dest: Path, limits: ArchiveLimits) -> int:
    """Extract ``entries`` (as ``read_entries`` found them) into ``dest``; returns the bytes written."""
    writer = _Writer(dest, _Budget(limits, byte_cap(archive, limits)))
    dest.mkdir(parents=True, exist_ok=True)
    with _Opened(archive) as opened:
        if isinstance(opened, zipfile.ZipFile):
            for entry, info in zip(entries, opened.infolist(), strict=True):
                if entry.is_dir:
                    writer.write(entry, None)
                else:
                    with opened.open(info) as source:
                        writer.write(entry, source)
        else:
            for entry, member in _tar_entries(opened, _Budget(limits, byte_cap(archive, limits))):
                writer.write(entry, None if entry.is_dir else opened.extractfile(member))
    return writer.budget.bytes


def extract(archive: Path, dest: Path, limits: ArchiveLimits) -> int:
    """Extract a zip or tar (optionally gzip/bzip2/xz compressed) into ``dest``; returns the extracted bytes."""
    return _write_all(archive, read_entries(archive, limits), dest, limits)


def _layout(files: set[tuple[str, ...]], root: tuple[str, ...]) -> Layout | None:
    if any(root + (f"transforms_{split}.json",) in files for split in SPLITS) or root + ("transforms.json",) in files:
        return "nerf_synthetic"
    for model in (root + ("sparse", "0"), root + ("sparse",)):
        if any(model + (f"cameras.{ext}",) in files for ext in ("bin", "txt")):
            return "colmap"
    return None


def find_dataset(entries: list[Entry]) -> tuple[Layout, tuple[str, ...]]:
    """The dataset folder by the entries' names: the top of the archive or, when that holds a single folder (an
    archive of one directory), that one, up to three levels down."""
    files = {e.parts for e in entries if not e.is_dir and e.parts}
    folders = {parts[:i] for parts in files for i in range(len(parts))} | {e.parts for e in entries if e.is_dir}
    current: tuple[str, ...] = ()
    for _ in range(4):
        layout = _layout(files, current)
        if layout is not None:
            return layout, current
        depth = len(current)
        children = {p[depth] for p in files | folders if len(p) > depth and p[:depth] == current} - {"__MACOSX"}
        if len(children) != 1 or current + (next(iter(children)),) not in folders:
            break
        current += (next(iter(children)),)
    raise _invalid(
        "bad_dataset",
        "images: neither a NeRF-Synthetic dataset (transforms_train.json, ... or transforms.json) nor a COLMAP one "
        "(sparse/0/cameras.bin or cameras.txt) at the top of the archive",
    )


def _image_size(path: Path, name: str, max_pixels: int) -> tuple[int, int] | None:
    """Width and height from the header of the file at ``path`` (``name`` in the archive); None when Pillow cannot
    read it and it does not claim to be an image by its suffix (a transforms file, a COLMAP model, notes)."""
    from PIL import Image, UnidentifiedImageError

    with open(path, "rb") as f:
        jpeg = f.read(2) == b"\xff\xd8"
    # Pillow keeps every APP segment of a JPEG as it opens it: one stuffed with them would be held whole. No image
    # within the pixel limit needs more than 8 bytes a pixel (16-bit RGBA, uncompressed), whatever it carries besides.
    if jpeg and path.stat().st_size > 8 * max_pixels + (1 << 20):
        raise _too_large("image_too_large", f"images: {name} holds more bytes than an image of {max_pixels} pixels")
    try:
        with Image.open(path) as image:
            return image.size
    except Image.DecompressionBombError:
        raise _too_large("image_too_large", f"images: {name} has too many pixels") from None
    except (OSError, SyntaxError, ValueError) as exc:
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            return None
        # Pillow's "cannot identify" and the system's errors name the file by its path on this server: their reason
        # only.
        if isinstance(exc, UnidentifiedImageError):
            reason = "not in an image format the service reads"
        else:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise _invalid("bad_image", f"images: {name} is not a readable image ({reason})") from None


def check_images(root: Path, limits: ArchiveLimits) -> int:
    """Count the images and read each one's size from its header; returns the count. Any file Pillow takes for an
    image counts, whatever its suffix: a dataset names its images freely (NeRF's ``file_path``, COLMAP's image
    names), and the worker decodes whatever it names."""
    count = 0
    for path in root.rglob("*"):
        if not path.is_file():
            continue
        name = path.relative_to(root).as_posix()
        size = _image_size(path, name, limits.max_image_pixels)
        if size is None:
            continue
        count += 1
        if count > limits.max_images:
            raise _too_large("too_many_images", f"images: more than {limits.max_images} images")
        width, height = size
        if width * height > limits.max_image_pixels:
            raise _too_large(
                "image_too_large", f"images: {name} is {width}x{height}, above {limits.max_image_pixels} pixels"
            )
    if count == 0:
        raise _invalid("bad_dataset", "images: the dataset holds no images")
    return count


def extract_dataset(archive: Path, dest: Path, limits: ArchiveLimits) -> Dataset:
    """Check the entries and find the dataset by name, extract, check its images; ApiError (413/422) on anything
    refused."""
    entries = read_entries(archive, limits)
    layout, root = find_dataset(entries)
    size = _write_all(archive, entries, dest, limits)
    images = check_images(dest.joinpath(*root), limits)
    return Dataset(layout, "/".join(root) or ".", images, size)
