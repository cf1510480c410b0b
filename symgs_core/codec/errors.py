"""The one error a `.symgs` reader raises, with a machine-readable code."""

from __future__ import annotations

from typing import Literal

ArchiveErrorCode = Literal[
    "bad_magic",  # not a .symgs file
    "unsupported_version",  # a .symgs file of a format version this build cannot read
    "truncated",  # the file ends before the data its header promises
    "bad_checksum",  # the header or a section does not match its CRC32
    "bad_header",  # the header is not valid JSON or breaks the schema (types, ranges, layout, codec parameters)
    "limit_exceeded",  # a count or size above the reader's DecodeLimits, or more memory than its budget
    "disproportionate",  # more Gaussians, stored or expanded, than a file of its size may hold (DecodeLimits)
    "unsupported_codec",  # a section names a codec this build does not know
    "trailing_data",  # bytes after the last section
    "corrupt_section",  # a section's payload does not decode to what the header describes
]


class ArchiveError(ValueError):
    """A `.symgs` file that cannot be read; ``code`` says why (see ``ArchiveErrorCode``)."""

    def __init__(self, code: ArchiveErrorCode, message: str) -> None:
        super().__init__(code, message)  # both, so a pickled copy (Celery's failure hook) keeps the code
        self.code: ArchiveErrorCode = code
        self.message = message

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"
