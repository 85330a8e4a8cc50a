"""The progress bar of a calibration: specimens done, and the step a batch is at.

:func:`~femcal.calibration.calibrate` opens one bar (:func:`specimen_bar`) over the specimens;
it advances by each chunk's specimens when the chunk is done. Within a chunk a calibrator
works on all its specimens at once; it says where it is with :func:`report_step` (pgd: the
Gauss-Newton iteration and how many specimens have settled), shown beside the bar. A
calibrator called outside a bar reports to nobody.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

#: Seconds before the bar appears: a calibration done sooner shows none.
BAR_DELAY = 2.0

_BAR: ContextVar[Any] = ContextVar("femcal_calibration_bar", default=None)


@contextmanager
def specimen_bar(total: int, desc: str, *, enabled: bool) -> Iterator[Any]:
    """A tqdm bar over ``total`` specimens (stderr) where ``enabled``, else None.

    The bar shows from :data:`BAR_DELAY` seconds on; :func:`report_step` writes to it
    meanwhile.
    """
    if not enabled:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=desc, unit="specimen", delay=BAR_DELAY)
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
        bar.set_postfix_str(f"{step}: {settled}/{of} specimens settled", refresh=True)
