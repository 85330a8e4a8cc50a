"""The selection rule of experiments/bench_selection_ceiling.py (issue 11's bound on bar (a))."""

from __future__ import annotations

import pytest

from experiments.bench_selection_ceiling import rule_right, select

#: criteria of one specimen: the pair 1.5 below the facet alone, the triple 0.7 below the pair
CRITERIA = {
    "": 80.0,
    "facet_contact": 40.0,
    "ligament_tension": 60.0,
    "facet_contact+ligament_tension": 38.5,
    "facet_contact+ligament_tension+neutral_zone": 37.8,
}


@pytest.mark.parametrize(
    ("tau", "expected"),
    [
        (0.0, ("facet_contact", "ligament_tension", "neutral_zone")),  # the lowest criterion
        (1.0, ("facet_contact", "ligament_tension")),  # 38.5 + 1 < 37.8 + 2 and < 40
        (2.0, ("facet_contact",)),  # 40 < 38.5 + 2 and < 37.8 + 4
    ],
)
def test_select_charges_each_further_effect_tau(tau, expected):
    assert select(CRITERIA, 10.0, tau) == expected


def test_select_keeps_the_disc_alone_when_no_effect_pays_the_first_gain():
    assert select({"": 45.0, "facet_contact": 36.0}, 10.0, 2.0) == ()
    assert select({"": 46.5, "facet_contact": 36.0}, 10.0, 2.0) == ("facet_contact",)


def test_rule_right_counts_the_out_of_library_verdicts_and_the_rule_on_the_rest():
    row = {
        "n_ool_right": 2,
        "specimens": [
            {"truth": "facet_contact", "criteria": CRITERIA, "own": {}},
            {"truth": "facet_contact+ligament_tension", "criteria": CRITERIA, "own": {}},
        ],
    }
    assert rule_right(row, 10.0, 2.0) == 3  # the facet right, the pair not
    assert rule_right(row, 10.0, 1.0) == 3  # the pair right, the facet not
    assert rule_right(row, 10.0, 2.0, key="own") == 2  # no own fits: only the verdicts
