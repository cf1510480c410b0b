"""Safe extraction of dataset archives: hostile entries are refused before anything escapes, caps hold."""

from __future__ import annotations

import io
import json
import os
import struct
import tarfile
import tracemalloc
import zipfile
from pathlib import Path

import pytest
from PIL import Image

from service.api.archives import ArchiveLimits, extract, extract_dataset, safe_parts
from service.api.errors import ApiError

LIMITS = ArchiveLimits(max_entries=20, max_bytes=1 << 20, max_images=4, max_image_pixels=64 * 64)


def _png(size: int = 16) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (size, size)).save(buffer, format="PNG")
    return buffer.getvalue()


def _write_zip(path: Path, entries: dict[str, bytes], *, mode: int | None = None, special: str | None = None) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
        if special is not None:
            info = zipfile.ZipInfo(special)
            info.external_attr = (mode or 0) << 16
            zf.writestr(info, b"/etc/passwd")
    return path


def _error(call) -> ApiError:  # noqa: ANN001
    with pytest.raises(ApiError) as caught:
        call()
    return caught.value


NERF = {"scene/transforms_train.json": json.dumps({"camera_angle_x": 0.7, "frames": []}).encode(),
        "scene/train/r_0.png": _png(), "scene/train/r_1.png": _png()}  # fmt: skip


@pytest.mark.parametrize(
    "name, parts",
    [("a/b.png", ["a", "b.png"]), ("./a//b", ["a", "b"]), ("dir/", ["dir"]), ("a/./b", ["a", "b"])],
)
def test_safe_names(name: str, parts: list[str]) -> None:
    assert safe_parts(name) == parts


@pytest.mark.parametrize("name", ["../x", "a/../../x", "/etc/passwd", "C:/Windows/x", "a\\..\\..\\x", "\\\\host\\x",
                                  "a\x00b"])  # fmt: skip
def test_unsafe_names(name: str) -> None:
    assert _error(lambda: safe_parts(name)).code == "unsafe_entry"


def test_dataset_in_a_folder_is_found(tmp_path: Path) -> None:
    archive = _write_zip(tmp_path / "a.zip", NERF)
    dataset = extract_dataset(archive, tmp_path / "out", LIMITS)
    assert (dataset.layout, dataset.root, dataset.images) == ("nerf_synthetic", "scene", 2)
    assert dataset.bytes == sum(len(v) for v in NERF.values())
    assert (tmp_path / "out" / "scene" / "train" / "r_1.png").read_bytes() == NERF["scene/train/r_1.png"]


def test_a_single_transforms_json_is_a_nerf_dataset(tmp_path: Path) -> None:
    entries = {"capture/transforms.json": NERF["scene/transforms_train.json"], "capture/images/f_0.png": _png()}
    dataset = extract_dataset(_write_zip(tmp_path / "n.zip", entries), tmp_path / "out", LIMITS)
    assert (dataset.layout, dataset.root, dataset.images) == ("nerf_synthetic", "capture", 1)


def test_colmap_at_the_top(tmp_path: Path) -> None:
    entries = {"sparse/0/cameras.txt": b"# none\n", "images/a.jpg": _png(), "images/b.jpg": _png()}
    dataset = extract_dataset(_write_zip(tmp_path / "c.zip", entries), tmp_path / "out", LIMITS)
    assert (dataset.layout, dataset.root, dataset.images) == ("colmap", ".", 2)


