"""femcal calibrate imports without the cyclic garbage collector, then freezes what it built.

:class:`femcal.stages.calibrate.ImportCollector`: off inside, frozen and back on after
``resume``, unfrozen and as found on leaving; a process forked inside keeps it off.
"""

from __future__ import annotations

import gc
import multiprocessing

import pytest

from femcal.stages.calibrate import ImportCollector


@pytest.fixture
def collector_state():
    enabled = gc.isenabled()
    yield
    gc.unfreeze()
    if enabled:
        gc.enable()
    else:  # pragma: no cover - pytest runs with the collector on
        gc.disable()


def _report(conn) -> None:
    conn.send(gc.isenabled())
    conn.close()


def test_off_inside_frozen_after_resume_restored_on_leaving(collector_state):
    gc.enable()
    with ImportCollector() as collector:
        assert not gc.isenabled()
        collector.resume()
        assert gc.isenabled()
        assert gc.get_freeze_count() > 0  # what existed at resume is never scanned again
    assert gc.isenabled()
    assert gc.get_freeze_count() == 0


def test_left_off_when_it_was_off(collector_state):
    gc.disable()
    with ImportCollector() as collector:
        collector.resume()
        assert not gc.isenabled()
    assert not gc.isenabled()


def test_restored_when_the_body_fails_before_resume(collector_state):
    gc.enable()
    with pytest.raises(RuntimeError, match="store"), ImportCollector():
        raise RuntimeError("the store failed")
    assert gc.isenabled() and gc.get_freeze_count() == 0


@pytest.mark.skipif(
    "fork" not in multiprocessing.get_all_start_methods(), reason="the MLflow process is forked"
)
def test_a_process_forked_inside_keeps_it_off(collector_state):
    gc.enable()
    ctx = multiprocessing.get_context("fork")
    with ImportCollector() as collector:
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_report, args=(child,))
        process.start()
        child.close()
        assert parent.recv() is False
        process.join(30)
        collector.resume()
    assert process.exitcode == 0
