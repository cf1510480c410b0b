"""Sections on one step whatever the step classes (``codec.classes.OneStep``): such a section decodes to what its codec
gives without classes while the others keep theirs, the header marks it, an archive none of whose sections takes the
classes is written without them, and readers refuse the mark where it cannot stand."""

from __future__ import annotations

import json

import pytest
import torch

from symgs_core.codec import ArchiveCodec, ArchiveContents, decode_archive, encode_archive, read_header
from symgs_core.codec.classes import OneStep
from symgs_core.codec.registry import ATTRIBUTE_NAMES
from symgs_core.codec.steps import QuantSteps
from symgs_core.pipeline.encode import write_archive
from symgs_core.pipeline.state import LevelState
from symgs_core.scene import GaussianScene
from tests.unit.test_archive_hostile import code_of, frame, split
from tests.unit.test_quantize import _random_scene

N = 400
EXTENT = 8.0


def _scene() -> GaussianScene:
    return _random_scene(N, 1, seed=5)


CLASSES = torch.arange(N) * 4 // N  # classes 0..3, in runs as the coding order leaves them
STEPS = QuantSteps().scaled(4.0)  # coarse enough that a class's multiple changes every section's values


def _archive(one_step: set[str], classes: torch.Tensor | None = CLASSES) -> bytes:
    codecs = STEPS.codecs(EXTENT)
    codecs = {name: OneStep(c) if name in one_step else c for name, c in codecs.items()}
    contents = ArchiveContents(_scene(), [], torch.zeros(N, 0, dtype=torch.bool), {}, classes)
    return encode_archive(contents, codec=ArchiveCodec("test-one-step", codecs))


@pytest.mark.parametrize("section", ATTRIBUTE_NAMES)
def test_a_one_step_section_decodes_as_without_classes_and_the_others_keep_theirs(section: str) -> None:
    classed = decode_archive(_archive(set())).stored.tensors()
    unclassed = decode_archive(_archive(set(), classes=None)).stored.tensors()
    data = _archive({section})
    mixed = decode_archive(data).stored.tensors()
    for name in ATTRIBUTE_NAMES:
        expected = unclassed[name] if name == section else classed[name]
        assert torch.equal(mixed[name], expected), name
        if name != "sh_rest" or section == "sh_rest":  # coarser classes decode elsewhere: the test can see them
            assert not torch.equal(classed[name], unclassed[name]), name
    marks = {s["name"]: s.get("classes") for s in read_header(data)["sections"]}
    assert marks == {name: False if name == section else None for name in marks}
    assert decode_archive(data).classes is not None and torch.equal(decode_archive(data).classes.long(), CLASSES)


def test_without_a_section_that_takes_them_the_classes_are_not_written() -> None:
    """The classes would cost their order alone: ``write_archive`` writes the state as without them, byte for
    byte."""
    state = LevelState.plain(_scene())
    codecs = STEPS.codecs(EXTENT)
    every = ArchiveCodec("test", {n: OneStep(c) if n in ATTRIBUTE_NAMES else c for n, c in codecs.items()})
    assert write_archive(state, {}, every, CLASSES) == write_archive(state, {}, ArchiveCodec("test", codecs))
    some = ArchiveCodec("test", {n: OneStep(c) if n == "means" else c for n, c in codecs.items()})
    assert decode_archive(write_archive(state, {}, some, CLASSES)).classes.any()


def _marked(section: str, value: object, version: int | None = None) -> bytes:
    header, body = split(_archive(set()))
    for entry in header["sections"]:
        if entry["name"] == section:
            entry["classes"] = value
    text = json.dumps(header, separators=(",", ":")).encode()
    return frame(text, body) if version is None else frame(text, body, version=version)


def test_the_mark_stands_only_as_false_on_an_attribute_from_version_6() -> None:
    for section, value, version in [("scales", True, None), ("scales", 0, None), ("bits", False, None),
                                    ("classes", False, None), ("scales", False, 5)]:  # fmt: skip
        assert code_of(_marked(section, value, version)) == "bad_header", (section, value, version)
