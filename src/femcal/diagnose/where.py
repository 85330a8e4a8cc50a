"""Where each chosen effect acts: its load cases chosen by the data within its prior (a step
of :func:`femcal.diagnose.diagnose`).

An effect declares a prior per load case (``load_case_prior``,
:class:`femcal.effects.base.Effect`); forward selection fits it in its likely load cases and,
for a single effect, in every load case its prior allows (:func:`wide_terms`). After the
backward check and the open-world elimination (so that an effect that only stands in for
physics outside the library is dropped before a further load case could entrench it),
specimen by specimen, each effect of the chosen model is refitted, from the chosen model's solution,
with one load case of prior strictly between 0 and 1 added or left out
(:meth:`femcal.effects.terms.Term.toggles`); where a load case is added, the model without each
other effect is fitted too (from the toggled fit), so that an effect acting in a further load
case can replace one that stood in for it there. An effect counts in a load case beyond its
likely ones only where it engages there (:func:`engaged`). A change is kept where it lowers the
criterion ``chi^2 + k ln n`` plus the prior cost (the probabilities' own,
:func:`femcal.diagnose.probabilities.model_prior_cost`) by ``min_delta_inadequate``; the best
change is made and the step repeats while one pays (:data:`ROUNDS` at most).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import torch

from femcal.effects.base import get_effect
from femcal.effects.split import tied_parameter
from femcal.effects.terms import Model, Term
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:
    from femcal.diagnose.state import DiagnosisState

logger = logging.getLogger(__name__)

#: Rounds of the step: at most this many changes of where an effect acts per specimen.
ROUNDS = 2


def wide_terms(candidates: list[Term]) -> list[Term]:
    """Each candidate acting in every load case its prior allows, where that is more than its
    likely load cases (in candidate order)."""
    out = []
    for name in candidates:
        prior = get_effect(name).load_case_prior
        wide = name.with_cases([lc for lc in LOAD_CASES if prior.get(lc, 0.0) > 0.0])
        if wide != name:
            out.append(wide)
    return out


def engaged(state: DiagnosisState, model: Model, rows: list[int]) -> np.ndarray:
    """Bool (r,): for each specimen of ``rows``, whether every effect of ``model`` fitted to
    it engages in each load case it acts in beyond its likely ones (its share of the load
    there is not flat, :func:`femcal.diagnose.outside.flatness`: a share about constant from
    low moments on is the disc's, stiffer or softer than the box, not an element's). True
    where the model holds no such load case or the disc has no network to read shapes with."""
    from femcal.diagnose.outside import ShapeReader, flatness, stand_in_ramp

    extra = [[LOAD_CASES.index(lc) for lc in e.beyond] for e in model]
    ok = np.ones(len(rows), dtype=bool)
    if not any(extra) or not hasattr(state.base, "surrogate"):
        return ok
    reader = ShapeReader(state.base, state.mask)
    v = state.solutions(rows, model).double().numpy()
    shares = reader.shares(model, v)
    for k, i in enumerate(rows):
        for js, (_, share) in zip(extra, shares):
            if js:
                flat = flatness(share[k], reader.window[i])[js]
                ok[k] &= bool(np.all(np.isfinite(flat)) and np.all(stand_in_ramp(flat) < 0.5))
    return ok


def not_engaged(state: DiagnosisState) -> set[tuple[int, Model]]:
    """The fitted models (specimen, model) with an effect in a load case beyond its likely
    ones where it does not engage (:func:`engaged`): stand-ins for the disc there, left out
    of the probabilities as they are of the search's choices."""
    by_model: dict[Model, list[int]] = {}
    for i in range(state.n):
        for m in state.per_spec[i]:
            if any(e.beyond for e in m):
                by_model.setdefault(m, []).append(i)
    return {
        (i, m)
        for m, rows in by_model.items()
        for i, ok in zip(rows, engaged(state, m, rows))
        if not ok
    }


