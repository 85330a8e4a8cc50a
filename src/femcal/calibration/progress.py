"""The progress bar of a calibration: specimens done, and the step a batch is at.

:func:`~femcal.calibration.calibrate` opens one bar (:func:`specimen_bar`) over the specimens;
it advances by each chunk's specimens when the chunk is done. Within a chunk a calibrator
works on all its specimens at once; it says where it is with :func:`report_step` (pgd: the
Gauss-Newton iteration and how many specimens have settled), shown beside the bar. A
calibrator called outside a bar reports to nobody.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

#: Seconds before the bar appears: a calibration done sooner shows none.
BAR_DELAY = 2.0

_BAR: ContextVar[Any] = ContextVar("femcal_calibration_bar", default=None)


class SpecimenBar:
    """A tqdm bar over ``total`` specimens (stderr), opened on the first update or step from
    :data:`BAR_DELAY` seconds on (none before)."""

    def __init__(self, total: int, desc: str) -> None:
        self.total, self.desc, self.n = total, desc, 0
        self.start = time.monotonic()
        self.bar: Any = None

    def _shown(self) -> Any:
        if self.bar is None and time.monotonic() - self.start >= BAR_DELAY:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=self.total, desc=self.desc, unit="specimen", initial=self.n)
        return self.bar

    def update(self, k: int) -> None:
        """``k`` more specimens done."""
        self.n += k
        if self._shown() is not None:
            self.bar.update(k)

    def step(self, text: str) -> None:
        """Show ``text`` beside the bar (where the running chunk is)."""
        if self._shown() is not None:
            self.bar.set_postfix_str(text)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


@contextmanager
def specimen_bar(total: int, desc: str, *, enabled: bool) -> Iterator[SpecimenBar | None]:
    """A :class:`SpecimenBar` where ``enabled``, else None; :func:`report_step` writes to it
    meanwhile."""
    if not enabled:
        yield None
        return
    bar = SpecimenBar(total, desc)
    token = _BAR.set(bar)
    try:
        yield bar
    finally:
        _BAR.reset(token)
        bar.close()


def report_step(step: str, *, settled: int, of: int) -> None:
    """Show a calibrator's step beside the bar: ``"<step>: <settled>/<of> specimens
    settled"``; nothing when no bar is open."""
    bar = _BAR.get()
    if bar is not None:
        bar.step(f"{step}: {settled}/{of} specimens settled")
