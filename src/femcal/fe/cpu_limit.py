"""A solver run's time limit counted in CPU seconds, so that the machine's load does not decide it.

A wall-clock limit turns a busy machine into failures: the same deck that solves in 60 s on a
quiet core is killed at 90 s beside other work, and a campaign's failures then depend on
what else ran. :class:`CpuLimit` watches the child's own CPU time (user + system, from
``/proc/<pid>/stat``) instead, and stops it once that passes ``limit_s``. A child that hangs
without using CPU is stopped by a wall-clock limit of :data:`WALL_FACTOR` times ``limit_s``.
Where ``/proc`` is not available, the limit is counted in wall-clock seconds.
"""

from __future__ import annotations

import os
import subprocess
import threading
import time
from pathlib import Path

#: The wall-clock limit, in multiples of the CPU limit, that stops a child which hangs.
WALL_FACTOR = 20.0
#: Longest pause between two readings of the child's CPU time, s.
POLL_S = 0.25


def cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) process ``pid`` has used; None without
    ``/proc`` or once the process is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2 :].split()  # after "pid (comm) "
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14, 15)


class CpuLimit:
    """Stop ``proc`` once it has used ``limit_s`` CPU seconds (see the module's text).

    Use as a context manager around the wait for ``proc``; :attr:`reason` then says which
    limit stopped it (None: it ended on its own).

    Parameters
    ----------
    proc : subprocess.Popen
        The running child.
    limit_s : float
        CPU seconds (user + system) the child may use.
    """

    def __init__(self, proc: subprocess.Popen, limit_s: float) -> None:
        self.proc, self.limit_s = proc, float(limit_s)
        self.reason: str | None = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True, name="femcal-cpu-limit")

    def _watch(self) -> None:
        start = time.monotonic()
        by_cpu = cpu_seconds(self.proc.pid) is not None
        wall_limit = self.limit_s * WALL_FACTOR if by_cpu else self.limit_s
        pause = min(POLL_S, max(0.01, self.limit_s / 10))
        while not self._done.wait(pause):
            used = cpu_seconds(self.proc.pid) if by_cpu else None
            if used is not None and used >= self.limit_s:
                self._stop(f"{self.limit_s:g} s of CPU time")
            elif time.monotonic() - start >= wall_limit:
                self._stop(f"{wall_limit:g} s of wall-clock time")
            else:
                continue
            return

    def _stop(self, reason: str) -> None:
        self.reason = reason
        self.proc.kill()

    def __enter__(self) -> CpuLimit:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()