def mapped_start(v: torch.Tensor, effects: Model, target: Model) -> torch.Tensor:
    """A fit of ``effects`` (r, dim) as a start (r, dim') of ``target``: the disc as fitted,
    each effect of ``target`` from the effect of ``effects`` with the same registered name,
    parameter by parameter (unit coordinates); a per-load-case copy ``q[lc]`` the source does
    not hold takes the source's ``q``, or the mean of its copies; an effect the source does
    not hold takes its parameters' ``start``."""
    n_disc = v.shape[1] - sum(len(get_effect(e).parameters) for e in effects)
    source: dict[str, dict[str, torch.Tensor]] = {}
    at = n_disc
    for name in effects:
        params = get_effect(name).parameters
        source[name.effect] = {q.name: v[:, at + j] for j, q in enumerate(params)}
        at += len(params)
    parts = [v[:, :n_disc]]
    for name in target:
        own = source.get(name.effect, {})
        for q in get_effect(name).parameters:
            if q.name in own:
                parts.append(own[q.name][:, None])
                continue
            stem = tied_parameter(q.name)
            copies = [x for key, x in own.items() if tied_parameter(key) == stem]
            if copies:
                parts.append(torch.stack(copies, 1).mean(1, keepdim=True))
            else:
                parts.append(torch.full((len(v), 1), float(q.start), dtype=v.dtype))
    return torch.cat(parts, dim=1)


def choose_cases(state: DiagnosisState) -> int:
    """Change where the chosen effects act, specimen by specimen, while a change pays (see
    the module docstring). Returns the changes made.

    Reads ``state.chosen`` and their fits in ``state.per_spec``; changes ``state.per_spec``
    (each toggled model and its replacements, fitted) and ``state.chosen`` (where a change
    pays)."""
    from femcal.diagnose.probabilities import model_prior_cost

    options = state.options
    delta = options.min_delta_inadequate

    def score(model: Model, i: int) -> float:
        return state.criterion(model, i) + model_prior_cost(
            model, options.min_delta, options.min_delta_inadequate
        )

    made = 0
    for _round in range(ROUNDS):
        options_of: dict[int, list[Model]] = {}
        jobs: dict[tuple[Model, Model], list[int]] = {}
        for i, current in enumerate(state.chosen):
            for term in current:
                for new in term.toggles():
                    model = current.replace(term, new)
                    options_of.setdefault(i, []).append(model)
                    if model not in state.per_spec[i]:
                        jobs.setdefault((current, model), []).append(i)
        if not options_of:
            return made
        for (current, model), rows in jobs.items():
            v0 = mapped_start(state.solutions(rows, current), current, model)
            state.fit(model, np.asarray(rows), v0[:, None])
        _fit_replacements(state, options_of)
        by_model: dict[Model, list[int]] = {}
        for i, models in options_of.items():
            for m in set(models):
                if m in state.per_spec[i]:
                    by_model.setdefault(m, []).append(i)
        engages = {
            (m, i): bool(ok)
            for m, rows in by_model.items()
            for i, ok in zip(rows, engaged(state, m, rows))
        }
        changed = 0
        for i, models in options_of.items():
            here = score(state.chosen[i], i)
            gains = {m: here - score(m, i) for m in models if engages.get((m, i), False)}
            if not gains:
                continue
            best = max(gains, key=gains.get)
            if gains[best] >= delta:
                logger.info(
                    "%s: %s acts where %s (gains %.1f)",
                    state.specimens[i],
                    best,
                    {str(e): e.acting for e in best},
                    gains[best],
                )
                state.chosen[i] = best
                changed += 1
        made += changed
        if not changed:
            return made
    return made


def _fit_replacements(state: DiagnosisState, options_of: dict[int, list[Model]]) -> None:
    """For each toggled model that adds a load case to an effect of a combination, the model
    without each other effect, fitted from the toggled fit; added to ``options_of``."""
    jobs: dict[tuple[Model, Model], list[int]] = {}
    for i, models in list(options_of.items()):
        current = state.chosen[i]
        if len(current) < 2:
            continue
        for model in list(models):  # the toggled models, not the ones this adds
            grown = [
                e
                for e in model
                if e not in current
                and any(e.effect == c.effect and set(e.acting) > set(c.acting) for c in current)
            ]
            for drop in model:
                if not grown or drop in grown:
                    continue
                rest = model.without(drop)
                options_of[i].append(rest)
                if rest not in state.per_spec[i]:
                    jobs.setdefault((model, rest), []).append(i)
    for (model, rest), rows in jobs.items():
        v0 = mapped_start(state.solutions(rows, model), model, rest)
        state.fit(rest, np.asarray(rows), v0[:, None])
