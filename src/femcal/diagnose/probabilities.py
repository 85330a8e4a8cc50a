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

*Outside the library*: a model with a smooth discrepancy (the Gaussian process of
:mod:`femcal.diagnose.discrepancy`, its amplitude per load case by type-II maximum likelihood),
weighted by its marginal likelihood, ``-2 log ML + (k + a) ln n + P + first``, ``a`` the load
cases whose amplitude is not zero: a discrepancy is named like a first effect. Two such models
compete: the chosen model with a discrepancy on top (an effect helped but did not finish the
job), and the disc alone with a discrepancy in place of every effect (the effects only stood in
for physics the library lacks: a softening, a law of another family). The second is what keeps
a flexible effect that fits within the noise from being named with certainty where a smooth
discrepancy explains the data about as well.

The inclusion probability of an effect is the sum over the models that hold it (tied or split,
in any load cases, and the discrepancy's model when it holds it); the probability that it acts
in a load case is the share, among those, of the models in which it acts there
(:func:`acts_in`).

*Honest where nothing in the library is the truth* (:func:`bootstrap_weights`). The weights
above hold where one of the fitted models is the truth. Where none is (a law from outside the
library's families, a structure in a load case the library does not let it act in, a disc
outside the box), two models can both fit within the noise, each a little better at some
points, and a few chi-square units decide between them: a flexible effect standing in for
something else then gets the probability of a found one. The reported probabilities are
therefore averaged over the Bayesian bootstrap of the measured points (pseudo-BMA+, Yao et al.
2018, *Bayesian Analysis* 13(3)): each draw weighs the points with Dirichlet(1, ..., 1) weights
(scaled to the point count) in every model's chi-square, the penalties and prior costs kept,
and the weights of each draw are averaged. Evidence that every point gives keeps its
probability; evidence from a few points, or that points give both ways, spreads it over the
models that fit. The most probable model, which the verdict names, is the point posterior's
(uniform weights), so the verdicts are those of the criterion.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence

import numpy as np

from femcal.diagnose.result import UNEXPLAINED, model_label
from femcal.effects.terms import Model
from femcal.schema import LOAD_CASES

#: Bayesian-bootstrap draws per specimen: the Monte Carlo error of a probability averaged over
#: them is at most 0.5 / sqrt(draws) = 0.016.
BOOTSTRAP_DRAWS = 1000


def bootstrap_rng(seed: int, specimen: str) -> np.random.Generator:
    """The bootstrap's generator for one specimen, from the diagnosis' seed and the specimen's
    name: its draws do not depend on which specimens are diagnosed together."""
    return np.random.default_rng([int(seed), zlib.crc32(str(specimen).encode())])


def bootstrap_weights(
    scores: np.ndarray, pointwise: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Model weights averaged over the Bayesian bootstrap of the measured points.

    Parameters
    ----------
    scores : ndarray, shape (k,)
        Each model's score, ``chi^2 + penalty + prior cost`` (finite).
    pointwise : ndarray, shape (k, p)
        Each model's chi-square contribution at each of the specimen's ``p`` measured points
        (summing to its chi-square).
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (k,)
        The mean over :data:`BOOTSTRAP_DRAWS` draws of ``exp(-S_b / 2)`` normalized, where
        ``S_b = scores + sum_j (p a_j - 1) pointwise_j`` and ``a ~ Dirichlet(1, ..., 1)``
        (``a_j = 1 / p`` gives the scores themselves).
    """
    scores = np.asarray(scores, dtype=float)
    pointwise = np.asarray(pointwise, dtype=float)
    p = pointwise.shape[1]
    if p < 2 or len(scores) < 2:
        w = np.exp(-(scores - scores.min()) / 2)
        return w / w.sum()
    a = rng.dirichlet(np.ones(p), size=BOOTSTRAP_DRAWS) * p  # (B, p), each row sums to p
    s = scores[None, :] + (a - 1.0) @ pointwise.T  # (B, k)
    s -= s.min(axis=1, keepdims=True)
    w = np.exp(-s / 2)
    return (w / w.sum(axis=1, keepdims=True)).mean(axis=0)


def prior_cost(effects: Model, first: float, further: float) -> float:
    """The evidence (criterion units) a model needs before it is named: ``first`` for its
    first effect, ``further`` for every further effect and every split form."""
    if not effects:
        return 0.0
    return first + further * (len(effects) - 1 + effects.n_split)


def model_prior_cost(effects: Model, first: float, further: float) -> float:
    """:func:`prior_cost` plus what the load cases its effects act in cost against their
    likely ones (:meth:`femcal.effects.terms.Model.case_cost`)."""
    return prior_cost(effects, first, further) + effects.case_cost()


def outside_label(effects: Model) -> str:
    """The label of model ``effects`` with a discrepancy: ``a+b+unexplained`` (the disc
    alone's: ``unexplained``)."""
    return f"{model_label(effects)}+{UNEXPLAINED}" if effects else UNEXPLAINED


def outside_models(chosen: Model) -> tuple[Model, ...]:
    """The models a discrepancy is fitted on for a specimen whose chosen model is ``chosen``:
    that model, and the disc alone where ``chosen`` has effects."""
    return (chosen, Model()) if chosen else (chosen,)


def acts_in(prob: Mapping[str, float], models: Mapping[str, Model]) -> dict:
    """Per effect, the probability that it acts in each load case given that it is present:
    over the models that hold it (``prob``: label -> probability, ``models``: label ->
    model), the share of those in which it acts there."""
    held: dict[str, float] = {}
    where: dict[str, dict[str, float]] = {}
    for label, p in prob.items():
        for term in models[label]:
            e = term.effect
            held[e] = held.get(e, 0.0) + p
            for lc in term.acting:
                where.setdefault(e, {})[lc] = where.setdefault(e, {}).get(lc, 0.0) + p
    return {
        e: {lc: round(where[e].get(lc, 0.0) / held[e], 4) for lc in LOAD_CASES if lc in where[e]}
        for e in sorted(where)
        if held[e] > 0
    }


def specimen_probabilities(
    criteria: Mapping[Model, float],
    outside: Sequence[tuple[Model, float]],
    first: float,
    further: float,
    pointwise: Mapping[str, np.ndarray] | None = None,
    rng: np.random.Generator | None = None,
) -> dict:
    """Posterior probabilities of one specimen's explanations.

    Parameters
    ----------
    criteria : mapping of Model to float
        Every fitted model's criterion (the disc alone is ``Model()``).
    outside : sequence of (Model, float)
        Each model a discrepancy sits on and the criterion of that model with its
        discrepancy (``-2 log ML - sum ln sigma^2 + (k + a) ln n``): the chosen model's first,
        then the disc alone's where the chosen model has effects (:func:`outside_models`);
        empty where no discrepancy was fitted.
    first, further : float
        Prior costs (:func:`prior_cost`).
    pointwise : mapping of str to ndarray of shape (p,), optional
        Per model label (as in ``models``), its chi-square contribution at each measured
        point. Given for every model with ``rng``, the reported probabilities are the
        Bayesian bootstrap's (:func:`bootstrap_weights`); else the point posterior's.
    rng : numpy.random.Generator, optional
        The bootstrap's generator (:func:`bootstrap_rng`).

    Returns
    -------
    dict
        ``models``: label -> probability (``a+b``, ``a:split``, ``none``, and
        ``<model>+unexplained`` and ``unexplained`` for the discrepancies), most probable first;
        ``inclusion``: effect name -> probability; ``outside_library``: the discrepancies'
        probability;
        ``most_probable``: the top label of the point posterior and ``most_probable_effects``
        its model's terms, written; ``unexplained``: a discrepancy is more probable than the chosen
        model alone (point posterior);
        ``acts_in``: effect -> load case -> the probability that it acts there given that it
        is present (:func:`acts_in`).
    """
    scores = {
        model_label(m): (m, c + model_prior_cost(m, first, further)) for m, c in criteria.items()
    }
    for m, c in outside:
        scores[outside_label(m)] = (m, c + model_prior_cost(m, first, further) + first)
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
    labels = list(finite)
    c = np.array([finite[k][1] for k in labels])
    point = np.exp(-(c - c.min()) / 2)
    point /= point.sum()
    weights = point
    if rng is not None and pointwise is not None and all(k in pointwise for k in labels):
        weights = bootstrap_weights(c, np.stack([pointwise[k] for k in labels]), rng)
    prob = {labels[j]: float(weights[j]) for j in np.argsort(-weights, kind="stable")}
    top = labels[int(np.argmax(point))]
    inclusion: dict[str, float] = {}
    for label, p in prob.items():
        for e in set(finite[label][0].effects):
            inclusion[e] = inclusion.get(e, 0.0) + p
    out_labels = [k for k in labels if k.endswith(UNEXPLAINED)]
    own = model_label(outside[0][0]) if outside else None
    at = {k: j for j, k in enumerate(labels)}
    point_own = point[at[own]] if own in at else 0.0
    point_out = max((point[at[k]] for k in out_labels), default=0.0)
    return {
        "unexplained": bool(point_out > point_own),
        "models": {k: round(p, 4) for k, p in prob.items() if p >= 1e-4},
        "inclusion": {k: round(v, 4) for k, v in sorted(inclusion.items())},
        "outside_library": round(sum(prob[k] for k in out_labels), 4),
        "most_probable": top,
        "most_probable_effects": [str(t) for t in finite[top][0]],
        "acts_in": acts_in(prob, {k: m for k, (m, _) in finite.items()}),
    }
