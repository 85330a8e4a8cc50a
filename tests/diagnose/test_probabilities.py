"""Posterior probabilities of a specimen's explanations (femcal.diagnose.probabilities)."""

from __future__ import annotations

import numpy as np
import pytest

from femcal.diagnose.elimination import _explains_most
from femcal.diagnose.probabilities import (
    bootstrap_rng,
    bootstrap_weights,
    prior_cost,
    specimen_probabilities,
)
from femcal.effects.terms import Model

FIRST, FURTHER = 10.0, 2.0
M = Model.parse


def typed(crit: dict[tuple[str, ...], float]) -> dict[Model, float]:
    """Criteria by model, from criteria by the models' terms written."""
    return {M("+".join(k)): v for k, v in crit.items()}


def test_prior_cost_charges_the_first_effect_each_further_one_and_each_split():
    assert prior_cost(Model(), FIRST, FURTHER) == 0.0
    assert prior_cost(M("facet_contact"), FIRST, FURTHER) == FIRST
    assert prior_cost(M("facet_contact+neutral_zone"), FIRST, FURTHER) == FIRST + FURTHER
    assert prior_cost(M("facet_contact:split"), FIRST, FURTHER) == FIRST + FURTHER


def test_probabilities_are_the_criteria_weights_with_the_prior():
    crit = {(): 100.0, ("facet_contact",): 80.0, ("facet_contact:split",): 78.0}
    p = specimen_probabilities(typed(crit), (), FIRST, FURTHER)
    # scores 100, 90, 90: the disc e^-5 against 1 and 1
    w = np.exp(-np.array([10.0, 0.0, 0.0]) / 2)
    want = w / w.sum()
    assert p["models"]["none"] == pytest.approx(want[0], abs=1e-4)
    assert p["models"]["facet_contact"] == pytest.approx(want[1], abs=1e-4)
    assert p["inclusion"]["facet_contact"] == pytest.approx(want[1] + want[2], abs=1e-4)
    assert sum(p["models"].values()) == pytest.approx(1.0, abs=1e-3)
    assert p["outside_library"] == 0.0 and not p["unexplained"]
    assert p["most_probable"] in ("facet_contact", "facet_contact:split")
    assert tuple(p["most_probable_effects"]) in crit  # written terms


def test_two_explanations_that_fit_equally_share_the_probability():
    crit = {(): 200.0, ("facet_contact",): 50.0, ("facet_contact", "neutral_zone"): 48.0}
    p = specimen_probabilities(typed(crit), (), FIRST, FURTHER)
    assert p["models"]["facet_contact"] == pytest.approx(0.5, abs=1e-3)
    assert p["inclusion"]["neutral_zone"] == pytest.approx(0.5, abs=1e-3)
    assert p["inclusion"]["facet_contact"] == pytest.approx(1.0, abs=1e-3)


def test_a_discrepancy_that_pays_its_prior_makes_the_verdict_unexplained():
    crit = {(): 300.0, ("ligament_tension",): 120.0}
    # the discrepancy on the ligament model: 40 below it, beyond the first effect's 10
    p = specimen_probabilities(typed(crit), [(M("ligament_tension"), 80.0)], FIRST, FURTHER)
    assert p["unexplained"] and p["most_probable"] == "ligament_tension+unexplained"
    assert p["outside_library"] > 0.99 and p["inclusion"]["ligament_tension"] > 0.99
    q = specimen_probabilities(typed(crit), [(M("ligament_tension"), 115.0)], FIRST, FURTHER)
    assert not q["unexplained"] and q["most_probable"] == "ligament_tension"
    assert q["outside_library"] == pytest.approx(1 / (1 + np.exp(2.5)), abs=1e-3)


def test_a_discrepancy_in_place_of_the_effect_takes_its_certainty():
    # the ligament fits within the noise (criterion 120 + prior 10 = 130); the disc alone with
    # a discrepancy in the ligament's place scores 121 + 10 = 131: odds e^0.5 for the ligament
    crit = {(): 300.0, ("ligament_tension",): 120.0}
    lig = M("ligament_tension")
    on_top = (lig, 200.0)  # a discrepancy on top of the ligament does not pay
    p = specimen_probabilities(typed(crit), [on_top, (Model(), 121.0)], FIRST, FURTHER)
    want = 1 / (1 + np.exp(-0.5))
    assert p["inclusion"]["ligament_tension"] == pytest.approx(want, abs=1e-3)
    assert p["outside_library"] == pytest.approx(1 - want, abs=1e-3)
    assert p["most_probable"] == "ligament_tension" and not p["unexplained"]
    # where the discrepancy alone is the more probable, the verdict says so
    q = specimen_probabilities(typed(crit), [on_top, (Model(), 110.0)], FIRST, FURTHER)
    assert q["unexplained"] and q["most_probable"] == "unexplained"
    assert q["inclusion"]["ligament_tension"] < 0.01
    # without it, the ligament is certain
    r = specimen_probabilities(typed(crit), [on_top], FIRST, FURTHER)
    assert r["inclusion"]["ligament_tension"] > 0.999


def test_no_finite_criterion_gives_no_probabilities():
    p = specimen_probabilities({Model(): np.inf}, (), FIRST, FURTHER)
    assert p["models"] == {} and p["most_probable"] is None and not p["unexplained"]


class _Fit:
    def __init__(self, chi2):
        self.chi2 = np.array([chi2])


