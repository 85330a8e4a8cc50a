"""What the calibration's and the diagnosis' figures share: names, bands, worker processes.

* :data:`LOAD_CASE_LABELS`: the load cases as the figures name them;
* :func:`dense_grid`: the moments continuous curves are drawn at;
* :func:`noise_band`: the ± 2σ band around a curve (or zero);
* :func:`plot_workers` and :func:`fork_map`: drawing many independent figures in worker
  processes, as many as the cores free (never more: a worker beside a busy core slows every
  figure down), forked from the process that holds the data.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

import numpy as np

from femcal.threads import THREAD_VARIABLES, choose_threads, machine_cpus, machine_load

#: Load-case names in figures.
LOAD_CASE_LABELS = {
    "Flexion": "flexion",
    "Extension": "extension",
    "LateralBending": "lateral bending",
    "AxialRotation": "axial rotation",
}

#: Fewest figures per worker process: below, a worker costs more than it saves.
MIN_FIGURES_PER_WORKER = 8


def dense_grid(moments: Sequence[float], q: int = 48) -> np.ndarray:
    """``q`` log-spaced moments spanning the measured grid (and every grid moment itself)."""
    m = np.asarray(moments, dtype=float)
    grid = np.geomspace(m.min(), m.max(), q)
    return np.unique(np.concatenate([grid, m]))


def noise_band(ax: Any, x: np.ndarray, centre: np.ndarray, sigma: Any, **style: Any) -> Any:
    """Fill ``centre ± 2 sigma`` over ``x`` on ``ax`` (no outline); returns the collection.

    ``sigma``: a scalar or an array like ``x``; ``style``: ``color``, ``alpha``, ``label``...
    """
    lo, hi = centre - 2 * np.asarray(sigma), centre + 2 * np.asarray(sigma)
    return ax.fill_between(x, lo, hi, lw=0, **style)


def free_cores() -> int:
    """The cores this command may keep busy: the thread count chosen when it started
    (:func:`femcal.threads.limit_threads` sets :data:`~femcal.threads.THREAD_VARIABLES`; a
    count the user set there counts too), else the cores free now."""
    for key in THREAD_VARIABLES:
        value = os.environ.get(key, "").strip()
        if value.isdigit() and int(value) > 0:
            return min(int(value), machine_cpus())
    return choose_threads(machine_cpus(), machine_load())


def plot_workers(n_figures: int, cores: int | None = None) -> int:
    """Processes to draw ``n_figures`` with: the free cores (:func:`free_cores`, or
    ``cores``), at most one per :data:`MIN_FIGURES_PER_WORKER` figures, at least 1."""
    cores = free_cores() if cores is None else int(cores)
    return max(1, min(cores, n_figures // MIN_FIGURES_PER_WORKER))


def chunks(n: int, workers: int) -> list[range]:
    """``range(n)`` cut into about ``4 * workers`` contiguous pieces (a worker that is done
    takes the next one; each piece reuses the worker's figure)."""
    size = max(1, -(-n // (4 * workers)))
    return [range(i, min(n, i + size)) for i in range(0, n, size)]


def fork_map(
    fn: Callable[[range], Any], pieces: Sequence[range], workers: int
) -> Iterator[tuple[range, Any]]:
    """``(piece, fn(piece))`` for every piece, in ``workers`` processes forked from this one
    (they read what this process holds), as each finishes; in this process where ``workers``
    is 1 or the platform does not fork."""
    if workers < 2 or len(pieces) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        for piece in pieces:
            yield piece, fn(piece)
        return
    ctx = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
        futures = {pool.submit(fn, piece): piece for piece in pieces}
        for future in as_completed(futures):
            yield futures[future], future.result()


def progress_over(pieces: Iterable[tuple[range, Any]], total: int, desc: str, show: bool):
    """``pieces`` as they come, with a bar (stderr) over the ``total`` figures when ``show``."""
    if not show or total < 2:
        yield from pieces
        return
    from tqdm.auto import tqdm

    with tqdm(total=total, desc=desc, unit="specimen") as bar:
        for piece, value in pieces:
            bar.update(len(piece))
            yield piece, value
