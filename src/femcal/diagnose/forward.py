"""Forward selection, a step of :func:`femcal.diagnose.diagnose`: add registered effects while
they pay, batched over the specimens that share a current model."""

from __future__ import annotations

import itertools
import logging

import numpy as np
import torch

from femcal.calibration.base import CalibrationProblem
from femcal.calibration.starts import combination_starts, effect_bank, nearest_starts
from femcal.diagnose.fits import Fit, fit_from, fit_starts, split_starts
from femcal.diagnose.forms import split_one
from femcal.diagnose.state import DiagnosisState
from femcal.diagnose.where import engaged, wide_terms
from femcal.effects.base import get_effect
from femcal.effects.split import has_split_form
from femcal.effects.terms import Model, Term

logger = logging.getLogger(__name__)


def forward_selection(state: DiagnosisState) -> None:
    """Add, level by level, the effect that lowers each specimen's criterion most.

    A new effect's fit starts from the current model's solution with a grid over the new
    effect's box, and from the disc-and-effect combinations of the start bank nearest the
    specimen's curves (the disc fitted alone has bent towards the missing physics). The first
    effect needs ``min_delta``; a further one ``min_delta_inadequate`` where the current model
    does not explain the data and ``min_delta_adequate`` where it does (None: stop there).
    At the first level every candidate is also fitted split per load case
    (:func:`_fit_splits`), a split form paying its prior cost ``min_delta_inadequate``, and
    every pair of effects on disjoint load cases in all its forms where the disc alone misses
    (:func:`_fit_pairs`): the pairs compete with the models of the second level, and at the
    first only where no single effect pays, their second effect then paying
    ``min_delta_inadequate``. At a further level the effect just added is tried split
    (:func:`_split_added`). Every model
    within ``beam_delta`` of the best of a level is extended at the next one.

    Reads ``state.chosen`` (the disc alone for every specimen) and the disc-alone fits in
    ``state.per_spec``; changes ``state.chosen`` (each specimen's model when the search
    stops) and ``state.per_spec`` (every model fitted).
    """
    options = state.options
    frontier: list[list[Model]] = [[Model()] for _ in range(state.n)]
    beam = options.min_delta if options.beam_delta is None else float(options.beam_delta)
    banks: dict[Model, tuple[torch.Tensor, torch.Tensor]] = {}
    pairs: dict[int, list[Model]] = {}
    active = np.arange(state.n)
    for _level in range(options.max_effects):
        if active.size == 0:
            return
        children = _extend(state, active, frontier, banks)
        if _level == 0:
            _fit_wide(state, [int(i) for i in active], children, banks)
            _fit_splits(state, [int(i) for i in active], children, banks)
            pairs = _fit_pairs(state, [int(i) for i in active], banks)
        elif _level == 1:  # the pairs compete with the models one effect larger
            for i in active:
                children[int(i)] = sorted({*children[int(i)], *pairs.pop(int(i), [])})
        improved: list[int] = []
        added: dict[int, Term] = {}
        for i in active:
            current = state.chosen[i]
            crits = _costed(state, i, children[int(i)], current)
            if not crits:
                continue
            cur_crit = state.criterion(current, i) + _prior_costs(state, current)
            logger.debug(
                "%s: forward from %s: criterion gains %s",
                state.specimens[i],
                [str(e) for e in frontier[i]],
                {str(e): round(cur_crit - b, 1) for e, b in crits.items()},
            )
            need = options.min_delta
            if current:
                if not state.adequate(current, i):
                    need = options.min_delta_inadequate
                elif options.min_delta_adequate is not None:
                    need = options.min_delta_adequate
            if _level == 0 and cur_crit - min(crits.values()) < need and pairs.get(int(i)):
                # no single effect pays: a pair may, its second effect paying too
                crits.update(_costed(state, i, pairs.pop(int(i)), current))
            best_eff = min(crits, key=crits.get)
            best_crit = crits[best_eff]
            if cur_crit - best_crit >= need:
                added[int(i)] = next(e for e in best_eff if e not in current)
                state.chosen[i] = best_eff
                frontier[i] = [e for e, b in crits.items() if b - best_crit < beam or e == best_eff]
                improved.append(int(i))
        if _level > 0:
            _split_added(state, added, frontier)
        # Keep adding while it pays; with min_delta_adequate None only where the chosen model
        # still does not explain the data.
        active = np.asarray(
            [
                i
                for i in improved
                if options.min_delta_adequate is not None or not state.adequate(state.chosen[i], i)
            ],
            dtype=int,
        )