@pytest.mark.parametrize(
    "entries, special, mode, status, code",
    [
        ({**NERF, "../escape.txt": b"x"}, None, None, 422, "unsafe_entry"),
        (NERF, "scene/link", 0o120777, 422, "unsafe_entry"),  # symbolic link
        (NERF, "scene/fifo", 0o010644, 422, "unsafe_entry"),  # named pipe
        ({**NERF, "scene/big.bin": bytes(2 << 20)}, None, None, 413, "archive_too_large"),  # compresses to ~2 KiB
        ({**NERF, **{f"scene/{i}.txt": b"" for i in range(20)}}, None, None, 413, "too_many_entries"),
        ({"readme.txt": b"hi"}, None, None, 422, "bad_dataset"),
        ({**NERF, "scene/train/r_2.png": _png(65)}, None, None, 413, "image_too_large"),
        ({**NERF, "scene/train/r_2.dat": _png(65)}, None, None, 413, "image_too_large"),  # an image by its content
        ({**NERF, **{f"scene/x{i}.png": _png() for i in range(3)}}, None, None, 413, "too_many_images"),
        ({**NERF, "scene/train/bad.png": b"\x89PNG\r\n\x1a\n garbage"}, None, None, 422, "bad_image"),
        ({**NERF, "scene/train/r_0.png/inner": b"x"}, None, None, 422, "bad_archive"),  # file where a folder goes
    ],
)
def test_refused_zips(
    tmp_path: Path, entries: dict, special: str | None, mode: int | None, status: int, code: str
) -> None:
    archive = _write_zip(tmp_path / "a.zip", entries, mode=mode, special=special)
    error = _error(lambda: extract_dataset(archive, tmp_path / "out" / "x", LIMITS))
    assert (error.status, error.code) == (status, code), error.message
    assert not (tmp_path / "out" / "escape.txt").exists() and not (tmp_path / "escape.txt").exists()


def test_a_jpeg_stuffed_with_app_segments_is_refused_unopened(tmp_path: Path) -> None:
    """Pillow holds every APP segment of a JPEG as it opens it: 16x16 pixels with 1.3 MB of them is refused by its
    size, before it is opened."""
    buffer = io.BytesIO()
    Image.new("RGB", (16, 16)).save(buffer, format="JPEG")
    jpeg = buffer.getvalue()
    segment = b"\xff\xef" + (65535).to_bytes(2, "big") + bytes(65533)  # APP15, as long as a segment may be
    stuffed = jpeg[:2] + segment * 20 + jpeg[2:]
    limits = ArchiveLimits(max_entries=20, max_bytes=8 << 20, max_images=4, max_image_pixels=64 * 64)
    archive = _write_zip(tmp_path / "a.zip", {**NERF, "scene/train/r_2.jpg": stuffed})
    error = _error(lambda: extract_dataset(archive, tmp_path / "out", limits))
    assert (error.status, error.code) == (413, "image_too_large"), error.message
    plain = _write_zip(tmp_path / "b.zip", {**NERF, "scene/train/r_2.jpg": jpeg})
    assert extract_dataset(plain, tmp_path / "out2", limits).images == 3


def test_images_are_known_by_their_content(tmp_path: Path) -> None:
    entries = {
        **NERF,
        "scene/train/r_2.dat": _png(),
        "scene/notes.dat": b"not an image",
        "scene/points.bin": b"\1" * 64,
    }
    dataset = extract_dataset(_write_zip(tmp_path / "a.zip", entries), tmp_path / "out", LIMITS)
    assert dataset.images == 3


def test_unreadable_image_is_named_as_in_the_archive(tmp_path: Path) -> None:
    archive = _write_zip(tmp_path / "a.zip", {**NERF, "scene/train/bad.png": b"no image format at all"})
    error = _error(lambda: extract_dataset(archive, tmp_path / "out", LIMITS))
    assert error.code == "bad_image" and "train/bad.png" in error.message
    assert str(tmp_path) not in error.message and "/out" not in error.message


def test_zip_bomb_with_lying_sizes_stops_at_the_cap(tmp_path: Path) -> None:
    """An entry whose headers claim 1 KiB but whose data inflates to 4 MiB is cut where the claim ends."""
    archive = _write_zip(tmp_path / "bomb.zip", {"scene/zeros.bin": bytes(4 << 20)})
    data = bytearray(archive.read_bytes())
    real = (4 << 20).to_bytes(4, "little")
    for at in [i for i in range(len(data) - 3) if data[i : i + 4] == real]:
        data[at : at + 4] = (1024).to_bytes(4, "little")
    archive.write_bytes(bytes(data))
    error = _error(lambda: extract(archive, tmp_path / "out", LIMITS))
    assert (error.status, error.code) == (422, "bad_archive")
    assert sum(f.stat().st_size for f in (tmp_path / "out").rglob("*") if f.is_file()) <= 1024


GENEROUS = ArchiveLimits(max_entries=20_000, max_bytes=8 << 30, max_images=2000, max_image_pixels=4096 * 4096)


def _written(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file()) if folder.exists() else 0


