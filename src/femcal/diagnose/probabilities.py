"""How probable each explanation of a specimen is: every fitted model, each effect, and
something outside the library.

Every model the diagnosis fitted to a specimen gets the weight ``exp(-(C + P) / 2)``: ``C`` its
criterion (``chi^2 + k ln n`` with ``k`` the effective number of parameters, the BIC's
approximation of -2 log evidence) and ``P`` its prior cost, the evidence the search asks of
it before it names it (``first`` for the first effect, ``further`` for each further one or a
split form: :func:`prior_cost`), and what the load cases its effects act in cost against
their likely ones, ``-2 ln`` of the ratio of their priors (:func:`model_prior_cost`,
:mod:`femcal.effects.terms`). So the search's bars are prior odds, and the most probable
model is what a search that saw every model would name.

*Outside the library*: the chosen model with a smooth discrepancy (the Gaussian process of
:mod:`femcal.diagnose.discrepancy`, its amplitude per load case by type-II maximum likelihood),
weighted by its marginal likelihood, ``-2 log ML + (k + a) ln n + P + first``, ``a`` the load
cases whose amplitude is not zero: a discrepancy is named like a first effect. The model's
probabilities are shared out over the rest.

The inclusion probability of an effect is the sum over the models that hold it (tied or split,
in any load cases, and the discrepancy's model when it holds it); the probability that it acts
in a load case is the share, among those, of the models in which it acts there
(:func:`acts_in`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from femcal.diagnose.result import UNEXPLAINED, model_label
from femcal.effects.split import base_name, is_split
from femcal.effects.terms import cases_of, model_case_cost
from femcal.schema import LOAD_CASES

Model = tuple[str, ...]


def prior_cost(effects: Model, first: float, further: float) -> float:
    """The evidence (criterion units) a model needs before it is named: ``first`` for its
    first effect, ``further`` for every further effect and every split form."""
    if not effects:
        return 0.0
    return first + further * (len(effects) - 1 + sum(is_split(e) for e in effects))


def model_prior_cost(effects: Model, first: float, further: float) -> float:
    """:func:`prior_cost` plus what the load cases its effects act in cost against their
    likely ones (:func:`femcal.effects.terms.model_case_cost`)."""
    return prior_cost(effects, first, further) + model_case_cost(effects)


def acts_in(prob: Mapping[str, float], models: Mapping[str, Model]) -> dict:
    """Per effect, the probability that it acts in each load case given that it is present:
    over the models that hold it (``prob``: label -> probability, ``models``: label ->
    model), the share of those in which it acts there."""
    held: dict[str, float] = {}
    where: dict[str, dict[str, float]] = {}
    for label, p in prob.items():
        for term in models[label]:
            e = base_name(term)
            held[e] = held.get(e, 0.0) + p
            for lc in cases_of(term):
                where.setdefault(e, {})[lc] = where.setdefault(e, {}).get(lc, 0.0) + p
    return {
        e: {lc: round(where[e].get(lc, 0.0) / held[e], 4) for lc in LOAD_CASES if lc in where[e]}
        for e in sorted(where)
        if held[e] > 0
    }


def specimen_probabilities(
    criteria: Mapping[Model, float],
    outside: tuple[Model, float] | None,
    first: float,
    further: float,
) -> dict:
    """Posterior probabilities of one specimen's explanations.

    Parameters
    ----------
    criteria : mapping of tuple of str to float
        Every fitted model's criterion (the disc alone is ``()``).
    outside : (tuple of str, float) or None
        The model the discrepancy sits on and the criterion of that model with the
        discrepancy (``-2 log ML - sum ln sigma^2 + (k + a) ln n``), or None.
    first, further : float
        Prior costs (:func:`prior_cost`).

    Returns
    -------
    dict
        ``models``: label -> probability (``a+b``, ``a:split``, ``none``, and
        ``<model>+unexplained`` for the discrepancy), most probable first; ``inclusion``:
        effect name -> probability; ``outside_library``: the discrepancy's probability;
        ``most_probable``: the top label and ``most_probable_effects`` its model's effects;
        ``unexplained``: the discrepancy is more probable than the model it sits on alone;
        ``acts_in``: effect -> load case -> the probability that it acts there given that it
        is present (:func:`acts_in`).
    """
    scores = {
        model_label(m): (m, c + model_prior_cost(m, first, further)) for m, c in criteria.items()
    }
    if outside is not None:
        m, c = outside
        label = f"{model_label(m)}+{UNEXPLAINED}" if m else UNEXPLAINED
        scores[label] = (m, c + model_prior_cost(m, first, further) + first)
    finite = {k: v for k, v in scores.items() if np.isfinite(v[1])}
    if not finite:
        return {
            "unexplained": False,
            "models": {},
            "inclusion": {},
            "outside_library": 0.0,
            "most_probable": None,
            "most_probable_effects": [],
            "acts_in": {},
        }
    low = min(c for _, c in finite.values())
    weight = {k: float(np.exp(-(c - low) / 2)) for k, (_, c) in finite.items()}
    total = sum(weight.values())
    prob = {k: w / total for k, w in sorted(weight.items(), key=lambda kv: -kv[1])}
    inclusion: dict[str, float] = {}
    for label, p in prob.items():
        for e in {base_name(e) for e in finite[label][0]}:
            inclusion[e] = inclusion.get(e, 0.0) + p
    out_label = next((k for k in prob if k.endswith(UNEXPLAINED)), None)
    own = model_label(outside[0]) if outside is not None else None
    return {
        "unexplained": bool(out_label and prob[out_label] > prob.get(own, 0.0)),
        "models": {k: round(p, 4) for k, p in prob.items() if p >= 1e-4},
        "inclusion": {k: round(v, 4) for k, v in sorted(inclusion.items())},
        "outside_library": round(prob.get(out_label, 0.0), 4) if out_label else 0.0,
        "most_probable": next(iter(prob)),
        "most_probable_effects": list(finite[next(iter(prob))][0]),
        "acts_in": acts_in(prob, {k: m for k, (m, _) in finite.items()}),
    }
