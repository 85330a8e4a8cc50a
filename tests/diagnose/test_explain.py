"""What to measure next (femcal.diagnose.explain.next_measurement) on given model curves."""

from __future__ import annotations

import numpy as np
import pytest

from femcal.diagnose import explain
from femcal.effects.terms import Model

DENSE = np.array([1.0, 2.0, 4.0, 8.0])
SIGMA = np.full(4, 0.05)


M = Model.parse


class _Table(dict):
    pass


@pytest.fixture
def curves(monkeypatch):
    """Each model's dense curves (4, 4) by its effects; no parameter covariance."""
    base = np.tile(np.array([1.0, 2.0, 3.0, 4.0]), (4, 1))
    table = _Table(
        {
            M(""): base,
            M("facet_contact"): base - np.array([0.0, 0.0, 0.1, 0.3]),
            # the chosen model with a further effect fitted to nothing: the same curves
            M("facet_contact+ligament_tension"): base - np.array([0.0, 0.0, 0.1, 0.3]) + 1e-4,
            M("facet_contact+neutral_zone"): base - np.array([0.15, 0.0, 0.1, 0.3]),
        }
    )
    table.sd = {}  # a model's prediction sd (4, q) where it has one; else zero
    table.jacobians = []  # the models whose sd was asked for

    def prediction(dense_base, effects, fit, pos, sd=True):
        if sd:
            table.jacobians.append(effects)
        return table[effects], table.sd.get(effects, np.zeros((4, 1))) if sd else np.zeros((4, 1))

    monkeypatch.setattr(explain, "_dense_prediction", prediction)
    return table


def _ranking(criteria: dict[tuple[str, ...], float]):
    return [
        {"effects": list(e), "effect": "+".join(e) or "none", "criterion": c}
        for e, c in criteria.items()
    ]


def _next(ranking, min_delta=10.0):
    fits = {M(r["effect"]): (None, 0) for r in ranking}
    return explain.next_measurement(
        ranking, fits, object(), DENSE, SIGMA, min_delta, M("facet_contact")
    )


def test_the_rival_named_is_the_one_fewest_measurements_settle(curves):
    ranking = _ranking(
        {
            ("facet_contact",): 20.0,
            ("facet_contact", "ligament_tension"): 21.0,  # closest, predicts the same
            ("facet_contact", "neutral_zone"): 26.0,  # 3 sigma apart at 1 Nm
            (): 60.0,  # beyond min_delta
        }
    )
    n = _next(ranking)
    assert n["between"] == ["facet_contact", "facet_contact+neutral_zone"]
    assert n["criterion_gap"] == pytest.approx(6.0)
    assert (n["load_case"], n["moment_nm"]) == ("Flexion", 1.0)
    assert n["difference_sigma"] == pytest.approx(3.0)
    assert n["repeats_to_settle"] == 2  # (10 + 6) / 3^2 = 1.8


def test_no_rival_within_min_delta_means_nothing_to_measure(curves):
    ranking = _ranking({("facet_contact",): 20.0, ("facet_contact", "neutral_zone"): 30.0})
    assert _next(ranking) is None
    assert _next(ranking, min_delta=10.5)["between"][1] == "facet_contact+neutral_zone"


def test_rivals_that_predict_the_same_are_named_with_no_measurement_to_make(curves):
    ranking = _ranking({("facet_contact",): 20.0, ("facet_contact", "ligament_tension"): 21.0})
    n = _next(ranking)
    assert n["between"][1] == "facet_contact+ligament_tension"
    assert n["difference_sigma"] == pytest.approx(1e-4 / 0.05)
    assert n["repeats_to_settle"] > 10**6


def test_a_rival_whose_own_uncertainty_hides_its_difference_is_passed_over(curves):
    """The rival whose curves differ most has a prediction sd that hides the difference (its
    parameters are not pinned where it differs): the other one is named, as trying every
    rival with its sd would; the Jacobian of a rival that cannot win is never computed."""
    curves.sd[M("facet_contact+neutral_zone")] = np.full((4, 4), 1.0)
    curves[M("facet_contact+ligament_tension")] = curves[M("facet_contact")] + 0.05
    curves[M("facet_contact+ligament_tension+neutral_zone")] = curves[M("facet_contact")]
    ranking = _ranking(
        {
            ("facet_contact",): 20.0,
            ("facet_contact", "ligament_tension"): 25.0,  # 1 sigma apart everywhere
            ("facet_contact", "neutral_zone"): 26.0,  # 3 sigma on its curves, ~0.15 with sd
            ("facet_contact", "ligament_tension", "neutral_zone"): 22.0,  # the same curves
        }
    )
    n = _next(ranking)
    assert n["between"][1] == "facet_contact+ligament_tension"
    assert n["repeats_to_settle"] == 15  # (10 + 5) / 1^2
    # the chosen model, then the rivals by their bound until none can win: the same curves
    # (bound: never settles) is never refined
    assert curves.jacobians == [
        M("facet_contact"),
        M("facet_contact+neutral_zone"),
        M("facet_contact+ligament_tension"),
    ]


@pytest.mark.parametrize(("rival_sd", "expected"), [(0.0, 2), (0.03, 5), (0.04, None)])
def test_a_rivals_own_uncertainty_is_not_averaged_out_by_repeats(curves, rival_sd, expected):
    """A rival whose prediction the data do not pin refits to new points: its prediction
    variance v is shared by repeats like the surrogate's error, k = noise^2 / (delta^2 /
    needed - v) (delta 0.15 deg at 1 Nm, noise 0.05, needed 10 + 6: 1.8 -> 2 without sd,
    4.9 -> 5 with sd 0.03; with 0.04, v alone exceeds delta^2 / needed: never)."""
    curves.sd[M("facet_contact+neutral_zone")] = np.full((4, 4), rival_sd)
    ranking = _ranking({("facet_contact",): 20.0, ("facet_contact", "neutral_zone"): 26.0})
    n = _next(ranking)
    assert n["repeats_to_settle"] == expected
    assert n["difference_sigma"] == pytest.approx(0.15 / np.hypot(0.05, rival_sd))