def _split_added(
    state: DiagnosisState, added: dict[int, Term], frontier: list[list[Model]]
) -> None:
    """The effect each specimen just took (``added``: specimen -> effect), tried split per
    load case from its tied fit before any further effect is tried: a further effect must not
    stand in for a load case the tied law could not fit. The split replaces the tied model
    (in ``state.chosen`` and the specimen's frontier) where it gains ``min_delta_inadequate``,
    a split's prior cost."""
    jobs: dict[tuple[Model, Model], list[int]] = {}
    for i, new in added.items():
        if has_split_form(new):
            jobs.setdefault((state.chosen[i], split_one(state.chosen[i], new)), []).append(i)
    for (current, split), rows in jobs.items():
        todo = [i for i in rows if split not in state.per_spec[i]]  # a pair's form is fitted
        if todo:
            v0 = split_starts(
                state.solutions(todo, current), current, split, state.options.effect_levels
            )
            state.fit(split, np.asarray(todo), v0)
    for (current, split), rows in jobs.items():
        for i in rows:
            gain = state.criterion(current, i) - state.criterion(split, i)
            if gain >= state.options.min_delta_inadequate:
                logger.info(
                    "%s: %s split per load case gains %.1f", state.specimens[i], split, gain
                )
                state.chosen[i] = split
                frontier[i] = [split if e == current else e for e in frontier[i]]


def _costed(state: DiagnosisState, i: int, models: list[Model], current: Model) -> dict:
    """Specimen ``i``'s criterion of each of ``models`` plus the prior costs forward selection
    counts against it from ``current``: a split form's and its load cases' (:func:`_prior_costs`)
    and that of every effect beyond the one a level adds (:func:`_extra_cost`)."""
    return {
        e: state.criterion(e, i) + _prior_costs(state, e) + _extra_cost(state, e, current)
        for e in models
    }


def _prior_costs(state: DiagnosisState, model: Model) -> float:
    """A model's split cost (:func:`_split_cost`) and what the load cases its effects act in
    cost against their likely ones (:meth:`femcal.effects.terms.Model.case_cost`)."""
    return _split_cost(state, model) + model.case_cost()


def _extra_cost(state: DiagnosisState, model: Model, current: Model) -> float:
    """The prior cost of the effects ``model`` holds beyond ``current`` and the one a level
    adds: ``min_delta_inadequate`` each (a pair fitted at the first level pays for its
    second effect as if added at the next)."""
    return state.options.min_delta_inadequate * max(0, len(model) - len(current) - 1)


def complementary_pairs(candidates: list[Term]) -> list[Model]:
    """The pairs of ``candidates`` whose effects act on disjoint load cases (in model order):
    each explains its own load cases, so neither may pay alone where the specimen needs both
    (a facet in extension and axial rotation beside a ligament in flexion and lateral
    bending)."""
    masks = {term: get_effect(term).load_case_mask() for term in candidates}
    ordered = sorted(candidates)
    return [
        Model.of(a, b)
        for k, a in enumerate(ordered)
        for b in ordered[k + 1 :]
        if not bool((masks[a] & masks[b]).any())
    ]


