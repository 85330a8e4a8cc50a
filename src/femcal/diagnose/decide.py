"""The step that decides each specimen's model (a step of :func:`femcal.diagnose.diagnose`):
how probable every fitted model is, with and without a discrepancy, and the most probable one.

Each final model gets the discrepancy it needs (type-II maximum likelihood), and so does the
disc alone: how probable something outside the library is, on top of the effects or in their
place. The probabilities of every fitted model and of those models with their discrepancy
follow (:func:`femcal.diagnose.probabilities.specimen_probabilities`).
The verdict is the most probable explanation: where a fitted model is more probable than the
search's choice (and no discrepancy is the most probable), that model is chosen, and the
discrepancies and probabilities are computed again for the models that changed. Last, the
out-of-box reading (:func:`femcal.diagnose.outside.assess`) shares the probabilities with a
disc beyond the parameter box; where it names the box, the verdict names it with the effects
that engage. The :class:`Decision` holds all of it, frozen, for the description to read.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from femcal.diagnose.balance import balance_stand_ins
from femcal.diagnose.discrepancy import DiscrepancyFit, fit_discrepancy
from femcal.diagnose.fits import Fit
from femcal.diagnose.outside import assess
from femcal.diagnose.probabilities import (
    bootstrap_rng,
    outside_label,
    outside_models,
    specimen_probabilities,
)
from femcal.diagnose.result import UNEXPLAINED, model_label, verdict_label
from femcal.diagnose.state import DiagnosisState
from femcal.diagnose.where import not_engaged
from femcal.effects.terms import Model, Term

#: An effect is idle in a fit when removing it raises the chi-square by less than this and
#: lowers the effective number of parameters by less than :data:`IDLE_PARAMETERS`.
IDLE_CHI2 = 1.0
IDLE_PARAMETERS = 0.5


@dataclass(frozen=True)
class SpecimenDecision:
    """What :func:`decide` decided for one specimen.

    Attributes
    ----------
    chosen : Model
        The fitted model decided: the description's fits, curves and residuals are its.
    verdict : str
        ``none``, ``unexplained``, the effects joined by ``+`` (possibly ending in
        ``+unexplained``) or, where the out-of-box reading names the box, the effects that
        engage and ``outside_box`` (:func:`femcal.diagnose.outside.assess`).
    model : tuple of Term
        The effects the verdict names: ``chosen``'s terms, or the reading's where it names the
        box.
    adequate : bool
        The verdict says the model explains the data: no discrepancy is named on top of it,
        and the box is not named.
    probabilities : dict
        :func:`~femcal.diagnose.probabilities.specimen_probabilities`, shared out with the box
        where the specimen looks beyond it (``unexplained`` then says whether a discrepancy is
        named beside the box).
    outside_box : dict or None
        The out-of-box reading where the specimen looks beyond the box, else None.
    """

    chosen: Model
    verdict: str
    model: tuple[Term, ...]
    adequate: bool
    probabilities: dict[str, Any]
    outside_box: dict[str, Any] | None


@dataclass(frozen=True)
class Decision:
    """What :func:`decide` decided, for the description to read.

    Attributes
    ----------
    finals : mapping of Model to tuple of int
        Each chosen model and its specimens (in specimen order).
    gp : mapping of Model to DiscrepancyFit
        Each chosen model refitted with the discrepancy it needs, to ``finals[model]`` in that
        order.
    specimens : tuple of SpecimenDecision, length n
        Per specimen, its model, verdict and probabilities.
    """

    finals: Mapping[Model, tuple[int, ...]]
    gp: Mapping[Model, DiscrepancyFit]
    specimens: tuple[SpecimenDecision, ...]


def decide(state: DiagnosisState, disc: Fit) -> Decision:
    """Each specimen's model and verdict: the most probable explanation (see the module
    docstring); ``disc`` is the disc alone's fit of every specimen of ``state``.

    Reads ``state.chosen``, every fit in ``state.per_spec`` and ``disc``; changes
    ``state.chosen`` (where another fitted model is the most probable) and the fits' effective
    parameters and covariance (:meth:`~femcal.diagnose.fits.Fit.ensure_trace`, once per fit).
    """
    # One Jacobian per fitted batch: effective parameters and covariance of every model.
    for i in range(state.n):
        for f, _ in state.per_spec[i].values():
            f.ensure_trace(state.mask, state.sigma)
    finals = _finals(state)
    gp = {effects: _gp_fit(state, effects, rows) for effects, rows in finals.items()}
    alone = _gp_fit(state, Model(), list(range(state.n)))
    probabilities = _probabilities(state, finals, gp, alone)
    switched = {}
    for i, p in enumerate(probabilities):
        top = p["most_probable"]
        if top.endswith(UNEXPLAINED):
            continue
        model = next(m for m in state.per_spec[i] if model_label(m) == top)
        if model != state.chosen[i]:
            switched[i] = model
    if switched:
        for i, model in switched.items():
            state.chosen[i] = model
        old, finals = finals, _finals(state)
        for effects, rows in finals.items():
            if rows != old.get(effects):  # the fits are per group, in its order
                gp[effects] = _gp_fit(state, effects, rows)
        probabilities = _probabilities(state, finals, gp, alone)
    probabilities, outside = _outside_box(state, disc, finals, gp, probabilities)
    return Decision(
        finals=MappingProxyType({m: tuple(rows) for m, rows in finals.items()}),
        gp=MappingProxyType({m: gp[m] for m in finals}),
        specimens=tuple(
            _specimen(state.chosen[i], probabilities[i], outside[i]) for i in range(state.n)
        ),
    )


def _specimen(
    chosen: Model, probabilities: dict[str, Any], reading: dict[str, Any] | None
) -> SpecimenDecision:
    """One specimen's decision from its chosen model, its (shared-out) probabilities and its
    out-of-box reading (or None)."""
    adequate = not probabilities["unexplained"]
    verdict, model = verdict_label(list(chosen), adequate), tuple(chosen)
    if reading is not None and reading["named"]:
        # The box, not the stand-ins: the verdict keeps the effects that engage.
        verdict, adequate, model = reading["verdict"], False, tuple(reading["model"])
    return SpecimenDecision(chosen, verdict, model, adequate, probabilities, reading)


def _outside_box(state: DiagnosisState, disc: Fit, finals, gp, probabilities):
    """The out-of-box reading (:func:`femcal.diagnose.outside.assess`) with each specimen's
    discrepancy and curves of its final model (``finals``, ``gp`` per final model): the
    probabilities shared out, and per specimen the reading or None. Where the box is named,
    ``unexplained`` says whether a discrepancy is named beside it. The specimens without a
    reading have their flat effects shared with something outside the library
    (:func:`femcal.diagnose.balance.balance_stand_ins`)."""
    delta = np.full(state.measured.shape, np.nan)
    pred = np.full(state.measured.shape, np.nan)
    for effects, rows in finals.items():
        for pos, i in enumerate(rows):
            delta[i] = gp[effects].delta_at_points[pos]
            f, at = state.per_spec[i][effects]
            pred[i] = f.pred[at].double().numpy()
    probabilities, outside = assess(state, disc, probabilities, delta, pred)
    probabilities = balance_stand_ins(state, probabilities, [o is not None for o in outside])
    probabilities = [
        {**p, "unexplained": UNEXPLAINED in reading["verdict"].split("+")}
        if reading is not None and reading["named"]
        else p
        for p, reading in zip(probabilities, outside)
    ]
    return probabilities, outside


def _finals(state: DiagnosisState) -> dict[Model, list[int]]:
    """Each chosen model and its specimens, in specimen order."""
    finals: dict[Model, list[int]] = {}
    for i in range(state.n):
        finals.setdefault(state.chosen[i], []).append(i)
    return finals


def _gp_fit(state: DiagnosisState, effects: Model, rows: list[int]) -> DiscrepancyFit:
    """Model ``effects`` refitted to specimens ``rows`` with the discrepancy it needs."""
    rows_a = np.asarray(rows)
    v = state.solutions(rows_a, effects)
    return fit_discrepancy(
        state.model(effects),
        v,
        state.measured[rows_a],
        state.sigma[rows_a],
        amplitude_deg="ml",
    )


def _probabilities(state: DiagnosisState, finals, gp, alone) -> list[dict[str, Any]]:
    """Per specimen, :func:`~femcal.diagnose.probabilities.specimen_probabilities` of every
    fitted model, of its final model with its discrepancy (``gp``, per final model, fitted to
    ``finals[model]`` in that order) and of the disc alone with its discrepancy (``alone``,
    fitted to every specimen). A model with an effect in a load case beyond its
    likely ones where it does not engage is left out (:func:`femcal.diagnose.where.not_engaged`),
    as the search leaves it out."""
    own = _outside_criteria(state, finals, gp)
    in_place = _outside_criteria(state, {Model(): list(range(state.n))}, {Model(): alone})
    aside = not_engaged(state)
    pointwise = _pointwise(state, finals, gp, alone)
    return [
        specimen_probabilities(
            {
                m: state.criterion(m, i)
                for m in state.per_spec[i]
                if m == state.chosen[i] or not (_idle_effect(state, m, i) or (i, m) in aside)
            },
            [
                (m, float((own if m == state.chosen[i] else in_place)[i]))
                for m in outside_models(state.chosen[i])
            ],
            state.options.min_delta,
            state.options.min_delta_inadequate,
            pointwise=pointwise[i],
            rng=bootstrap_rng(state.options.seed, state.specimens[i]),
        )
        for i in range(state.n)
    ]


def _pointwise(state: DiagnosisState, finals, gp, alone) -> list[dict[str, np.ndarray]]:
    """Per specimen, each fitted model's chi-square contribution at each measured point
    (label -> (p,)), and its final model's and the disc alone's with their discrepancy's mean
    added (the discrepancies' labels; ``alone`` fitted to every specimen): what the Bayesian
    bootstrap of the probabilities reweighs."""
    out: list[dict[str, np.ndarray]] = [{} for _ in range(state.n)]
    for i in range(state.n):
        for m, (f, at) in state.per_spec[i].items():
            out[i][model_label(m)] = _chi2_points(state, i, f.pred[at])
    # the discrepancies' models at their joint optimum with the discrepancy's mean
    for effects, rows in finals.items():
        for pos, i in enumerate(rows):
            fit = gp[effects]
            out[i][outside_label(effects)] = _chi2_points(
                state, i, fit.pred[pos], fit.delta_at_points[pos]
            )
    for i in range(state.n):
        if state.chosen[i]:
            out[i][UNEXPLAINED] = _chi2_points(state, i, alone.pred[i], alone.delta_at_points[i])
    return out


def _chi2_points(state: DiagnosisState, i: int, pred, delta: np.ndarray | float = 0.0):
    """Specimen ``i``'s chi-square contribution at each measured point, shape (p,), of curves
    ``pred`` (4, m) plus ``delta`` (a discrepancy's mean at the points, or 0)."""
    r = state.measured[i] - pred.double().numpy() - delta
    return (r / state.sigma[i])[state.mask[i]] ** 2


def _idle_effect(state: DiagnosisState, effects: Model, i: int) -> bool:
    """Whether model ``effects`` holds an effect that does nothing for specimen ``i``: the
    fitted model without it has (almost) the same chi-square and effective parameters. Such a
    model is its sub-model under another name, and is left out of the probabilities (counted,
    it would give the idle effect the prior odds of a further effect, about 0.27, however
    little the data say for it)."""
    fits = state.per_spec[i]
    f, at = fits[effects]
    for drop in effects:
        rest = effects.without(drop)
        if rest not in fits:
            continue
        g, bt = fits[rest]
        if (
            float(g.chi2[bt]) - float(f.chi2[at]) < IDLE_CHI2
            and float(f.trace[at]) - float(g.trace[bt]) < IDLE_PARAMETERS
        ):
            return True
    return False


def _outside_criteria(
    state: DiagnosisState, finals: dict[Model, list[int]], gp: dict[Model, DiscrepancyFit]
) -> np.ndarray:
    """Per specimen (n,): the criterion of its final model with its discrepancy,
    ``-2 log ML - sum ln sigma^2 + (k + a) ln n`` (``k`` the model's effective parameters,
    ``a`` the load cases whose discrepancy amplitude is not zero), comparable with the
    models' ``chi^2 + k ln n``."""
    out = np.full(state.n, np.inf)
    for effects, members in finals.items():
        rows = np.asarray(members)
        dfit = gp[effects]
        ok = state.mask[rows]
        log_noise = np.where(ok, np.log(state.sigma[rows] ** 2), 0.0).sum(axis=(1, 2))
        n_amp = (np.asarray(dfit.amplitude_deg) > 0).sum(axis=1)
        for pos, i in enumerate(rows):
            f, at = state.per_spec[i][effects]
            k = float(f.trace[at]) + float(n_amp[pos])
            out[i] = float(dfit.neg2_log_ml[pos] - log_noise[pos]) + k * float(state.log_n[i])
    return out
