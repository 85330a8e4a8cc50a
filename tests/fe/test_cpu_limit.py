"""The solver's time limit in CPU seconds (femcal.fe.cpu_limit)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from femcal.fe.cpu_limit import WALL_FACTOR, CpuLimit, cpu_seconds

pytestmark = pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs /proc")


def _child(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code])


def test_cpu_seconds_counts_this_process_work():
    before = cpu_seconds(os.getpid())
    end = time.process_time() + 0.2
    while time.process_time() < end:
        pass
    # /proc counts in clock ticks (1/100 s): 0.2 s of work shows as at least 0.15 s.
    assert cpu_seconds(os.getpid()) - before >= 0.15


def test_a_gone_process_has_no_cpu_seconds():
    proc = _child("pass")
    proc.wait()
    assert cpu_seconds(proc.pid) is None


def test_a_busy_child_is_stopped_on_its_cpu_seconds():
    proc = _child("while True: pass")
    with CpuLimit(proc, 0.3) as limit:
        proc.wait(timeout=60)
    assert limit.reason == "0.3 s of CPU time"
    assert proc.returncode == -9


def test_a_child_that_waits_is_stopped_on_the_wall_clock_safety_limit():
    proc = _child("import time; time.sleep(600)")
    start = time.monotonic()
    with CpuLimit(proc, 0.05) as limit:
        proc.wait(timeout=60)
    assert limit.reason == f"{0.05 * WALL_FACTOR:g} s of wall-clock time"
    assert time.monotonic() - start >= 0.05 * WALL_FACTOR


def test_a_child_that_ends_in_time_is_left_alone():
    proc = _child("pass")
    with CpuLimit(proc, 30.0) as limit:
        proc.wait(timeout=60)
    assert limit.reason is None and proc.returncode == 0
