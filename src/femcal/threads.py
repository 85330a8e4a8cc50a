"""How many threads femcal's numerical libraries use: the cores free on this machine.

torch, OpenMP and the BLAS libraries (MKL, OpenBLAS) start one thread per core by default,
and their threads wait for each other by spinning. When another program keeps a core busy, a
thread that shares its core stalls the others at every step: a calibration on all cores then
runs several times slower than on the free ones alone. :func:`limit_threads`, called once by
the command line before anything heavy is imported, sets the thread count of all of them to
the cores free when the command starts (:func:`choose_threads`); a thread count the user set
wins.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections.abc import MutableMapping
from dataclasses import dataclass

logger = logging.getLogger(__name__)

#: The variables the thread pools read: OpenMP's (torch's intra-op threads), MKL's, OpenBLAS'.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")

#: A core counts as busy from this much load on (a program on one core shows about 1).
BUSY_LOAD = 0.5
#: Seconds over which :func:`machine_load` measures the busy cores.
LOAD_SAMPLE_S = 0.05


def choose_threads(cpus: int, load: float) -> int:
    """The threads to use on ``cpus`` cores of which ``load`` are busy: the free ones.

    Parameters
    ----------
    cpus : int
        The cores this process may run on (:func:`os.sched_getaffinity`).
    load : float
        The cores other programs keep busy (:func:`machine_load`). Each full core of load
        counts once it reaches :data:`BUSY_LOAD` of a core (0.4 counts none, 0.6 one, 1.5
        two).

    Returns
    -------
    int
        ``cpus`` minus the busy cores, at least 1 and at most ``cpus``.
    """
    cpus = max(1, int(cpus))
    load = float(load) if math.isfinite(load) and load > 0 else 0.0
    busy = math.floor(load + 1.0 - BUSY_LOAD)
    return max(1, min(cpus, cpus - busy))


def machine_cpus() -> int:
    """The cores this process may run on (its affinity; all cores where that is unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _cpu_times() -> tuple[float, float] | None:
    """The machine's busy and total CPU time so far, in clock ticks (None without /proc)."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            fields = [float(x) for x in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 5:
        return None
    idle = fields[3] + fields[4]  # idle and iowait
    return sum(fields[:8]) - idle, sum(fields[:8])


def machine_load(sample_s: float = LOAD_SAMPLE_S) -> float:
    """The cores other programs keep busy now.

    On Linux, the busy share of the machine's CPU time over ``sample_s`` seconds (from
    ``/proc/stat``, while this process sleeps) times its cores: a program spinning on one
    core reads about 1, and a command that ended a moment ago reads 0, where the load average
    of the last minute would still count it. Elsewhere, that load average (0 where the
    platform has none).
    """
    first = _cpu_times()
    if first is not None:
        time.sleep(sample_s)
        second = _cpu_times()
        if second is not None and second[1] > first[1]:
            share = (second[0] - first[0]) / (second[1] - first[1])
            return max(0.0, share) * (os.cpu_count() or 1)
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):  # pragma: no cover - Windows
        return 0.0


@dataclass(frozen=True)
class ThreadChoice:
    """The thread count the command runs with, and where it comes from.

    Attributes
    ----------
    threads : int or None
        The count femcal set; None where the user set one (``user``).
    cpus : int
        The cores this process may run on.
    load : float
        The busy cores when the command started (:func:`machine_load`).
    user : dict of str to str
        The :data:`THREAD_VARIABLES` the user set, as given (empty when femcal chose).
    """

    threads: int | None
    cpus: int
    load: float
    user: dict[str, str]

    def describe(self) -> str:
        """One line for the log: the count and why."""
        if self.user:
            given = ", ".join(f"{k}={v}" for k, v in self.user.items())
            return f"torch, OpenMP and BLAS threads as set by the user ({given})"
        plural = "s" if self.threads != 1 else ""
        return (
            f"torch, OpenMP and BLAS on {self.threads} thread{plural} of {self.cpus} cores "
            f"({self.load:.2f} cores busy; set OMP_NUM_THREADS to choose another count)"
        )


def limit_threads(
    environ: MutableMapping[str, str] | None = None,
    *,
    cpus: int | None = None,
    load: float | None = None,
) -> ThreadChoice:
    """Set the thread count of torch, OpenMP and BLAS to the cores free now.

    Where none of :data:`THREAD_VARIABLES` is set in ``environ``, each is set to
    :func:`choose_threads` of the machine's cores and load (child processes inherit them), and
    torch's intra-op count too when torch is already imported. Where the user set any of
    them, nothing changes: the user's count wins (torch reads ``OMP_NUM_THREADS``).

    Parameters
    ----------
    environ : mutable mapping, optional
        The environment to read and set (default: the process's).
    cpus, load : optional
        The cores and the busy ones (default: :func:`machine_cpus`, :func:`machine_load`).

    Returns
    -------
    ThreadChoice
    """
    environ = os.environ if environ is None else environ
    cpus = machine_cpus() if cpus is None else int(cpus)
    load = machine_load() if load is None else float(load)
    user = {k: environ[k] for k in THREAD_VARIABLES if environ.get(k, "").strip()}
    if user:
        choice = ThreadChoice(None, cpus, load, user)
    else:
        n = choose_threads(cpus, load)
        for key in THREAD_VARIABLES:
            environ[key] = str(n)
        if environ is os.environ and "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(n)
        choice = ThreadChoice(n, cpus, load, {})
    # Said where it slows the command down (fewer threads than cores), else at DEBUG level.
    fewer = choice.threads is not None and choice.threads < cpus
    logger.log(logging.INFO if fewer else logging.DEBUG, choice.describe())
    return choice
