"""Work set aside for the report: computed on a thread of its own at idle priority, coding its streams there alone,
and read back as if computed in place."""

from __future__ import annotations

import os
import sys
import threading

import pytest

from symgs_core.cameras import COORDINATE_CONVENTION
from symgs_core.codec.section import coding_alone, coding_pool
from symgs_core.config import CompressConfig
from symgs_core.pipeline import compress
from symgs_core.pipeline.aside import IDLE_NICENESS, Aside
from symgs_core.pipeline.encode import float32_size
from symgs_core.pipeline.state import LevelState
from symgs_core.synthetic import synthetic_scene


def _where() -> tuple[int, int, list[str]]:
    """This thread's id, its niceness, and the threads the coding pool runs four tasks on."""
    tid = threading.get_native_id()
    names = list(coding_pool().map(lambda _: threading.current_thread().name, range(4)))
    return tid, os.getpriority(os.PRIO_PROCESS, tid), names


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="threads have their own niceness on Linux")
def test_set_aside_work_runs_on_its_own_idle_thread_and_codes_there_alone() -> None:
    aside = Aside()
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    aside.start("where", _where)
    tid, niceness, names = aside.result("where", pytest.fail)
    assert tid != threading.get_native_id()
    assert niceness == IDLE_NICENESS
    assert set(names) == {"aside"}
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own  # the job's threads keep theirs
    assert all(name.startswith("coding") for name in _where()[2])  # outside, the shared pool


def test_a_result_is_read_once_and_one_never_started_is_computed_in_place() -> None:
    aside = Aside()
    assert aside.result("never", threading.get_native_id) == threading.get_native_id()
    aside.start("value", lambda a, b: a * b, 6, 7)
    assert aside.result("value", pytest.fail) == 42
    assert aside.result("value", lambda: "again") == "again"


def test_an_error_reaches_the_reader() -> None:
    def broken() -> None:
        raise ValueError("no such archive")

    aside = Aside()
    aside.start("broken", broken)
    with pytest.raises(ValueError, match="no such archive"):
        aside.result("broken", pytest.fail)


def test_coding_alone_keeps_tasks_and_their_errors_on_the_calling_thread() -> None:
    with coding_alone():
        assert {name for name in _where()[2]} == {threading.current_thread().name}
        with coding_alone():
            pass
        assert coding_pool().submit(lambda: 1 / 0).exception().__class__ is ZeroDivisionError
    assert all(name.startswith("coding") for name in _where()[2])


def test_the_report_is_the_same_whether_its_archives_were_set_aside_or_not(monkeypatch) -> None:
    scene = synthetic_scene("global", n=900, seed=6, sh_degree=1).scene
    config = CompressConfig.for_preset(
        "balanced", iterations=10, train_views=4, fit_views=2, eval_views=2, resolution=64, eval_resolution=64,
        max_levels=1, pictures=False,
    )  # fmt: skip
    aside = compress(scene, config=config)
    monkeypatch.setattr(Aside, "start", lambda self, name, fn, *args: None)
    in_place = compress(scene, config=config)
    sizes = lambda result: [(s.stage, s.bytes_before, s.bytes_after, s.removed) for s in result.report.stages]  # noqa: E731
    assert aside.archive == in_place.archive
    assert sizes(aside) == sizes(in_place) and [s.stage for s in aside.report.stages][-1] == "sh_reduction"
    assert aside.report.ratio_to_baseline == in_place.report.ratio_to_baseline
    meta = {"input_gaussians": len(scene), "sh_degree": scene.sh_degree, "coordinate_convention": COORDINATE_CONVENTION}
    assert aside.report.stages[0].bytes_before == float32_size(LevelState.plain(scene), meta)
