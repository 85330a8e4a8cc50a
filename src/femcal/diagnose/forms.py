"""Tied or split: whether an effect's parameters differ per load case (a step of
:func:`femcal.diagnose.diagnose`).

Forward selection adds effects in their tied form (one value per parameter for all of the
effect's load cases) and tries each added effect split before adding another. Then each effect
of the chosen model that has a split form (:mod:`femcal.effects.split`) and is still tied is
refitted split, from the tied fit, and the split stays where it lowers the criterion by
``min_delta_inadequate``: a split's extra parameters pay like any other, by their effective
number. The backward check that follows asks again, given the split, whether every further
effect is still needed.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from femcal.diagnose.fits import fit_solutions, split_starts
from femcal.effects.split import has_split_form
from femcal.effects.terms import Model, Term

if TYPE_CHECKING:
    from femcal.diagnose.state import DiagnosisState

logger = logging.getLogger(__name__)


def split_one(effects: Model, term: Term) -> Model:
    """``effects`` with ``term`` in its split form."""
    return effects.replace(term, term.as_split())


def choose_forms(state: DiagnosisState) -> None:
    """Split, specimen by specimen, the chosen effects whose split form pays
    ``min_delta_inadequate`` (a split's prior cost).

    Each split starts from the tied fit, its values copied into every load case, and from each
    load case's copy moved alone over the start levels
    (:func:`femcal.diagnose.fits.split_starts`).

    Reads ``state.chosen`` and their fits in ``state.per_spec``; changes ``state.per_spec``
    (the split forms fitted) and ``state.chosen`` (where a split pays).
    """
    chosen, per_spec = state.chosen, state.per_spec
    delta = state.options.min_delta_inadequate
    for _round in range(max((len(c) for c in chosen), default=0)):
        jobs: dict[tuple[Model, Model], list[int]] = {}
        for i, current in enumerate(chosen):
            for name in current:
                split = split_one(current, name)
                if has_split_form(name) and split not in per_spec[i]:
                    jobs.setdefault((current, split), []).append(i)
        if not jobs:
            return
        for (current, split), rows in jobs.items():
            v = fit_solutions(per_spec, rows, current)
            v0 = split_starts(v, current, split, state.options.effect_levels)
            state.fit(split, np.asarray(rows), v0)
        changed = 0
        for i, current in enumerate(chosen):
            options = [
                split_one(current, name)
                for name in current
                if has_split_form(name) and split_one(current, name) in per_spec[i]
            ]
            if not options:
                continue
            here = state.criterion(current, i)
            gains = {s: here - state.criterion(s, i) for s in options}
            best = max(gains, key=gains.get)
            if gains[best] >= delta:
                logger.info(
                    "%s: %s split per load case gains %.1f", state.specimens[i], best, gains[best]
                )
                chosen[i] = best
                changed += 1
        if not changed:
            return
