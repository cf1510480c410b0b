"""Files the command line and the HTTP client write for a user: whole, or not at all."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


@contextmanager
def whole_file(path: Path) -> Iterator[BinaryIO]:
    """``path`` opened for writing under a temporary name beside it, put in its place when the block ends without an
    error and removed otherwise: a reader never takes half a file for a result. A device or pipe (not a regular
    file) is written directly."""
    direct = path.exists() and not path.is_file()
    partial = path if direct else path.with_name(f".{path.name}.partial")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(partial, "wb") as out:
            yield out
        if not direct:
            os.replace(partial, path)
    finally:
        if not direct:
            partial.unlink(missing_ok=True)
