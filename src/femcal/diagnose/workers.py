"""The specimens of a diagnosis shared out over worker processes.

Every step after the disc-alone fit works specimen by specimen (its fits are batched only to be
fast), and each model's random draws come from a generator of its own
(:meth:`femcal.diagnose.state.DiagnosisState.model_rng`). So the specimens can be diagnosed in
groups, one worker process per core. A specimen's fits then share their batches with other
specimens; where two starts or two models are nearly tied, batches of another size (and their
float32 rounding) can send the search another way, so a verdict can differ with the number of
workers (docs/anatomy-cohorts.md, *Time*). The groups interleave the specimens
(``i % workers``), so that a cohort sorted by class shares its hard specimens out evenly.

A caller can have each worker do more with its group as soon as it is diagnosed
(:func:`each_group`): ``femcal diagnose`` draws the group's figures there, while the other
worker still diagnoses its own.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from femcal.diagnose.result import Diagnosis
from femcal.diagnose.state import DiagnosisState
from femcal.effects.terms import Model

#: Fewest specimens per worker: below, the fits' batches are too small to pay for a process.
MIN_ROWS = 8

#: What the workers read: (state, the function diagnosing one group, its keywords), set before
#: they fork.
_SHARED: tuple[DiagnosisState, Callable[..., Diagnosis], dict[str, Any]] | None = None

#: What each worker calls with its group's diagnosis (:func:`each_group`).
_EACH_GROUP: list[Callable[[Diagnosis, np.ndarray], None]] = []


@contextlib.contextmanager
def each_group(fn: Callable[[Diagnosis, np.ndarray], None]) -> Iterator[None]:
    """Within the block, each worker process of :func:`in_workers` calls ``fn(diag, rows)``
    as soon as its group is diagnosed: ``diag`` the group's :class:`Diagnosis`, ``rows`` (k,)
    the group's specimen indices in the cohort (``diag.specimens[j]`` is specimen
    ``rows[j]``). Not called where the specimens are diagnosed in this process (one group);
    ``fn``'s errors fail the diagnosis."""
    _EACH_GROUP.append(fn)
    try:
        yield
    finally:
        _EACH_GROUP.remove(fn)


def available_cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def groups(n: int, workers: int | None) -> list[np.ndarray]:
    """Specimen indices per worker: ``i % k`` for ``k`` workers, at most ``workers`` (None:
    :func:`available_cpus`) and at least :data:`MIN_ROWS` specimens each."""
    k = available_cpus() if workers is None else int(workers)
    k = max(1, min(k, n // MIN_ROWS))
    return [np.arange(j, n, k) for j in range(k)]


def _one(j: int) -> Diagnosis:
    import torch

    torch.set_num_threads(1)  # one process per core
    state, run, keywords = _SHARED
    keywords = dict(keywords)
    rows = groups(state.n, keywords.pop("_workers"))[j]
    sub = state.rows(rows)
    disc = sub.per_spec[0][Model()][0]  # their disc-alone fit, renumbered
    diag = run(sub, disc=disc, **keywords)
    for fn in _EACH_GROUP:
        fn(diag, rows)
    return diag


def in_workers(
    state: DiagnosisState,
    run: Callable[..., Diagnosis],
    workers: int | None,
    **keywords: Any,
) -> Diagnosis | None:
    """``run(sub_state, disc=sub_disc, **keywords)`` for each group of specimens (``sub_disc``
    their disc-alone fit, which ``state`` holds) in a worker process that forks from this one,
    merged into one :class:`Diagnosis` in the specimens' order; None where one group would hold
    them all (or the platform does not fork)."""
    parts = groups(state.n, workers)
    if len(parts) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        return None
    global _SHARED
    _SHARED = (state, run, dict(keywords, _workers=workers))
    try:
        ctx = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(len(parts), mp_context=ctx) as pool:
            results = list(pool.map(_one, range(len(parts))))
    finally:
        _SHARED = None
    specimens: list[Any] = [None] * state.n
    for rows, diag in zip(parts, results):
        for i, sd in zip(rows, diag.specimens):
            specimens[int(i)] = sd
    merged = results[0]
    merged.specimens = specimens
    return merged