@pytest.mark.parametrize(
    ("chi2_rest", "needed"),
    [(450.0, True), (300.0, False)],  # disc-alone excess 464: the facet removes 390 or 240
)
def test_an_effect_that_removes_most_of_the_misfit_is_needed(chi2_rest, needed):
    fits = {Model(): (_Fit(500.0), 0), M("facet_contact"): (_Fit(60.0), 0)}
    fits[M("neutral_zone")] = (_Fit(chi2_rest), 0)
    current = M("facet_contact+neutral_zone")
    fits[current] = (_Fit(60.0), 0)
    assert _explains_most(fits, current, M("neutral_zone"), 36.0) is needed
    assert not _explains_most(fits, current, M("no_such"), 36.0)  # never fitted: no claim


def test_a_model_whose_further_effect_does_nothing_is_its_sub_model():
    from types import SimpleNamespace

    from femcal.diagnose.decide import _idle_effect

    def fit(chi2, trace):
        return (SimpleNamespace(chi2=np.array([chi2]), trace=np.array([trace])), 0)

    facet, both = M("facet_contact"), M("facet_contact+ligament_tension")
    state = SimpleNamespace(per_spec=[{Model(): fit(300.0, 5.0), facet: fit(40.0, 7.8)}])
    state.per_spec[0][both] = fit(39.9, 7.81)  # the ligament changes nothing
    assert _idle_effect(state, both, 0)
    assert not _idle_effect(state, facet, 0)  # the facet does: 260 in chi-square
    state.per_spec[0][both] = fit(37.0, 7.9)  # 3 in chi-square: it does something
    assert not _idle_effect(state, both, 0)
    state.per_spec[0][both] = fit(39.9, 8.6)  # the data determine 0.8 more parameters
    assert not _idle_effect(state, both, 0)
    del state.per_spec[0][facet]  # no sub-model fitted: nothing to compare with
    assert not _idle_effect(state, both, 0)


def test_where_an_effect_acts_is_the_share_of_its_models_acting_there():
    wide = "facet_contact@Extension,LateralBending,AxialRotation"
    lift = -2 * np.log(0.3 / 0.7)  # what acting in lateral bending costs: the prior's ratio
    crit = {(): 200.0, ("facet_contact",): 50.0, (wide,): 50.0 - lift}
    p = specimen_probabilities(typed(crit), (), FIRST, FURTHER)
    # equal scores once the prior's cost is counted: half the facet's probability acts there
    assert p["models"]["facet_contact"] == pytest.approx(p["models"][wide], abs=1e-3)
    where = p["acts_in"]["facet_contact"]
    assert where["LateralBending"] == pytest.approx(0.5, abs=1e-3)
    assert where["Extension"] == where["AxialRotation"] == 1.0
    assert p["inclusion"]["facet_contact"] == pytest.approx(1.0, abs=1e-3)


def _one_point_apart(p: int = 40, gap: float = 20.0) -> dict[str, np.ndarray]:
    """Two models fitting ``p`` points alike but at one, where the second misses by ``gap``
    chi-square units."""
    a = np.ones(p)
    b = a.copy()
    b[0] += gap
    return {"facet_contact": a, "ligament_tension": b}


def test_evidence_every_point_gives_alike_keeps_the_point_posterior():
    # each point says 0.5 chi-square units for the facet: a constant shift under every draw
    p = 40
    pointwise = {"facet_contact": np.ones(p), "ligament_tension": np.full(p, 1.5)}
    scores = np.array([pointwise[k].sum() for k in pointwise])
    w = bootstrap_weights(scores, np.stack(list(pointwise.values())), np.random.default_rng(0))
    point = np.exp(-(scores - scores.min()) / 2)
    np.testing.assert_allclose(w, point / point.sum(), rtol=1e-9)


def test_evidence_from_one_point_is_spread_over_the_models_that_fit():
    pointwise = _one_point_apart()
    crit = {(k,): float(v.sum()) for k, v in pointwise.items()}
    point = specimen_probabilities(typed(crit), (), FIRST, FURTHER)
    boot = specimen_probabilities(
        typed(crit), (), FIRST, FURTHER, pointwise=pointwise, rng=np.random.default_rng(0)
    )
    # 20 chi-square units: odds e^10 for the facet under the point posterior
    assert point["inclusion"]["facet_contact"] > 0.9999
    # under the bootstrap the one point weighs Exp(1) p / p: the facet's weight is
    # E[1 / (1 + exp(-10 E))], E ~ Exp(1), = 0.94 (Monte Carlo error 0.016)
    assert boot["inclusion"]["facet_contact"] == pytest.approx(0.94, abs=0.03)
    # the verdict's model is the point posterior's
    assert boot["most_probable"] == point["most_probable"] == "facet_contact"


def test_the_bootstrap_is_seeded_per_specimen():
    pointwise = _one_point_apart()
    crit = {(k,): float(v.sum()) for k, v in pointwise.items()}

    def run(name: str) -> dict:
        rng = bootstrap_rng(0, name)
        return specimen_probabilities(typed(crit), (), FIRST, FURTHER, pointwise=pointwise, rng=rng)

    assert run("S01")["models"] == run("S01")["models"]
    assert run("S01")["models"] != run("S02")["models"]


def test_the_bootstrap_needs_every_models_points():
    pointwise = _one_point_apart()
    crit = {(k,): float(v.sum()) for k, v in pointwise.items()}
    crit[()] = 500.0  # the disc alone, without pointwise contributions: the point posterior
    p = specimen_probabilities(
        typed(crit), (), FIRST, FURTHER, pointwise=pointwise, rng=np.random.default_rng(0)
    )
    assert p["inclusion"]["facet_contact"] > 0.9999
