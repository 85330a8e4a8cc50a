"""Where an effect acts: load cases chosen by the data within the effect's prior.

The "FE model" of this synthetic world is a small fitted surrogate, so the surrogate's own
error is zero. The hidden elements are numpy laws that are not the library's formulas (a
linear contact spring after a gap, a toe-then-linear ligament), and they act beyond the
built-in effects' likely load cases: facets that also impinge in lateral bending, ligaments
whose capsules also pull in extension.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from femcal.calibration import SurrogateCurveModel
from femcal.diagnose import diagnose
from femcal.diagnose.where import mapped_start, wide_terms
from femcal.effects.base import get_effect
from femcal.effects.terms import Model, Term
from femcal.schema import LOAD_CASES
from femcal.surrogates.nn import NeuralSurrogate

from synth import parallel_curves, study_space, tidy_table

NOISE = 0.02
MOMENTS = np.arange(1.0, 5.01, 0.5)
FLEX, EXT, LB, AR = (
    LOAD_CASES.index(c) for c in ("Flexion", "Extension", "LateralBending", "AxialRotation")
)
KINDS = ("facet_lb", "ligament_ext", "facet")


def _facet(fe_rom, lcs):  # a linear spring after a 1.5 deg gap
    return parallel_curves(MOMENTS, fe_rom, lcs, lambda p: 1.2 * np.clip(p - 1.5, 0, None), MOMENTS)


def _ligament(fe_rom, lcs):  # toe region (quadratic) then linear, slack 1.5 deg
    def law(p):
        s = np.clip(p - 1.5, 0, None)
        return np.where(s < 1.0, 0.6 * s**2, 0.6 + 1.2 * (s - 1.0))

    return parallel_curves(MOMENTS, fe_rom, lcs, law, MOMENTS)


@pytest.fixture(scope="module")
def world():
    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    rng = np.random.default_rng(5)
    configs = study_space().sample_uniform(6, rng)
    fe = SurrogateCurveModel(surrogate, MOMENTS).predict(configs)
    curves, truth = [], []
    for i, fe_rom in enumerate(fe):
        kind = KINDS[i % len(KINDS)]
        if kind == "facet_lb":
            c = _facet(fe_rom, [EXT, LB, AR])
        elif kind == "ligament_ext":
            c = _ligament(fe_rom, [FLEX, EXT, LB])
        else:
            c = _facet(fe_rom, [EXT, AR])
        curves.append(c)
        truth.append(kind)
    rom = np.stack(curves) + rng.normal(0, NOISE, (len(curves), 4, len(MOMENTS)))
    base = SurrogateCurveModel(surrogate, MOMENTS)
    specimens = [f"S{i:02d}" for i in range(len(rom))]
    diag = diagnose(base, rom, specimens=specimens, noise_deg=NOISE)
    return np.array(truth), diag


def test_a_facet_that_also_engages_in_lateral_bending_is_named_acting_there(world):
    truth, diag = world
    for s in (s for s, t in zip(diag.specimens, truth) if t == "facet_lb"):
        assert s.verdict == "facet_contact", (s.specimen, s.verdict, s.load_cases)
        assert s.load_cases["facet_contact"] == ["Extension", "LateralBending", "AxialRotation"]
        assert s.probabilities["acts_in"]["facet_contact"]["LateralBending"] > 0.9


def test_a_ligament_that_also_pulls_in_extension_is_named_acting_there(world):
    truth, diag = world
    for s in (s for s, t in zip(diag.specimens, truth) if t == "ligament_ext"):
        # The toe-then-linear law is not the library's exponential one: what the fitted law
        # leaves may be named `unexplained` beside it; the element is the ligament alone.
        assert s.effects == ["ligament_tension"], (s.specimen, s.verdict, s.load_cases)
        assert "Extension" in s.load_cases["ligament_tension"]
        assert s.probabilities["acts_in"]["ligament_tension"]["Extension"] > 0.9


def test_a_facet_in_its_likely_load_cases_stays_there(world):
    truth, diag = world
    for s in (s for s, t in zip(diag.specimens, truth) if t == "facet"):
        assert s.verdict == "facet_contact", (s.specimen, s.verdict)
        assert s.load_cases["facet_contact"] == ["Extension", "AxialRotation"]
        assert s.to_dict()["load_cases"] == s.load_cases


def test_the_wide_forms_are_the_effects_in_every_load_case_their_prior_allows():
    names = ["facet_contact", "ligament_tension", "neutral_zone"]
    assert [str(t) for t in wide_terms([Term.parse(n) for n in names])] == [
        "facet_contact@Extension,LateralBending,AxialRotation",
        "ligament_tension@Flexion,Extension,LateralBending",
    ]


def test_a_start_maps_each_parameter_by_name_and_a_new_load_case_from_the_others():
    tied = Model.parse("facet_contact:split")
    wide = Model.parse("facet_contact@Extension,LateralBending,AxialRotation:split")
    names_tied = [q.name for q in get_effect(tied.terms[0]).parameters]
    names_wide = [q.name for q in get_effect(wide.terms[0]).parameters]
    v = torch.cat(
        [
            torch.full((2, 13), 0.5),
            torch.rand(2, len(names_tied), generator=torch.Generator().manual_seed(0)),
        ],
        1,
    )
    out = mapped_start(v, tied, wide)
    assert out.shape == (2, 13 + len(names_wide))
    col = {n: 13 + j for j, n in enumerate(names_tied)}
    new = {n: 13 + j for j, n in enumerate(names_wide)}
    assert torch.equal(out[:, new["facet_exponent"]], v[:, col["facet_exponent"]])
    expected = 0.5 * (
        v[:, col["facet_gap_deg[Extension]"]] + v[:, col["facet_gap_deg[AxialRotation]"]]
    )
    assert torch.allclose(out[:, new["facet_gap_deg[LateralBending]"]], expected)
    assert torch.equal(mapped_start(out, wide, tied), v)
