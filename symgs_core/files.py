"""Files written whole, or not at all, through temporary files that no one else can have planted.

A temporary file beside its target takes a fresh random name and is created exclusively (``O_EXCL``, and
``O_NOFOLLOW`` where the system has it): a link or file already at that name, put there by another user in a shared
folder or by another process writing the same target, is never written through, nor half written by two writers
that would then move each other's bytes into place.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

_EXCLUSIVE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)


def partial_name(path: Path) -> Path:
    """A fresh hidden name beside ``path`` for its bytes until they are whole: ``.NAME.<random>.partial``."""
    return path.with_name(f".{path.name}.{secrets.token_hex(8)}.partial")


def create_exclusive(path: Path) -> BinaryIO:
    """``path`` created new and opened for writing (permissions as the umask gives, like ``open``); FileExistsError
    when anything, a link included, is there already."""
    fd = os.open(path, _EXCLUSIVE, 0o666)
    return os.fdopen(fd, "wb")


@contextmanager
def partial_file(path: Path) -> Iterator[tuple[BinaryIO, Path]]:
    """A new temporary file beside ``path`` (``partial_name``), opened for writing, and its name; removed when the
    block raises. The caller moves it into place (``os.replace``) once it is whole."""
    partial = partial_name(path)
    try:
        with create_exclusive(partial) as out:
            yield out, partial
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


@contextmanager
def whole_file(path: Path) -> Iterator[BinaryIO]:
    """``path`` opened for writing under a temporary name beside it, put in its place when the block ends without an
    error and removed otherwise: a reader never takes half a file for a result. A device or pipe (not a regular
    file) is written directly."""
    if path.exists() and not path.is_file():
        with open(path, "wb") as out:
            yield out
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with partial_file(path) as (out, partial):
        yield out
    try:
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
