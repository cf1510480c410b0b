"""Safe extraction of an uploaded dataset archive (zip or tar) and a check of what it holds.

Nothing in an archive may write outside the destination or cost more than the limits: absolute paths, ``..``
components, links and special files are refused, and the entry count and the extracted size are counted while
extracting (declared sizes are checked first, actual bytes as they are written), so a zip bomb stops at the cap.
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
from typing import BinaryIO, Literal

from .errors import ApiError

CHUNK = 1 << 20
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}
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


class _Extractor:
    """Writes entries under ``dest`` while counting entries and bytes against the limits."""

    def __init__(self, dest: Path, limits: ArchiveLimits) -> None:
        self.dest, self.limits = dest.resolve(), limits
        self.entries = 0
        self.bytes = 0

    def count(self) -> None:
        self.entries += 1
        if self.entries > self.limits.max_entries:
            raise _too_large("too_many_entries", f"the archive has more than {self.limits.max_entries} entries")

    def reserve(self, declared: int) -> None:
        if self.bytes + declared > self.limits.max_bytes:
            raise self.over()

    def over(self) -> ApiError:
        return _too_large("archive_too_large", f"the archive extracts to more than {self.limits.max_bytes} bytes")

    def target(self, name: str) -> Path | None:
        parts = safe_parts(name)
        if not parts:
            return None
        path = self.dest.joinpath(*parts)
        if not path.resolve().is_relative_to(self.dest):  # belt and braces: a link planted by an earlier entry
            raise _invalid("unsafe_entry", f"archive entry {name[:80]!r} leaves the archive folder")
        return path

    def directory(self, name: str) -> None:
        path = self.target(name)
        if path is not None:
            path.mkdir(parents=True, exist_ok=True)

    def file(self, name: str, source: BinaryIO) -> None:
        path = self.target(name)
        if path is None:
            return
        if path.exists():
            raise _invalid("duplicate_entry", f"archive entry {name[:80]!r} appears twice")
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "xb") as out:
            while chunk := source.read(CHUNK):
                self.bytes += len(chunk)
                if self.bytes > self.limits.max_bytes:
                    raise self.over()
                out.write(chunk)


def _extract_zip(archive: Path, ex: _Extractor) -> None:
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        if len(infos) > ex.limits.max_entries:
            raise _too_large("too_many_entries", f"the archive has {len(infos)} entries, above {ex.limits.max_entries}")
        declared = 0
        for info in infos:
            safe_parts(info.filename)
            mode = info.external_attr >> 16
            if stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise _invalid("unsafe_entry", f"archive entry {info.filename[:80]!r} is a link or a special file")
            if info.flag_bits & 0x1:
                raise _invalid("bad_archive", f"archive entry {info.filename[:80]!r} is encrypted")
            declared += info.file_size
        ex.reserve(declared)
        for info in infos:
            ex.count()
            if info.is_dir():
                ex.directory(info.filename)
            else:
                with zf.open(info) as source:
                    ex.file(info.filename, source)


def _extract_tar(archive: Path, ex: _Extractor) -> None:
    # Stream mode reads members in order without seeking or building the whole member list first.
    with tarfile.open(archive, mode="r|*") as tf:
        for member in tf:
            ex.count()
            if member.isdir():
                ex.directory(member.name)
            elif member.isreg():
                ex.reserve(member.size)
                source = tf.extractfile(member)
                assert source is not None  # regular members always have data
                ex.file(member.name, source)
            else:
                raise _invalid("unsafe_entry", f"archive entry {member.name[:80]!r} is a link or a special file")


def extract(archive: Path, dest: Path, limits: ArchiveLimits) -> int:
    """Extract a zip or tar (optionally gzip/bzip2/xz compressed) into ``dest``; returns the extracted bytes."""
    with open(archive, "rb") as f:
        magic = f.read(4)
    ex = _Extractor(dest, limits)
    dest.mkdir(parents=True, exist_ok=True)
    try:
        if magic[:2] == b"PK":
            _extract_zip(archive, ex)
        elif tarfile.is_tarfile(archive):
            _extract_tar(archive, ex)
        else:
            raise _invalid("bad_archive", "images: not a zip or tar archive")
    except (zipfile.BadZipFile, tarfile.TarError, zlib.error, EOFError, NotImplementedError) as exc:
        raise _invalid("bad_archive", f"images: the archive is damaged ({exc})") from None
    except OSError as exc:  # a gzip/xz stream that is not one, or entries that clash (a file where a folder goes)
        raise _invalid("bad_archive", f"images: cannot extract the archive ({exc.strerror or exc})") from None
    return ex.bytes


def _layout(folder: Path) -> Layout | None:
    if any((folder / f"transforms_{split}.json").is_file() for split in ("train", "val", "test")):
        return "nerf_synthetic"
    for model in (folder / "sparse" / "0", folder / "sparse"):
        if any((model / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return "colmap"
    return None


def find_dataset(folder: Path) -> tuple[Layout, Path]:
    """The dataset folder: ``folder`` itself or, when it holds a single folder (an archive of one directory),
    that one, up to three levels down."""
    current = folder
    for _ in range(4):
        layout = _layout(current)
        if layout is not None:
            return layout, current
        children = [p for p in current.iterdir() if p.name != "__MACOSX"]
        if len(children) != 1 or not children[0].is_dir():
            break
        current = children[0]
    raise _invalid(
        "bad_dataset",
        "images: neither a NeRF-Synthetic dataset (transforms_train.json, ...) nor a COLMAP one "
        "(sparse/0/cameras.bin or cameras.txt) at the top of the archive",
    )


def _images(root: Path) -> Iterator[Path]:
    for path in root.rglob("*"):
        if path.suffix.lower() in IMAGE_SUFFIXES and path.is_file():
            yield path


def check_images(root: Path, limits: ArchiveLimits) -> int:
    """Count the images and read each one's size from its header; returns the count."""
    from PIL import Image

    count = 0
    for path in _images(root):
        count += 1
        if count > limits.max_images:
            raise _too_large("too_many_images", f"images: more than {limits.max_images} images")
        name = path.relative_to(root).as_posix()
        try:
            with Image.open(path) as image:
                width, height = image.size
        except Image.DecompressionBombError:
            raise _too_large("image_too_large", f"images: {name} has too many pixels") from None
        except (OSError, SyntaxError, ValueError) as exc:
            raise _invalid("bad_image", f"images: {name} is not a readable image ({exc})") from None
        if width * height > limits.max_image_pixels:
            raise _too_large(
                "image_too_large", f"images: {name} is {width}x{height}, above {limits.max_image_pixels} pixels"
            )
    if count == 0:
        raise _invalid("bad_dataset", "images: the dataset holds no images")
    return count


def extract_dataset(archive: Path, dest: Path, limits: ArchiveLimits) -> Dataset:
    """Extract, find the dataset folder and check its images; ApiError (413/422) on anything refused."""
    size = extract(archive, dest, limits)
    layout, root = find_dataset(dest)
    images = check_images(root, limits)
    return Dataset(layout, root.relative_to(dest).as_posix(), images, size)
