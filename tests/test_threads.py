"""The thread count of torch, OpenMP and BLAS: the free cores, or what the user set.

And the calibration's progress bar, which says where a batch is while it works.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from femcal.threads import THREAD_VARIABLES, choose_threads, limit_threads


@pytest.mark.parametrize(
    ("cpus", "load", "threads"),
    [
        (2, 0.0, 2),  # a quiet machine: every core
        (2, 0.3, 2),  # a little background work is no busy core
        (2, 1.0, 1),  # one program on one of two cores (the CalculiX campaign)
        (2, 0.7, 1),
        (2, 2.0, 1),  # both cores busy: still one thread, never none
        (2, 9.5, 1),
        (8, 2.6, 5),
        (1, 0.0, 1),
        (4, float("nan"), 4),  # no load known: every core
        (0, 0.0, 1),
    ],
)
def test_the_threads_are_the_free_cores(cpus, load, threads):
    assert choose_threads(cpus, load) == threads


def test_the_load_is_the_busy_share_of_the_cpu_time_now(monkeypatch):
    """The busy cores over the sample, from two readings of /proc/stat: a program spinning on
    one of two cores reads 1 (a load average would still count a command that just ended)."""
    import femcal.threads as threads

    readings = iter([(1000.0, 4000.0), (1050.0, 4100.0)])  # busy, total ticks
    monkeypatch.setattr(threads, "_cpu_times", lambda: next(readings))
    monkeypatch.setattr(threads.os, "cpu_count", lambda: 2)
    assert threads.machine_load(sample_s=0.0) == pytest.approx(1.0)


def test_the_load_of_this_machine_is_a_count_of_cores():
    """Read for real: between no core and every core."""
    import os

    from femcal.threads import machine_load

    load = machine_load(sample_s=0.02)
    assert 0.0 <= load <= (os.cpu_count() or 1) + 1e-9


def test_the_count_chosen_is_set_for_every_thread_pool():
    environ: dict[str, str] = {}
    choice = limit_threads(environ, cpus=2, load=1.1)
    assert choice.threads == 1 and not choice.user
    assert {k: environ[k] for k in THREAD_VARIABLES} == dict.fromkeys(THREAD_VARIABLES, "1")
    assert "on 1 thread of 2 cores (1.10 cores busy" in choice.describe()


@pytest.mark.parametrize("variable", THREAD_VARIABLES)
def test_a_count_the_user_set_wins(variable):
    environ = {variable: "3"}
    choice = limit_threads(environ, cpus=2, load=1.5)
    assert environ == {variable: "3"}  # nothing else set either
    assert choice.threads is None and choice.user == {variable: "3"}
    assert f"threads as set by the user ({variable}=3)" in choice.describe()


def test_fewer_threads_than_cores_are_said(caplog):
    with caplog.at_level(logging.DEBUG, logger="femcal.threads"):
        limit_threads({}, cpus=2, load=1.0)
        limit_threads({}, cpus=2, load=0.0)
    levels = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert levels[0][0] == logging.INFO and "on 1 thread of 2 cores" in levels[0][1]
    assert levels[1][0] == logging.DEBUG and "on 2 threads of 2 cores" in levels[1][1]


def test_the_command_line_chooses_before_the_stage_runs(monkeypatch):
    """``femcal`` sets the count once, before the command's work."""
    import os

    import torch

    import femcal.cli as cli

    for key in THREAD_VARIABLES:
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setattr("femcal.threads.machine_load", lambda: 1.0)
    monkeypatch.setattr("femcal.threads.machine_cpus", lambda: 2)
    seen = {}

    def dispatch(args, params):
        seen.update({k: os.environ.get(k) for k in THREAD_VARIABLES}, torch=torch.get_num_threads())

    monkeypatch.setattr(cli, "dispatch", dispatch)
    monkeypatch.setattr(cli, "load_params", lambda path, **_: {})
    before = torch.get_num_threads()
    try:
        assert cli.main(["prepare"]) == 0
    finally:
        torch.set_num_threads(before)
    assert seen == dict.fromkeys(THREAD_VARIABLES, "1") | {"torch": 1}


def test_the_bar_shows_the_step_of_a_batch(curve_model_free, monkeypatch):
    """One chunk of 6 specimens: the bar says which Gauss-Newton iteration runs, and how many
    specimens have settled, while the chunk works."""
    from femcal.calibration import calibrate, progress

    steps = []
    real = progress.report_step

    def spy(step, *, settled, of):
        steps.append((step, settled, of))
        real(step, settled=settled, of=of)

    monkeypatch.setattr("femcal.calibration.gauss_newton.report_step", spy)
    model, rom = curve_model_free
    calibrate(model, rom, method="pgd", progress=True, options={"n_bank_uniform": 64})
    assert steps and steps[0][0].startswith("Gauss-Newton iteration 1/")
    assert all(of == len(rom) and 0 <= settled <= of for _, settled, of in steps)
    # no bar open: the calibrator reports to nobody
    calibrate(model, rom, method="pgd", progress=False, options={"n_bank_uniform": 64})


@pytest.fixture
def curve_model_free():
    """A tiny surrogate's curve model and six curves it produces."""
    from femcal.calibration import SurrogateCurveModel
    from femcal.surrogates.nn import NeuralSurrogate

    from synth import study_space, tidy_table

    table = tidy_table(24, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(16,), max_epochs=3, patience=3, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    model = SurrogateCurveModel(surrogate, (1.0, 2.0, 3.0, 4.0, 5.0))
    x = model.space.sample_uniform(6, np.random.default_rng(1))
    return model, model.predict(x)


def test_a_bar_opens_only_after_its_delay(monkeypatch, capsys):
    from femcal.calibration import progress

    with progress.specimen_bar(4, "calibrate (pgd)", enabled=True) as bar:
        progress.report_step("Gauss-Newton iteration 1/12", settled=1, of=4)
        bar.update(4)
        assert bar.bar is None  # done within the delay: no bar at all
    monkeypatch.setattr(progress, "BAR_DELAY", 0.0)
    with progress.specimen_bar(4, "calibrate (pgd)", enabled=True) as bar:
        progress.report_step("Gauss-Newton iteration 1/12", settled=1, of=4)
        assert bar.bar is not None
        assert bar.bar.postfix == "Gauss-Newton iteration 1/12: 1/4 specimens settled"
        bar.update(4)
        assert bar.bar.n == 4
    with progress.specimen_bar(4, "calibrate (pgd)", enabled=False) as bar:
        assert bar is None
        progress.report_step("Gauss-Newton iteration 1/12", settled=1, of=4)  # to nobody