def _fit_pairs(
    state: DiagnosisState, rows: list[int], banks: dict[Model, tuple[torch.Tensor, torch.Tensor]]
) -> dict[int, list[Model]]:
    """Every complementary pair (:func:`complementary_pairs`), tied and in each split form,
    fitted at the first level for the specimens ``rows`` the disc alone does not explain: a
    beam over single effects misses a pair whose members each explain half the misfit when a
    flexible effect over all load cases explains more of it alone. The tied pair starts from
    the better-fitting member's solution with the other's grid and the start bank
    (:func:`_new_effect_starts`); a split form from the tied pair's fit
    (:func:`femcal.diagnose.fits.split_starts`) and from its members' own fits side by side
    (:func:`_members_start`); each then takes the combination rounds of the next levels.
    Returns, per specimen, the pair models fitted."""
    out: dict[int, list[Model]] = {}
    if state.options.max_effects < 2:
        return out
    rows = [i for i in rows if not state.adequate(Model(), i)]
    if not rows:
        return out
    for pair in complementary_pairs(state.candidates):
        jobs: dict[Term, list[int]] = {}
        for i in rows:
            parent = min(pair, key=lambda e, i=i: state.criterion(Model.of(e), i))
            jobs.setdefault(parent, []).append(i)
        for parent, members in jobs.items():
            new = next(e for e in pair if e != parent)
            rows_a = np.asarray(members)
            v0 = _new_effect_starts(state, rows_a, Model.of(parent), new, banks)
            fit = state.fit(pair, rows_a, v0)
            _refine_combination(state, fit)
        forms = _split_forms(pair)
        for form in forms:
            v0 = split_starts(state.solutions(rows, pair), pair, form, state.options.effect_levels)
            v0 = torch.cat([v0, _members_start(state, rows, form)], 1)
            fit = state.fit(form, np.asarray(rows), v0)
            _refine_combination(state, fit)
        for i in rows:
            out[i] = sorted({*out.get(i, []), pair, *forms})
    return out


def _split_forms(effects: Model) -> list[Model]:
    """The forms of ``effects`` with at least one effect split per load case."""
    options = [[e, e.as_split()] if has_split_form(e) else [e] for e in effects]
    forms = [Model(f) for f in itertools.product(*options)]
    return [f for f in forms if f.n_split]


def _members_start(state: DiagnosisState, rows: list[int], form: Model) -> torch.Tensor:
    """A start (r, 1, dim) of model ``form`` from its members' own fits at the first level:
    each effect's parameters from its own fit (in the same form), the disc from the member
    that fits the specimen better."""
    n_disc = state.base.dim
    own = {e: state.solutions(rows, Model.of(e)) for e in form}
    better = [min(form, key=lambda e, i=i: state.criterion(Model.of(e), i)) for i in rows]
    disc = torch.stack([own[e][k, :n_disc] for k, e in enumerate(better)])
    return torch.cat([disc, *(own[e][:, n_disc:] for e in form)], dim=1)[:, None]


def _split_cost(state: DiagnosisState, model: Model) -> float:
    """The prior cost a model's split forms add to its criterion in forward selection:
    ``min_delta_inadequate`` when it holds one."""
    return state.options.min_delta_inadequate if model.n_split else 0.0


def _fit_splits(
    state: DiagnosisState,
    rows: list[int],
    children: dict[int, list[Model]],
    banks: dict[Model, tuple[torch.Tensor, torch.Tensor]],
) -> None:
    """Every candidate effect split per load case for the specimens ``rows``, added to their
    ``children``: a law tied across load cases may not fit a specimen whose anatomy differs
    between them, and an effect whose tied form loses to another's may win split. Each split
    form starts from its tied fit (:func:`femcal.diagnose.fits.split_starts`) and, like a new
    effect, from the disc alone's solution with the effect's grid and from the start bank
    (:func:`_new_effect_starts`): the disc the tied law bent holds a split fit near the tied
    one. The first level then chooses among tied and split forms, a split paying its prior
    cost (:func:`_split_cost`)."""
    if not rows:
        return
    rows_a = np.asarray(rows)
    for name in state.candidates:
        if has_split_form(name):
            split = Model.of(name.as_split())
            v = state.solutions(rows, Model.of(name))
            v0 = split_starts(v, Model.of(name), split, state.options.effect_levels)
            w0 = _new_effect_starts(state, rows_a, Model(), name.as_split(), banks)
            state.fit(split, rows_a, torch.cat([v0, w0], dim=1))
            for i in rows:
                children[i] = sorted({*children[i], split})


def _fit_wide(
    state: DiagnosisState,
    rows: list[int],
    children: dict[int, list[Model]],
    banks: dict[Model, tuple[torch.Tensor, torch.Tensor]],
) -> None:
    """Every candidate effect acting in every load case its prior allows
    (:func:`femcal.diagnose.where.wide_terms`), tied, for the specimens ``rows``, added to
    their ``children``: an element that acts beyond its likely load cases (a facet impinging
    in lateral bending) is otherwise fitted there by an effect that stands in for it. Each
    starts from its tied fit in the likely load cases (the same parameters) and, like a new
    effect, from the disc alone with its grid and the start bank (:func:`_new_effect_starts`);
    it pays the prior cost of its further load cases (:func:`_prior_costs`) and competes only
    where it engages in them (:func:`femcal.diagnose.where.engaged`)."""
    if not rows:
        return
    rows_a = np.asarray(rows)
    for name in state.candidates:
        for wide in wide_terms([name]):
            v = state.solutions(rows, Model.of(name))[:, None]
            v0 = torch.cat([v, _new_effect_starts(state, rows_a, Model(), wide, banks)], dim=1)
            state.fit(Model.of(wide), rows_a, v0)
            for i, ok in zip(rows, engaged(state, Model.of(wide), rows)):
                if ok:
                    children[i] = sorted({*children[i], Model.of(wide)})