@pytest.mark.parametrize("layout", [NERF, {"notes.txt": b"no dataset here"}])
def test_zip_bomb_under_the_configured_cap_is_refused_from_its_directory(tmp_path: Path, layout: dict) -> None:
    """64 MiB of zeros in a 65 kB zip, far below the default cap of 8 GiB: refused before a byte is written."""
    archive = _write_zip(tmp_path / "bomb.zip", {**layout, "scene/zeros.bin": bytes(64 << 20)})
    assert archive.stat().st_size < 100_000
    error = _error(lambda: extract_dataset(archive, tmp_path / "out", GENEROUS))
    assert (error.status, error.code) == (413, "archive_too_large"), error.message
    assert "times its own size" in error.message
    assert _written(tmp_path / "out") == 0


def _overlapping_bomb(path: Path, copies: int) -> Path:
    """A zip whose central directory lists ``copies`` entries that all point at one compressed blob of 4 MiB of
    zeros (a non-recursive bomb: the archive stays small however many copies it lists)."""
    data = _write_zip(path, {"k": bytes(4 << 20)}).read_bytes()
    end = data.rindex(b"PK\x05\x06")
    start = struct.unpack_from("<I", data, end + 16)[0]
    record = data[start:end]
    name_length = struct.unpack_from("<H", record, 28)[0]
    names = [f"scene/z{i}.bin".encode() for i in range(copies)]
    directory = b"".join(record[:28] + struct.pack("<H", len(n)) + record[30:46] + n + record[46 + name_length :]
                         for n in names)  # fmt: skip
    trailer = data[end : end + 8] + struct.pack("<HHII", copies, copies, len(directory), start) + data[end + 20 :]
    path.write_bytes(data[:start] + directory + trailer)
    return path


def test_overlapping_zip_entries_are_summed_from_the_directory(tmp_path: Path) -> None:
    bomb = _overlapping_bomb(tmp_path / "many.zip", 100)
    with zipfile.ZipFile(bomb) as zf:
        assert sum(i.file_size for i in zf.infolist()) == 100 * (4 << 20) and bomb.stat().st_size < 20_000
    error = _error(lambda: extract_dataset(bomb, tmp_path / "out", GENEROUS))
    assert (error.status, error.code) == (413, "archive_too_large")
    assert _written(tmp_path / "out") == 0


def test_layout_is_checked_before_extracting(tmp_path: Path) -> None:
    archive = _write_zip(tmp_path / "a.zip", {"photos/a.png": _png(), "photos/b.png": _png()})
    error = _error(lambda: extract_dataset(archive, tmp_path / "out", GENEROUS))
    assert (error.status, error.code) == (422, "bad_dataset")
    assert not (tmp_path / "out").exists()


