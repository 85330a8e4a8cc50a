"""Where an effect may act: its prior per load case and the terms naming its forms
(femcal.effects.terms)."""

from __future__ import annotations

import math

import pytest
import torch

from femcal.effects import Effect, EffectParameter, get_effect, register_effect
from femcal.effects.split import base_name, is_split
from femcal.effects.terms import (
    Term,
    acting_in,
    as_split,
    case_prior_cost,
    cases_of,
    format_term,
    model_case_cost,
    parse_term,
    toggles,
    with_cases,
)
from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

WIDE_FACET = "facet_contact@Extension,LateralBending,AxialRotation"


def test_the_built_in_effects_act_in_their_likely_load_cases():
    assert get_effect("facet_contact").load_cases == ("Extension", "AxialRotation")
    assert get_effect("ligament_tension").load_cases == ("Flexion", "LateralBending")
    assert get_effect("neutral_zone").load_cases == tuple(LOAD_CASES)
    assert get_effect("facet_contact").load_case_prior["LateralBending"] == 0.3
    assert get_effect("ligament_tension").load_case_prior["Extension"] == 0.3
    assert "Flexion" not in get_effect("facet_contact").load_case_prior


def test_a_term_is_parsed_and_formatted_back():
    assert parse_term("facet_contact") == Term("facet_contact")
    assert parse_term("facet_contact:split") == Term("facet_contact", split=True)
    term = parse_term(WIDE_FACET + ":split")
    assert term == Term("facet_contact", True, ("Extension", "LateralBending", "AxialRotation"))
    assert str(term) == WIDE_FACET + ":split"
    # the likely load cases are left out; any order of the load cases is read
    assert format_term(Term("facet_contact", False, ("AxialRotation", "Extension"))) == (
        "facet_contact"
    )
    assert str(parse_term("facet_contact@AxialRotation,LateralBending,Extension")) == WIDE_FACET
    assert base_name(WIDE_FACET + ":split") == "facet_contact" and is_split(WIDE_FACET + ":split")
    assert as_split(WIDE_FACET) == WIDE_FACET + ":split"
    assert with_cases("facet_contact:split", cases_of(WIDE_FACET)) == WIDE_FACET + ":split"


def test_a_term_with_an_unknown_load_case_is_refused():
    with pytest.raises(ConfigError, match=r"after '@' give load cases from .*got \['Torsion'\]"):
        parse_term("facet_contact@Torsion")
    with pytest.raises(ConfigError, match="got none"):
        parse_term("facet_contact@")


def test_an_effect_outside_its_prior_is_refused():
    with pytest.raises(ConfigError, match=r"may act in .* only \(its load_case_prior\).*Flexion"):
        get_effect("facet_contact@Flexion,Extension")


def test_a_term_acting_elsewhere_is_the_same_law_in_other_load_cases():
    wide = get_effect(WIDE_FACET)
    assert wide is acting_in(get_effect("facet_contact"), cases_of(WIDE_FACET))
    assert wide.name == WIDE_FACET and issubclass(wide, get_effect("facet_contact"))
    assert wide.load_case_mask().tolist() == [False, True, True, True]
    split = get_effect(WIDE_FACET + ":split")
    assert split.name == WIDE_FACET + ":split" and split.tied is wide
    assert "facet_gap_deg[LateralBending]" in [q.name for q in split.parameters]
    u = torch.rand(3, len(wide.parameters), generator=torch.Generator().manual_seed(0))
    x = torch.rand(3, 1, 5, generator=torch.Generator().manual_seed(1)) * 6
    assert torch.equal(
        wide().moment(x, wide.from_unit(u)),
        get_effect("facet_contact")().moment(x, wide.from_unit(u)),
    )


def test_the_prior_prices_a_set_of_load_cases_against_the_likely_one():
    assert case_prior_cost("facet_contact") == 0.0
    assert case_prior_cost(WIDE_FACET) == pytest.approx(-2 * math.log(0.3 / 0.7))
    assert case_prior_cost("facet_contact@Extension") == pytest.approx(-2 * math.log(0.1 / 0.9))
    assert case_prior_cost("neutral_zone:split") == 0.0
    assert model_case_cost(("facet_contact", WIDE_FACET)) == pytest.approx(
        case_prior_cost(WIDE_FACET)
    )


def test_the_toggles_add_or_leave_out_one_load_case_the_prior_leaves_open():
    assert toggles("facet_contact") == [
        "facet_contact@AxialRotation",
        WIDE_FACET,
        "facet_contact@Extension",
    ]
    # a split form keeps two load cases; a prior of 1 is never toggled
    assert toggles("facet_contact:split") == [WIDE_FACET + ":split"]
    assert toggles("neutral_zone") == []


class _Fixed(Effect):
    name = "fixed_spring"
    kind = "parallel"
    load_cases = ("Flexion",)
    parameters = (EffectParameter("k", "Nm/deg", 0.0, 1.0),)

    def moment(self, rotation_deg, p):
        return p["k"].reshape(-1, 1, 1) * rotation_deg.clamp_min(0.0)


def test_a_plugin_declaring_only_load_cases_acts_there_with_prior_one(clean_registry):
    cls = register_effect(_Fixed)
    assert cls.load_case_prior == {"Flexion": 1.0}
    assert toggles("fixed_spring") == [] and case_prior_cost("fixed_spring") == 0.0
    assert math.isinf(case_prior_cost("fixed_spring@Extension"))
    with pytest.raises(ConfigError, match="may act in"):
        get_effect("fixed_spring@Flexion,Extension")


def test_a_plugin_declaring_a_prior_gets_its_load_cases_from_it(clean_registry):
    @register_effect
    class Capsule(_Fixed):
        name = "capsule"
        load_case_prior = {"AxialRotation": 0.8, "LateralBending": 0.2}

    assert Capsule.load_cases == ("AxialRotation",)
    assert toggles("capsule") == ["capsule@LateralBending,AxialRotation"]


def test_a_bad_prior_is_refused(clean_registry):
    class Both(_Fixed):
        name = "both_declared"
        load_cases = ("Flexion",)
        load_case_prior = {"Extension": 0.9}

    with pytest.raises(ConfigError, match="Declare one of them"):
        register_effect(Both)

    class Unlikely(_Fixed):
        name = "unlikely"
        load_case_prior = {"Extension": 0.2}

    with pytest.raises(ConfigError, match="give one load case a prior >= 0.5"):
        register_effect(Unlikely)

    class Outside(_Fixed):
        name = "outside"
        load_case_prior = {"Extension": 1.5, "Torsion": 0.5}

    with pytest.raises(ConfigError, match=r"probabilities in \[0, 1\]; got .*Torsion"):
        register_effect(Outside)


def test_a_name_holding_the_terms_marks_is_refused(clean_registry):
    class Marked(_Fixed):
        name = "spring@Flexion"

    with pytest.raises(ConfigError, match="holds one of"):
        register_effect(Marked)


def test_a_comma_list_keeps_each_terms_load_cases():
    """``--effects`` takes a comma-separated list; a term's own load cases stay with it."""
    from femcal.effects.terms import split_terms

    assert split_terms("ligament_tension@Flexion,Extension:split, neutral_zone") == [
        "ligament_tension@Flexion,Extension:split",
        "neutral_zone",
    ]
    assert split_terms("facet_contact,ligament_tension,") == ["facet_contact", "ligament_tension"]
    assert split_terms("facet_contact@Extension,LateralBending,AxialRotation") == [
        "facet_contact@Extension,LateralBending,AxialRotation"
    ]
