"""`symgs compress` progress without a terminal: plain lines, and more of them while the pipeline is silent."""

from __future__ import annotations

import io
import re
import time

from rich.console import Console

from service.cli.local_progress import LocalProgress
from symgs_core.progress import ProgressEvent

LINE = re.compile(r"^compress: (\w+)(?: L(\d+))? +(\d+)%  elapsed (\d+):(\d\d)  left (-:--|\d+:\d\d)  (.*)$")


def test_plain_lines_per_stage_and_while_a_step_runs_long():
    out = io.StringIO()
    with LocalProgress(Console(file=out, force_terminal=False), line_every_s=0.5) as progress:
        progress(ProgressEvent("load", None, 0.0, "reading"))
        progress(ProgressEvent("load", None, 0.01, "reading"))  # same stage, within 0.5 s: no line
        progress(ProgressEvent("levels", 0, 0.2, "level 0: step 1/10"))
        time.sleep(1.3)  # the pipeline says nothing: the ticker prints the last report again, with the time moving
    lines = [LINE.match(line) for line in out.getvalue().splitlines()]
    assert all(lines) and len(lines) >= 3, out.getvalue()
    assert [(m.group(1), m.group(2), m.group(3)) for m in lines[:2]] == [("load", None, "0"), ("levels", "0", "20")]
    assert {(m.group(1), m.group(3), m.group(7)) for m in lines[2:]} == {("levels", "20", "level 0: step 1/10")}
    assert int(lines[-1].group(4)) * 60 + int(lines[-1].group(5)) >= 1


def test_quiet_prints_nothing():
    out = io.StringIO()
    with LocalProgress(Console(file=out, force_terminal=False), quiet=True, line_every_s=0.0) as progress:
        progress(ProgressEvent("load", None, 0.5, "reading"))
    assert out.getvalue() == ""
