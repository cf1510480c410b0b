"""The heap during a job: a freed array stays in the heap for the next one, and goes back to the system after it."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

LIBC, VERSION = platform.libc_ver()
pytestmark = pytest.mark.skipif(
    LIBC != "glibc" or tuple(map(int, VERSION.split(".")[:2])) < (2, 33),
    reason="the heap's settings are glibc's; its accounts (mallinfo2) since 2.33",
)

# Run in a fresh interpreter: the figures depend on what the heap already holds. glibc's own accounts (mallinfo2):
# hblkhd, the bytes in blocks mapped on their own; fordblks, the free bytes the heap keeps.
PROBE = r"""
import ctypes, json, os
import numpy as np
from symgs_core import heap

MB = 1 << 20
FIELDS = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")

class Info(ctypes.Structure):
    _fields_ = [(f, ctypes.c_size_t) for f in FIELDS]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info

def accounts(make):
    before = libc.mallinfo2()
    array = make()
    during = libc.mallinfo2()
    del array
    after = libc.mallinfo2()
    return {"mapped": during.hblkhd - before.hblkhd, "free_after": after.fordblks}

def resident():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

out = {"outside": accounts(lambda: np.ones(64 * MB // 8))}
with heap.kept():
    out["inside"] = accounts(lambda: np.ones(64 * MB // 8))
    with heap.kept():  # a nested job leaves the heap as it is
        pass
    out["nested"] = accounts(lambda: np.ones(256 * MB // 8))
    out["kept_resident"] = resident()
out["after_resident"] = resident()
out["outside_again"] = accounts(lambda: np.ones(64 * MB // 8))
print(json.dumps(out))
"""


def test_inside_a_job_a_freed_array_stays_in_the_heap_and_after_it_the_memory_goes_back():
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True)
    out = json.loads(done.stdout)
    mb = 1 << 20
    assert out["outside"]["mapped"] >= 64 * mb  # by default glibc maps a block this large on its own ...
    assert out["outside"]["free_after"] < 64 * mb  # ... and unmaps it when freed: its pages fault in again next time
    for inside, size in ((out["inside"], 64 * mb), (out["nested"], 256 * mb)):
        assert inside["mapped"] < mb  # from the heap
        assert inside["free_after"] >= size  # and kept there for the next array
    assert out["kept_resident"] - out["after_resident"] > 200 * mb  # the free pages went back when the job left
    assert out["outside_again"]["mapped"] >= 64 * mb  # the defaults are back


def test_a_job_runs_with_the_heap_kept_and_leaves_it_as_it_found_it():
    from symgs_core import heap
    from symgs_core.config import CompressConfig
    from symgs_core.pipeline import compress
    from symgs_core.synthetic import synthetic_scene
    from symgs_core.warm import WARM_JOB

    seen: list[int] = []
    scene = synthetic_scene("global", n=600, seed=1, sh_degree=1).scene
    config = CompressConfig.for_preset("balanced", **WARM_JOB)
    compress(scene, config=config, progress=lambda *_: seen.append(heap._jobs))
    assert seen and set(seen) == {1}
    assert heap._jobs == 0


# The main thread allocates and frees 256 MB in blocks below the mmap threshold (a rung's trial encodes), then two
# threads do as much at once (the coding pool's layouts), then the main thread again: at most 512 MB are live at
# any time. The process's peak above its start, in MB.
ARENAS = r"""
import sys, threading
import numpy as np
from symgs_core import heap

MB = 1 << 20

def peak():
    return next(int(line.split()[1]) << 10 for line in open("/proc/self/status") if line.startswith("VmHWM"))

def churn(together=None):
    blocks = [np.ones(16 * MB // 8) for _ in range(16)]
    if together is not None:
        together.wait()
    del blocks

if sys.argv[1] == "glibc":
    heap.one_arena = lambda: None
with heap.kept():
    start = peak()
    churn()
    both = threading.Barrier(2)
    threads = [threading.Thread(target=churn, args=(both,)) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    churn()
    print((peak() - start) // MB)
"""


@pytest.mark.parametrize("arenas", ["one", "glibc"])
def test_what_one_thread_of_a_job_freed_serves_another(arenas):
    """With one arena the threads reuse what the main thread freed, and it theirs: the peak is what was live at
    once. With glibc's arenas (the oracle that the probe sees the difference) each new thread's arena takes its
    own memory beside the main heap's freed 256 MB."""
    done = subprocess.run([sys.executable, "-c", ARENAS, arenas], capture_output=True, text=True, check=True)
    peak = int(done.stdout)
    assert peak < 600 if arenas == "one" else peak > 700