def _new_effect_starts(
    state: DiagnosisState,
    rows: np.ndarray,
    current: Model,
    new: Term,
    banks: dict[Model, tuple[torch.Tensor, torch.Tensor]],
) -> torch.Tensor:
    """Starts (r, g, dim) of model ``current`` plus ``new`` for specimens ``rows``: the
    current model's solution with a grid over the new effect's box, and the ``bank_starts``
    disc-and-effect combinations of the start bank nearest each specimen's curves (the disc
    fitted alone has bent towards the missing physics)."""
    options = state.options
    effects = current.plus(new)
    model = state.model(effects)
    v0 = fit_starts(model, effects, current, state.solutions(rows, current), new, options)
    if state.start_bank is not None and options.bank_starts > 0:
        if effects not in banks:
            banks[effects] = effect_bank(
                model, state.start_bank, state.model_rng(effects), options.bank_samples
            )
        problem = CalibrationProblem.from_arrays(model, state.measured[rows], state.weight[rows])
        near = nearest_starts(problem, *banks[effects], options.bank_starts)  # (r, K)
        v0 = torch.cat([v0, banks[effects][0][near]], dim=1)
    return v0


def _extend(
    state: DiagnosisState,
    active: np.ndarray,
    frontier: list[list[Model]],
    banks: dict[Model, tuple[torch.Tensor, torch.Tensor]],
) -> dict[int, list[Model]]:
    """Fit every model one effect larger than a frontier model, each once per specimen (from
    its best parent in the frontier); per specimen, the models fitted."""
    jobs: dict[tuple[Model, Term], list[int]] = {}
    children: dict[int, list[Model]] = {}
    for i in active:
        parents = sorted(frontier[i], key=lambda e, i=i: state.criterion(e, i))
        seen: set[Model] = set()
        for current in parents:
            held = set(current.effects)
            for new in state.candidates:
                effects = current.plus(new)
                if new.effect in held or effects in seen:
                    continue
                seen.add(effects)
                if effects not in state.per_spec[i]:  # a pair of the first level is fitted
                    jobs.setdefault((current, new), []).append(int(i))
        children[int(i)] = sorted(seen)
    for (current, new), members in jobs.items():
        rows = np.asarray(members)
        effects = current.plus(new)
        fit = state.fit(effects, rows, _new_effect_starts(state, rows, current, new, banks))
        if len(effects) > 1:
            _refine_combination(state, fit)
    return children


def _refine_combination(state: DiagnosisState, fit: Fit) -> None:
    """More rounds for the specimens whose combination fit does not explain the data yet
    (``chi2`` above ``n - k/2``): each effect again from its grid and a small design, the disc
    and the other effects as found (:func:`femcal.calibration.starts.combination_starts`);
    the better fit is kept (``fit`` updated in place)."""
    model, rows = fit.model, fit.rows
    for _ in range(state.options.combination_rounds):
        bad = np.flatnonzero(fit.chi2 > np.maximum(state.n_points[rows] - model.dim / 2, 1.0))
        if bad.size == 0:
            return
        v1 = combination_starts(model, fit.v[bad], state.options.effect_levels, 8)
        v2, p2, c2 = fit_from(
            model, state.measured, state.weight, state.sigma, rows[bad], v1, state.options.max_iter
        )
        better = c2 < fit.chi2[bad]
        if not better.any():
            return
        at = torch.as_tensor(bad[better])
        fit.v, fit.pred, fit.chi2 = fit.v.clone(), fit.pred.clone(), fit.chi2.copy()
        fit.v[at] = v2[torch.as_tensor(better)]
        fit.pred[at] = p2[torch.as_tensor(better)]
        fit.chi2[bad[better]] = c2[better]
