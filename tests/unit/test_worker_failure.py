"""A job's failure names what was wrong with its input, in the process that records it: Celery hands the failure
hook a pickled copy of the exception, which must keep its code."""

from __future__ import annotations

import pytest
from celery.utils.serialization import get_pickleable_exception

from symgs_core.codec import ArchiveError
from symgs_core.datasets import DatasetError
from symgs_core.ply_header import PlyError
from worker.runner import JobInputError, failure_of


@pytest.mark.parametrize(
    "exc, code",
    [
        (PlyError("non_finite", "scene.ply: NaN or infinite values in x (1 values)"), "non_finite"),
        (JobInputError("bad_params", "params: resolution must be in 16..4096, got 8"), "bad_params"),
        (DatasetError("bad_transforms", "transforms_train.json: no frames"), "bad_transforms"),
    ],
)
def test_input_errors_keep_their_code_and_message_through_celery(exc: ValueError, code: str) -> None:
    carried = get_pickleable_exception(exc)
    assert type(carried) is type(exc)
    assert failure_of(carried) == (code, str(exc))
    assert not str(exc).startswith(code)  # the message is the sentence, the code travels beside it


def test_other_errors_are_internal() -> None:
    # An archive the worker wrote itself failing to decode is our fault, not the client's input.
    assert failure_of(get_pickleable_exception(ArchiveError("truncated", "x")))[0] == "internal_error"
    assert failure_of(get_pickleable_exception(RuntimeError()))[0] == "internal_error"
    assert failure_of(RuntimeError()) == ("internal_error", "RuntimeError")
