"""The composite curves' Jacobian (femcal.effects.jacobian) against forward-mode AD and
finite differences, in float64 so that agreement to 1e-7 relative is a fair demand."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwad

from femcal.calibration import SurrogateCurveModel
from femcal.effects.composite import EffectModel
from femcal.effects.jacobian import disc_partials
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

#: Moments below the lowest trained one (1 Nm) take the power-law continuation.
MOMENTS = [0.2, 0.6, 1.0, 2.5, 5.0]


@pytest.fixture(scope="module")
def surrogate() -> NeuralSurrogate:
    table = tidy_table(40, seed=5)
    model = NeuralSurrogate(study_space(), hidden=(24, 24), max_epochs=30, batch_size=16, seed=0)
    return model.fit(table, table["rom_deg"].to_numpy())


def _model(surrogate, effects, *, log_target=True) -> EffectModel:
    model = EffectModel(SurrogateCurveModel(surrogate, MOMENTS), effects)
    model.net = copy.deepcopy(model.net).double()
    model.net.log_target = log_target
    model.moments = model.moments.double()
    return model


def _dual_jacobian(model: EffectModel, v: torch.Tensor) -> torch.Tensor:
    """The Jacobian (n, 4, m, dim) by one dual row per column through the whole curves."""
    n, d = v.shape
    share = model._disc_share(v).repeat_interleave(d, 0)
    with fwad.dual_level():
        tangent = torch.eye(d, dtype=v.dtype).repeat(n, 1)
        out = model.curves(fwad.make_dual(v.repeat_interleave(d, 0), tangent), share=share)
        jac = fwad.unpack_dual(out).tangent
    return jac.reshape(n, d, *jac.shape[1:]).permute(0, 2, 3, 1)


@pytest.mark.parametrize(
    "effects",
    [
        ["facet_contact", "ligament_tension", "neutral_zone"],
        ["facet_contact:split", "neutral_zone"],
        ["ligament_tension:split"],
        ["neutral_zone"],
        [],
    ],
)
def test_the_jacobian_equals_forward_mode_ad_through_the_curves(surrogate, effects):
    model = _model(surrogate, effects)
    v = torch.rand(4, model.dim, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    v[1, : model.n_disc] = v[0, : model.n_disc]
    value, jac = model.curves_jacobian(v)
    torch.testing.assert_close(value, model.curves(v), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(jac, _dual_jacobian(model, v), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("log_target", [True, False])
def test_disc_partials_match_finite_differences(surrogate, log_target):
    model = _model(surrogate, [], log_target=log_target)
    v = torch.rand(3, model.n_disc, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    coef = model._coefficients(v)  # (K, n, 4, p)
    rng = np.random.default_rng(0)
    dcoef = torch.tensor(rng.normal(size=(*coef.shape[:2], 2, *coef.shape[2:])))
    # off the lowest trained moment, where the slope may have a kink (a clipped power law)
    moment = model.moments.expand(3, 4, -1) * torch.tensor([1.05, 0.7, 1.3, 1.1])[None, :, None]
    log_low = float(np.log(model.m_low))
    phi, slope, along = disc_partials(model.net, coef, dcoef, moment, log_low)

    def curve(c: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        return model._disc(v, c)(m, slope=False)[0]

    torch.testing.assert_close(phi, curve(coef, moment), rtol=1e-12, atol=1e-12)
    eps = 1e-6
    fd = (curve(coef, moment * (1 + eps)) - curve(coef, moment * (1 - eps))) / (2 * eps * moment)
    torch.testing.assert_close(slope, fd, rtol=1e-6, atol=1e-9)
    for q in range(2):
        step = eps * dcoef[:, :, q]
        fd = (curve(coef + step, moment) - curve(coef - step, moment)) / (2 * eps)
        torch.testing.assert_close(along[:, q], fd, rtol=1e-6, atol=1e-9)


def test_the_jacobian_counts_one_evaluation_per_row_and_column(surrogate):
    model = _model(surrogate, ["facet_contact"])
    v = torch.rand(3, model.dim, dtype=torch.float64, generator=torch.Generator().manual_seed(9))
    model.curves_jacobian(v)
    assert model.n_evaluations == 3 * (1 + model.dim)


@pytest.fixture(scope="module")
def ensemble() -> NeuralSurrogate:
    table = tidy_table(40, seed=5)
    model = NeuralSurrogate(
        study_space(), hidden=(24, 24), max_epochs=5, batch_size=16, seed=0, n_members=2
    )
    return model.fit(table, table["rom_deg"].to_numpy())


def test_a_cheaper_jacobian_differentiates_the_disc_through_its_first_members(ensemble):
    # jacobian_members=1: the curves and the effects' columns stay exact (they do not pass
    # through the disc network's tangents); the disc's columns are those the disc alone gets
    # from its first member (SurrogateCurveModel's cheaper Jacobian), here without a parallel
    # effect, where the disc carries the whole moment (at the trained moments: below them the
    # composite continues the disc's curve as a power law).
    model = _model(ensemble, ["facet_contact", "neutral_zone"])
    assert len(model.net.members) == 2
    v = torch.rand(3, model.dim, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    value, exact = model.curves_jacobian(v)
    value_1, cheap = model.curves_jacobian(v, jacobian_members=1)
    torch.testing.assert_close(value_1, value, rtol=1e-12, atol=1e-12)
    nd = model.n_disc
    torch.testing.assert_close(cheap[..., nd:], exact[..., nd:], rtol=1e-10, atol=1e-12)
    assert not torch.allclose(cheap[..., :nd], exact[..., :nd])
    alone = _model(ensemble, ["neutral_zone"])
    base = SurrogateCurveModel(ensemble, MOMENTS)
    base.net, base.moments = alone.net, alone.moments
    v = v[:, : alone.dim]
    trained = [i for i, m in enumerate(MOMENTS) if m >= alone.m_low]
    torch.testing.assert_close(
        alone.curves_jacobian(v, jacobian_members=1)[1][:, :, trained, :nd],
        base.curves_jacobian(v[:, :nd], jacobian_members=1)[1][:, :, trained],
        rtol=1e-10,
        atol=1e-12,
    )


@pytest.mark.parametrize("section_points", [1, 64, 1 << 20])
def test_the_disc_share_is_the_same_however_many_levels_one_evaluation_bisects(
    surrogate, monkeypatch, section_points
):
    """One bisection level per evaluation (:func:`_bisect_levels`' torch path) and several
    (its grid path) visit the same midpoints: the shares are equal bit for bit; and the share
    solves ``M_d + sum M_e = M`` (float32 here, as in the diagnosis: 1e-5 of the moment)."""
    from femcal.effects import composite

    model = EffectModel(SurrogateCurveModel(surrogate, MOMENTS), ["facet_contact:split"])
    v = torch.rand(12, model.dim, generator=torch.Generator().manual_seed(3))
    monkeypatch.setattr(composite, "_SECTION_POINTS", 16384)
    reference = model._disc_share(v)
    monkeypatch.setattr(composite, "_SECTION_POINTS", section_points)
    assert torch.equal(model._disc_share(v), reference)
    phi = model._disc(v[:, : model.n_disc])(reference, slope=False)[0]
    params = model.effects[0].from_unit(v[:, model.n_disc :])
    carried = model.effects[0].moment_at(phi, params) * model._lc_masks[0][None, :, None]
    applied = model.moments.expand_as(reference)
    torch.testing.assert_close(reference + carried, applied, rtol=1e-5, atol=1e-5)