def _tar_add(tf: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    tf.addfile(info, io.BytesIO(data))


def test_tar_bomb_stops_at_its_header(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.tar.gz"
    with tarfile.open(bomb, "w:gz") as tf:
        for name, data in NERF.items():
            _tar_add(tf, name, data)
        _tar_add(tf, "scene/zeros", bytes(64 << 20))
    error = _error(lambda: extract_dataset(bomb, tmp_path / "out", GENEROUS))
    assert (error.status, error.code) == (413, "archive_too_large")
    assert _written(tmp_path / "out") == 0


@pytest.mark.parametrize("kind", [tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.CHRTYPE, tarfile.FIFOTYPE])
def test_tar_links_and_devices_are_refused(tmp_path: Path, kind: bytes) -> None:
    path = tmp_path / "a.tar"
    with tarfile.open(path, "w") as tf:
        info = tarfile.TarInfo("scene/x")
        info.type, info.linkname = kind, "/etc/passwd"
        tf.addfile(info)
    assert _error(lambda: extract(path, tmp_path / "out", LIMITS)).code == "unsafe_entry"


def test_tar_bomb_and_traversal(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.tar.xz"
    with tarfile.open(bomb, "w:xz") as tf:
        _tar_add(tf, "scene/zeros", bytes(3 << 20))
    assert bomb.stat().st_size < 10_000
    error = _error(lambda: extract(bomb, tmp_path / "out", LIMITS))
    assert (error.status, error.code) == (413, "archive_too_large")

    sneaky = tmp_path / "sneaky.tar.gz"
    with tarfile.open(sneaky, "w:gz") as tf:
        _tar_add(tf, "../../sneaky.txt", b"x")
    assert _error(lambda: extract(sneaky, tmp_path / "out2", LIMITS)).code == "unsafe_entry"
    assert not (tmp_path / "sneaky.txt").exists() and not Path(os.path.dirname(tmp_path), "sneaky.txt").exists()


class _Zeros(io.RawIOBase):
    """``size`` zero bytes, read without holding them all."""

    def __init__(self, size: int) -> None:
        self.left = size

    def readinto(self, buffer) -> int:  # noqa: ANN001
        n = min(len(buffer), self.left)
        buffer[:n] = bytes(n)
        self.left -= n
        return n


def _tar_record(tf: tarfile.TarFile, kind: bytes, data: io.RawIOBase | io.BytesIO, size: int) -> None:
    """A record of type ``kind`` (long name, long link, pax) as tarfile writes a member: header, then data."""
    info = tarfile.TarInfo("././@LongLink")
    info.type, info.size = kind, size
    tf.addfile(info, data)


def _pax(key: str, value: str) -> bytes:
    body = f" {key}={value}\n"
    length = len(body) + 1
    length += len(str(length)) - 1
    return f"{length}{body}".encode()


def _peak_mib(call) -> tuple[ApiError, float]:  # noqa: ANN001
    tracemalloc.start()
    try:
        error = _error(call)
        return error, tracemalloc.get_traced_memory()[1] / (1 << 20)
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("kind", [tarfile.GNUTYPE_LONGNAME, tarfile.GNUTYPE_LONGLINK, tarfile.XHDTYPE, tarfile.XGLTYPE])
def test_huge_tar_extended_header_is_refused_unread(tmp_path: Path, kind: bytes) -> None:
    """A long name (or link, or pax record) of 32 MiB, 32 kB compressed: tarfile would read it whole before the first
    member reaches the budget; it is refused having read no more than the cap on one member's headers."""
    size = 32 << 20
    path = tmp_path / "long.tar.gz"
    with tarfile.open(path, "w:gz", format=tarfile.GNU_FORMAT) as tf:
        _tar_record(tf, kind, _Zeros(size), size)
        for name, data in NERF.items():
            _tar_add(tf, name, data)
    assert path.stat().st_size < 100_000
    error, peak = _peak_mib(lambda: extract_dataset(path, tmp_path / "out", GENEROUS))
    assert (error.status, error.code) == (422, "bad_archive"), error.message
    assert peak < 8, f"peak {peak:.1f} MiB"
    assert _written(tmp_path / "out") == 0


def test_tar_headers_that_pile_up_are_refused(tmp_path: Path) -> None:
    chain = tmp_path / "chain.tar"  # a member behind 2000 long names, each replacing the last
    with tarfile.open(chain, "w", format=tarfile.GNU_FORMAT) as tf:
        for _ in range(2000):
            _tar_record(tf, tarfile.GNUTYPE_LONGNAME, io.BytesIO(b"scene/x\0"), 8)
        _tar_add(tf, "scene/x", b"x")
    globals_ = tmp_path / "globals.tar"  # global pax records hold for every later member, so their keys add up
    with tarfile.open(globals_, "w", format=tarfile.GNU_FORMAT) as tf:
        for i in range(100):
            record = _pax(f"key{i}", "x" * 1000)
            _tar_record(tf, tarfile.XGLTYPE, io.BytesIO(record), len(record))
            _tar_add(tf, f"scene/{i}", b"")
    for path in (chain, globals_):
        error = _error(lambda: extract(path, tmp_path / "out", GENEROUS))  # noqa: B023
        assert (error.status, error.code) == (422, "bad_archive"), (path.name, error.message)


def test_huge_tar_sparse_map_is_refused_unread(tmp_path: Path) -> None:
    """A GNU 1.0 sparse map of 4 million pieces in 8 MB (10 kB compressed), which tarfile reads into a list before
    the member it maps reaches the budget."""
    path = tmp_path / "sparse.tar.gz"
    with tarfile.open(path, "w:gz", format=tarfile.PAX_FORMAT) as tf:
        info = tarfile.TarInfo("scene/x")
        info.pax_headers = {"GNU.sparse.major": "1", "GNU.sparse.minor": "0"}
        data = b"2000000\n" + b"1\n" * 4_000_000
        info.size = len(data)
        tf.addfile(info, io.BytesIO(data))
    error, peak = _peak_mib(lambda: extract(path, tmp_path / "out", GENEROUS))
    assert (error.status, error.code) == (422, "bad_archive"), error.message
    assert peak < 8, f"peak {peak:.1f} MiB"


def test_tar_long_names_and_pax_records_are_read(tmp_path: Path) -> None:
    long_name = "scene/" + "d" * 200 + "/notes.txt"
    for form in (tarfile.GNU_FORMAT, tarfile.PAX_FORMAT):
        path = tmp_path / f"{form}.tar.gz"
        with tarfile.open(path, "w:gz", format=form, pax_headers={"comment": "a git archive's commit"}) as tf:
            for name, data in {**NERF, long_name: b"hello", "scene/caf\u00e9.txt": b"x"}.items():
                _tar_add(tf, name, data)
        out = tmp_path / f"out{form}"
        assert extract_dataset(path, out, LIMITS).images == 2
        assert (out / long_name).read_bytes() == b"hello"


def test_tar_dataset_is_extracted(tmp_path: Path) -> None:
    path = tmp_path / "d.tar.gz"
    with tarfile.open(path, "w:gz") as tf:
        for name, data in NERF.items():
            _tar_add(tf, name, data)
    dataset = extract_dataset(path, tmp_path / "out", LIMITS)
    assert (dataset.layout, dataset.root, dataset.images) == ("nerf_synthetic", "scene", 2)


def test_not_an_archive(tmp_path: Path) -> None:
    path = tmp_path / "x.bin"
    path.write_bytes(b"hello world, not an archive")
    assert _error(lambda: extract(path, tmp_path / "out", LIMITS)).code == "bad_archive"


@pytest.mark.parametrize(
    "name",
    ["scene/notes/a\x01b.txt", "scene/notes/a\x1bb.txt", "scene/notes/a\ufffeb.txt", "scene/notes/a\rb.txt",
     "scene/a\u202eb.txt", "scene/" + "n" * 256 + ".txt", "scene/" + "/".join(["d" * 100] * 6) + "/x.txt"],
    ids=["SOH", "ESC", "non-character", "CR", "bidi override", "long file name", "long path"],
)  # fmt: skip
def test_entry_names_the_storage_cannot_keep_are_refused_before_extracting(tmp_path: Path, name: str) -> None:
    """Each file becomes an object key as named: a name S3's DeleteObjects cannot carry made its job undeletable (and
    stopped the expiry sweep for every tenant), so it is refused at the door, with its own code."""
    archive = _write_zip(tmp_path / "a.zip", {**NERF, name: b"notes"})
    error = _error(lambda: extract_dataset(archive, tmp_path / "out", LIMITS))
    assert (error.status, error.code) == (422, "bad_name"), error.message
    assert not (tmp_path / "out").exists()


def test_printable_names_of_any_script_are_kept(tmp_path: Path) -> None:
    entries = {**NERF, "scene/notes/façade vue 東 😀.txt": b"notes"}
    extract_dataset(_write_zip(tmp_path / "a.zip", entries), tmp_path / "out", LIMITS)
    assert (tmp_path / "out" / "scene" / "notes" / "façade vue 東 😀.txt").read_bytes() == b"notes"


@pytest.mark.realdata
def test_phone_photographs_pass_the_default_limits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """instant-ngp's fox, zipped as a user would (50 JPEGs of 1080x1920 and its transforms.json), is taken whole by
    the limits a service starts with (``worker.settings.Settings``): 2 MP a photograph, under the 16.7 MP cap."""
    from tests.conftest import shared_file
    from worker.settings import Settings

    fox = shared_file("instant_ngp_fox_capture")
    for name in [n for n in os.environ if n.startswith("SYMGS_")]:
        monkeypatch.delenv(name)
    settings = Settings()
    limits = ArchiveLimits(max_entries=settings.max_archive_entries, max_bytes=settings.max_extracted_bytes,
                           max_images=settings.max_images, max_image_pixels=settings.max_image_pixels)  # fmt: skip
    archive = tmp_path / "fox.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as zf:  # JPEGs: nothing left to deflate
        for path in sorted(fox.rglob("*")):
            if path.is_file():
                zf.write(path, f"fox/{path.relative_to(fox).as_posix()}")
    dataset = extract_dataset(archive, tmp_path / "out", limits)
    assert (dataset.layout, dataset.root, dataset.images) == ("nerf_synthetic", "fox", 50)
    assert archive.stat().st_size < settings.max_upload_bytes
