"""The codec tables: section codecs by name (what readers look up) and archive codecs (what writers choose).

An archive codec names one section codec for every section of the archive. Section codecs are registered once, at
import, and are then readable by every reader of this build, since each section records the name of the codec
that wrote it and everything that codec needs to decode it. A writer passes its ``ArchiveCodec`` to the encoder;
a few fixed ones (lossless, float16) are also known by name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from .classes import CLASSES, unwrapped
from .errors import ArchiveError
from .floats import FLOAT16, FLOAT32
from .masks import MASKS
from .section import SectionCodec, SectionKind

# Every archive holds these sections, in this order: the attributes, the level bit matrix (``bits``) and the stored
# Gaussians' step classes (``classes``), which archives of format versions 1 and 2 do not hold (all class 0).
ATTRIBUTE_NAMES = ("means", "quats", "scales", "opacities", "sh_dc", "sh_rest")
SECTION_NAMES = (*ATTRIBUTE_NAMES, "bits", "classes")
SECTION_KINDS: dict[str, SectionKind] = {**{name: "float32" for name in ATTRIBUTE_NAMES}, "bits": "bool",
                                         "classes": "uint8"}  # fmt: skip

_SECTION_CODECS: dict[str, SectionCodec] = {}
_ARCHIVE_CODECS: dict[str, ArchiveCodec] = {}


def register_section_codec(codec: SectionCodec) -> None:
    """Make ``codec`` readable under ``codec.name``; a name already taken by a different codec is a ValueError."""
    known = _SECTION_CODECS.get(codec.name)
    if known is not None and type(known) is not type(codec):
        raise ValueError(f"section codec name {codec.name!r} is already taken by {type(known).__name__}")
    if codec.kind not in ("float32", "bool", "uint8"):
        raise ValueError(f"section codec {codec.name!r} has kind {codec.kind!r}, expected 'float32', 'bool' or 'uint8'")
    _SECTION_CODECS.setdefault(codec.name, codec)


@dataclass(frozen=True)
class ArchiveCodec:
    """What writes an archive: a name (recorded in the header, for people) and the codec of every section.

    A job builds its own from its fitted steps (``QuantSteps.archive_codec``) and passes it to the writer; nothing
    global changes. Readers need nothing of it: each section names its codec and carries its own parameters.
    """

    name: str
    sections: Mapping[str, SectionCodec]

    def __post_init__(self) -> None:
        if set(self.sections) != set(SECTION_NAMES):
            raise ValueError(
                f"archive codec {self.name!r} covers sections {sorted(self.sections)}, expected {sorted(SECTION_NAMES)}"
            )
        for section, given in self.sections.items():
            codec, classed = unwrapped(given)
            if not classed and section not in ATTRIBUTE_NAMES:
                raise ValueError(f"archive codec {self.name!r}: section {section!r} has no step classes to ignore")
            if codec.kind != SECTION_KINDS[section]:
                raise ValueError(
                    f"archive codec {self.name!r}: {codec.name!r} ({codec.kind}) cannot hold section {section!r}"
                )
            known = _SECTION_CODECS.get(codec.name)
            if known is None or type(known) is not type(codec):
                raise ValueError(f"archive codec {self.name!r}: section codec {codec.name!r} is not readable")


def register_archive_codec(name: str, codecs: Mapping[str, SectionCodec]) -> ArchiveCodec:
    """Make archive codec ``name`` writable by name, once, when a module is imported: ``codecs`` maps every
    section name to the codec that writes it (its section codecs become readable)."""
    for codec in codecs.values():
        register_section_codec(codec)
    _ARCHIVE_CODECS[name] = ArchiveCodec(name, dict(codecs))
    return _ARCHIVE_CODECS[name]


def archive_codec(codec: str | ArchiveCodec) -> ArchiveCodec:
    """The archive codec named ``codec`` (or ``codec`` itself); ValueError naming the known ones otherwise."""
    if isinstance(codec, ArchiveCodec):
        return codec
    if codec not in _ARCHIVE_CODECS:
        raise ValueError(f"unknown archive codec {codec!r}; known: {sorted(_ARCHIVE_CODECS)}")
    return _ARCHIVE_CODECS[codec]


def archive_codec_names() -> list[str]:
    return sorted(_ARCHIVE_CODECS)


def section_codec(name: str, section: str) -> SectionCodec:
    """The reader's codec for ``section`` written by ``name``; ArchiveError if unknown or of the wrong kind."""
    codec = _SECTION_CODECS.get(name)
    if codec is None:
        known = sorted(_SECTION_CODECS)
        raise ArchiveError("unsupported_codec", f"section {section!r} uses codec {name!r}; known: {known}")
    if codec.kind != SECTION_KINDS[section]:
        raise ArchiveError("bad_header", f"section {section!r} cannot be stored by codec {name!r} ({codec.kind})")
    return codec


# Bit-exact float32: the reference every lossy codec is measured against.
register_archive_codec("lossless", {name: FLOAT32 for name in ATTRIBUTE_NAMES} | {"bits": MASKS, "classes": CLASSES})
# float16 + zstd: about half the size of "lossless" with no quantiser to tune; rounds every attribute.
register_archive_codec("float16", {name: FLOAT16 for name in ATTRIBUTE_NAMES} | {"bits": MASKS, "classes": CLASSES})
