"""Per-load-case effect parameters: the split form of an effect (femcal.effects.split)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.calibration.starts import single_effect_starts
from femcal.effects import Effect, EffectParameter, get_effect, register_effect
from femcal.effects.composite import EffectModel
from femcal.effects.split import base_name, has_split_form, split_effect
from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = [1.0, 2.0, 3.0, 4.0, 5.0]
BUILTIN = ["facet_contact", "ligament_tension", "neutral_zone"]


@pytest.fixture(scope="module")
def surrogate() -> NeuralSurrogate:
    table = tidy_table(40, seed=5)
    model = NeuralSurrogate(study_space(), hidden=(24, 24), max_epochs=30, batch_size=16, seed=0)
    return model.fit(table, table["rom_deg"].to_numpy())


@pytest.mark.parametrize("name", BUILTIN)
def test_a_split_with_equal_values_is_the_tied_effect(name):
    tied, split = get_effect(name), get_effect(f"{name}:split")
    assert split is split_effect(tied) and split.tied is tied and base_name(split.name) == name
    u = torch.rand(6, len(tied.parameters), generator=torch.Generator().manual_seed(0))
    x = torch.rand(6, 4, 7, generator=torch.Generator().manual_seed(1)) * 6 + 0.1
    p_tied, p_split = tied.from_unit(u), split.from_unit(split.expand_tied(u))
    law = "moment_at" if tied.kind == "parallel" else "rotation_at"
    a = getattr(tied(), law)(x, p_tied)
    b = getattr(split(), law)(x, p_split)
    own = tied.load_case_mask()[None, :, None]
    torch.testing.assert_close(b * own, a * own)  # exactly the tied law where it acts
    assert torch.all(b[:, ~tied.load_case_mask()] == 0)


def test_each_load_case_has_its_own_values():
    split = get_effect("facet_contact:split")
    names = [q.name for q in split.parameters]
    assert names == [
        "facet_gap_deg[Extension]",
        "facet_gap_deg[AxialRotation]",
        "facet_stiffness[Extension]",
        "facet_stiffness[AxialRotation]",
        "facet_exponent",
        "facet_onset_deg",
    ]
    u = torch.full((1, len(names)), 0.5)
    x = torch.full((1, 4, 3), 4.0)
    before = split().moment_at(x, split.from_unit(u))
    u[0, names.index("facet_stiffness[Extension]")] = 0.9  # stiffer facets in extension only
    after = split().moment_at(x, split.from_unit(u))
    ext, ar = LOAD_CASES.index("Extension"), LOAD_CASES.index("AxialRotation")
    assert torch.all(after[:, ext] > before[:, ext])
    torch.testing.assert_close(after[:, ar], before[:, ar])


def test_the_load_cases_of_a_partial_axis_are_named_by_cases():
    split = get_effect("facet_contact:split")
    u = torch.rand(2, len(split.parameters), generator=torch.Generator().manual_seed(3))
    p = split.from_unit(u)
    x = torch.rand(2, 4, 5, generator=torch.Generator().manual_seed(4)) * 5
    full = split().moment_at(x, p)
    cases = [LOAD_CASES.index("Extension"), LOAD_CASES.index("AxialRotation")]
    torch.testing.assert_close(split().moment_at(x[:, cases], p, cases), full[:, cases])


def test_split_forms_need_a_parameter_that_may_differ(clean_registry):
    @register_effect
    class Creep(Effect):
        name = "creep_test"
        kind = "series"
        load_cases = ("Flexion", "Extension")
        parameters = (EffectParameter("creep_deg", "deg", 0.0, 1.0),)

        def rotation(self, moment_nm, p):
            return p["creep_deg"].reshape(-1, 1, 1) * torch.tanh(moment_nm)

    assert not has_split_form("creep_test")
    with pytest.raises(ConfigError, match="none of its parameters may differ per load case"):
        get_effect("creep_test:split")
    with pytest.raises(ConfigError, match="Unknown physical effect .no_such_effect."):
        get_effect("no_such_effect:split")


def test_a_user_effect_splits_by_declaring_it(clean_registry):
    @register_effect
    class Laxity(Effect):
        name = "laxity_test"
        kind = "series"
        load_cases = ("Flexion", "LateralBending")
        parameters = (EffectParameter("lax_deg", "deg", 0.0, 1.0, per_load_case=True),)

        def rotation(self, moment_nm, p):
            return p["lax_deg"].reshape(-1, 1, 1) * torch.tanh(moment_nm)

    split = get_effect("laxity_test:split")
    assert [q.name for q in split.parameters] == ["lax_deg[Flexion]", "lax_deg[LateralBending]"]
    u = torch.tensor([[0.2, 0.8]])
    out = split().rotation_at(torch.ones(1, 4, 2), split.from_unit(u))
    flex, lb = LOAD_CASES.index("Flexion"), LOAD_CASES.index("LateralBending")
    assert out[0, lb, 0] == pytest.approx(4 * out[0, flex, 0].item(), rel=1e-6)


def test_names_femcal_uses_as_separators_are_refused(clean_registry):
    class Bad(Effect):
        name = "facet:two"
        kind = "series"
        load_cases = ("Flexion",)
        parameters = (EffectParameter("a", "deg", 0.0, 1.0),)

    with pytest.raises(ConfigError, match="name it with letters, digits and underscores"):
        register_effect(Bad)


def test_a_split_starts_from_the_tied_grid_copied_into_each_case():
    tied, split = get_effect("ligament_tension"), get_effect("ligament_tension:split")
    a = single_effect_starts(tied(), (0.2, 0.8))
    b = single_effect_starts(split(), (0.2, 0.8))
    assert b.shape == (len(a), len(split.parameters))
    torch.testing.assert_close(b, split.expand_tied(a))


def test_split_composite_jacobian_matches_finite_differences(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["facet_contact:split", "ligament_tension:split", "neutral_zone"])
    model.net = copy.deepcopy(model.net).double()
    model.moments = model.moments.double()
    v = torch.rand(2, model.dim, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    _, jac = model.curves_jacobian(v)
    eps = 1e-6
    for i in range(model.dim):
        dv = torch.zeros_like(v)
        dv[:, i] = eps
        fd = (model.curves(v + dv) - model.curves(v - dv)) / (2 * eps)
        torch.testing.assert_close(jac[..., i], fd, rtol=1e-5, atol=1e-7)


def test_calibration_recovers_facets_that_differ_per_load_case(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["facet_contact:split"])
    rng = np.random.default_rng(3)
    # gap 0.5 deg and stiff in extension, 2.5 deg and soft in axial rotation
    effect = np.array([0.5, 2.5, 1.0, 0.2, 1.0, 0.05])
    x = np.concatenate([study_space().sample_uniform(3, rng), np.tile(effect, (3, 1))], axis=1)
    targets = model.predict(x)
    res = calibrate(
        model, targets, method="pgd", options={"n_bank_uniform": 512, "fit_tolerance": 0.0}
    )
    assert np.all(res.exceedance == 0) and res.mae_deg.max() < 0.02
    tied = calibrate(
        EffectModel(base, ["facet_contact"]),
        targets,
        method="pgd",
        options={"n_bank_uniform": 512, "fit_tolerance": 0.0},
    )
    assert np.median(tied.mae_deg) > 2 * np.median(res.mae_deg)  # one law cannot fit both
