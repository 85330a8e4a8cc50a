"""Tied or split: whether an effect's parameters differ per load case (a step of
:func:`femcal.diagnose.diagnose`).

Forward selection adds effects in their tied form (one value per parameter for all of the
effect's load cases). Then each effect of the chosen model that has a split form
(:mod:`femcal.effects.split`) is refitted split, from the tied fit with each value copied into
every load case, and the split stays where it lowers the criterion by ``delta``: a split's extra
parameters pay like any other, by their effective number. The backward check that follows asks
again, given the split, whether every further effect is still needed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np
import torch

from femcal.diagnose.fits import _solutions, _split_start
from femcal.effects.split import SPLIT_SUFFIX, has_split_form

logger = logging.getLogger(__name__)

Model = tuple[str, ...]


def _split_one(effects: Model, name: str) -> Model:
    return tuple(sorted(e + SPLIT_SUFFIX if e == name else e for e in effects))


def choose_forms(
    chosen: list[Model],
    per_spec: list[dict],
    fit: Callable[[Model, np.ndarray, torch.Tensor], None],
    criterion: Callable[[Model, int], float],
    delta: float,
    specimens: Sequence[str],
) -> None:
    """Split, specimen by specimen, the chosen effects whose split form pays ``delta``.

    Parameters
    ----------
    chosen : list of tuple of str
        Per specimen, the chosen model's effects; updated in place.
    per_spec : list of dict
        Per specimen, every fitted model: ``effects -> (fit, row in the fit)``.
    fit : callable
        ``fit(effects, rows, v0)`` fits model ``effects`` to specimens ``rows`` (r,) from one
        start each, ``v0`` (r, dim), and records it in ``per_spec``.
    criterion : callable
        ``criterion(effects, i)``: specimen ``i``'s criterion of a fitted model.
    delta : float
        Criterion gain a split needs over the tied form.
    specimens : sequence of str
        Names, for the log.
    """
    for _round in range(max((len(c) for c in chosen), default=0)):
        jobs: dict[tuple[Model, Model], list[int]] = {}
        for i, current in enumerate(chosen):
            for name in current:
                split = _split_one(current, name)
                if has_split_form(name) and split not in per_spec[i]:
                    jobs.setdefault((current, split), []).append(i)
        if not jobs:
            return
        for (current, split), rows in jobs.items():
            v = _solutions(per_spec, rows, current)
            fit(split, np.asarray(rows), _split_start(v, current, split))
        changed = 0
        for i, current in enumerate(chosen):
            options = [
                _split_one(current, name)
                for name in current
                if has_split_form(name) and _split_one(current, name) in per_spec[i]
            ]
            if not options:
                continue
            here = criterion(current, i)
            gains = {s: here - criterion(s, i) for s in options}
            best = max(gains, key=gains.get)
            if gains[best] >= delta:
                logger.info(
                    "%s: %s split per load case gains %.1f", specimens[i], best, gains[best]
                )
                chosen[i] = best
                changed += 1
        if not changed:
            return
