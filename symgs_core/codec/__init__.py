"""The `.symgs` archive: container format, section codecs, level masks and the stored set's coding order."""

from __future__ import annotations

from .archive import (
    ArchiveContents,
    DecodeLimits,
    decode_archive,
    encode_archive,
    expand_archive,
    expanded_count,
    read_header,
    section_bytes,
)
from .container import FORMAT_VERSION, MAGIC
from .errors import ArchiveError, ArchiveErrorCode
from .order import coding_order, morton_codes
from .registry import (
    SECTION_NAMES,
    ArchiveCodec,
    archive_codec,
    archive_codec_names,
    register_archive_codec,
    register_section_codec,
    section_codec,
)
from .section import EncodedSection, SectionCodec
from .steps import QuantSteps  # registers the quantising section codecs for readers

__all__ = [
    "FORMAT_VERSION",
    "MAGIC",
    "QuantSteps",
    "SECTION_NAMES",
    "ArchiveCodec",
    "ArchiveContents",
    "ArchiveError",
    "ArchiveErrorCode",
    "DecodeLimits",
    "EncodedSection",
    "SectionCodec",
    "archive_codec",
    "archive_codec_names",
    "coding_order",
    "decode_archive",
    "encode_archive",
    "expand_archive",
    "expanded_count",
    "morton_codes",
    "read_header",
    "register_archive_codec",
    "register_section_codec",
    "section_bytes",
    "section_codec",
]
