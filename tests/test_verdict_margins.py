"""experiments.verdict_margins: each wrong verdict against the best fit of the true effects."""

from __future__ import annotations

import pytest

from experiments.verdict_margins import (
    LEFT_OUT,
    NOT_FITTED,
    PREFERRED,
    WITHIN,
    margins,
    table,
)
from femcal.diagnose import DiagnoseOptions
from femcal.effects.base import available_effects

OPTIONS = DiagnoseOptions()  # min_delta 10, min_delta_inadequate 2


@pytest.fixture(autouse=True)
def _effects():
    available_effects()


def _specimen(effects, model, ranking, kept):
    return {
        "specimen": "7",
        "effects": effects,
        "verdict": "+".join(effects) or "none",
        "model": model,
        "ranking": [{"effect": e, "criterion": c} for e, c in ranking],
        "probabilities": {"models": {k: 0.5 for k in kept}},
    }


def test_a_right_verdict_has_no_row():
    s = _specimen(["facet_contact"], ["facet_contact"], [("facet_contact", 50.0)], [])
    assert margins(s, {"facet_contact"}, OPTIONS) is None


def test_scores_add_the_probabilities_prior_costs():
    # facet_contact+neutral_zone: 10 + 2 (a further effect); facet_contact: 10
    s = _specimen(
        ["facet_contact", "neutral_zone"],
        ["facet_contact", "neutral_zone"],
        [("facet_contact+neutral_zone", 80.0), ("facet_contact", 83.5), ("none", 300.0)],
        ["facet_contact+neutral_zone", "facet_contact"],
    )
    row = margins(s, {"facet_contact"}, OPTIONS)
    assert row["chosen_score"] == 92.0 and row["true_score"] == 93.5
    assert row["gap"] == 1.5 and row["reading"] == WITHIN
    s["ranking"][1]["criterion"] = 90.0
    assert margins(s, {"facet_contact"}, OPTIONS)["reading"] == PREFERRED


def test_a_best_true_set_missing_from_the_probabilities_is_left_out():
    s = _specimen(
        ["ligament_tension", "neutral_zone"],
        ["ligament_tension", "neutral_zone"],
        [
            ("ligament_tension@Flexion,Extension,LateralBending", 70.0),
            ("ligament_tension+neutral_zone", 75.0),
        ],
        ["ligament_tension+neutral_zone"],
    )
    row = margins(s, {"ligament_tension"}, OPTIONS)
    assert row["reading"] == LEFT_OUT and row["gap"] < 0
    assert row["true_model"] == "ligament_tension@Flexion,Extension,LateralBending"


def test_an_unfitted_true_set_and_the_table():
    s = _specimen(["neutral_zone"], ["neutral_zone"], [("neutral_zone", 60.0)], ["neutral_zone"])
    row = margins(s, {"facet_contact", "ligament_tension"}, OPTIONS)
    assert row["reading"] == NOT_FITTED and row["true_score"] is None
    text = table([row])
    assert "| 7 | `facet_contact+ligament_tension` | `neutral_zone` | 70.0 | - | - | - |" in text
    assert text.endswith(f"{NOT_FITTED}: 1")
