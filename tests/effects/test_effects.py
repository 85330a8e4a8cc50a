"""Physical effects: registry, composition with the disc (gradients), planted cohorts."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.effects import Effect, EffectParameter, available_effects, get_effect, register_effect
from femcal.effects.composite import EffectModel
from femcal.effects.planted import fe_rotation, make_cohort, plant
from femcal.errors import ConfigError
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = [1.0, 2.0, 3.0, 4.0, 5.0]
#: The built-in effects (a test below registers a user effect too).
BUILTIN = ["facet_contact", "ligament_tension", "neutral_zone"]


@pytest.fixture(scope="module")
def surrogate() -> NeuralSurrogate:
    table = tidy_table(40, seed=5)
    model = NeuralSurrogate(study_space(), hidden=(24, 24), max_epochs=30, batch_size=16, seed=0)
    return model.fit(table, table["rom_deg"].to_numpy())


def test_registry_has_the_three_effects_and_names_unknown_ones():
    assert {"facet_contact", "ligament_tension", "neutral_zone"} <= set(available_effects())
    with pytest.raises(ConfigError, match="Unknown physical effect 'x'; choose one of facet"):
        get_effect("x")


def test_a_user_effect_is_one_class(clean_registry):
    @register_effect
    class Twist(Effect):
        name = "test_twist"
        kind = "series"
        load_cases = ("AxialRotation",)
        parameters = (EffectParameter("twist_deg", "deg", 0.0, 1.0),)

        def rotation(self, moment_nm, p):
            return p["twist_deg"].reshape(-1, 1, 1) * torch.tanh(moment_nm)

    assert get_effect("test_twist") is Twist
    with pytest.raises(ConfigError, match="load_cases must be a non-empty subset"):

        @register_effect
        class Bad(Effect):
            name = "bad"
            kind = "series"
            load_cases = ("Twisting",)


def test_disc_alone_equals_the_surrogate(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    v = torch.rand(4, 13, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(EffectModel(base, []).curves(v), base.curves(v))


def test_effects_act_where_they_should(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    v = torch.rand(3, 13, generator=torch.Generator().manual_seed(1))
    disc = base.curves(v)
    for name, lcs in (("facet_contact", [1, 3]), ("ligament_tension", [0, 2])):
        model = EffectModel(base, [name])
        k = len(get_effect(name).parameters)
        out = model.curves(torch.cat([v, torch.full((3, k), 0.3)], 1))
        others = [j for j in range(4) if j not in lcs]
        torch.testing.assert_close(out[:, others], disc[:, others])
        assert torch.all(out[:, lcs] <= disc[:, lcs] + 1e-6)  # a parallel element stiffens
    k = len(get_effect("neutral_zone").parameters)
    nz = EffectModel(base, ["neutral_zone"]).curves(torch.cat([v, torch.full((3, k), 0.5)], 1))
    assert torch.all(nz > disc)


@pytest.mark.parametrize("name", ["facet_contact", "ligament_tension"])
def test_parallel_effects_carry_no_moment_in_the_neutral_position(name):
    # Over the whole box (a soft facet onset over a small gap included), the element is
    # unloaded at zero rotation and its moment grows with the rotation.
    effect = get_effect(name)()
    u = torch.rand(4096, len(effect.parameters), generator=torch.Generator().manual_seed(3))
    p = effect.from_unit(u)
    rotation = torch.linspace(0.0, 10.0, 41).expand(4096, 1, 41)
    moment = effect.moment(rotation, p)
    # 0 up to the law's floor on the closure (1e-12 deg, times k <= 5 Nm/deg^n)
    assert moment[..., 0].abs().max() < 1e-10
    assert torch.all(torch.diff(moment, dim=-1) >= 0)


def test_facet_contact_is_never_stiffer_than_a_sharp_contact_without_gap():
    # The closure counts from the neutral position, its slope is at most 1: contact carries at
    # most k phi^n, the sharp law with no gap. A soft onset over no gap used to give a tangent
    # stiffness of k n (w ln 2)^(n - 1) at zero rotation (14 Nm/deg at the box's corner), so
    # that curves in radians (0.1 deg at 5 Nm) fell within the effects' envelope.
    effect = get_effect("facet_contact")()
    u = torch.rand(4096, 4, generator=torch.Generator().manual_seed(5))
    u[:8] = torch.tensor([0.0, 1.0, 1.0, 1.0])  # no gap, stiffest, n = 3, softest onset
    p = effect.from_unit(u)
    rotation = torch.linspace(0.0, 10.0, 41).expand(4096, 1, 41)
    moment = effect.moment(rotation, p)
    k = p["facet_stiffness"].reshape(-1, 1, 1)
    n = p["facet_exponent"].reshape(-1, 1, 1)
    assert torch.all(moment <= k * rotation**n * (1 + 1e-5) + 1e-10)
    # At 0.25 deg, the box's corner: 0.011 Nm; 4.1 Nm with the power's value at zero
    # subtracted instead, 17 Nm (13 of them preload) before either.
    assert moment[:8, 0, 1].max() < 0.05


def test_a_soft_facet_onset_over_no_gap_gives_finite_curves(surrogate):
    # No gap, the stiffest contact and the softest onset: the rounded corner used to preload
    # the facets by more than the applied moment, and the disc's share had no solution.
    model = EffectModel(SurrogateCurveModel(surrogate, MOMENTS), ["facet_contact"])
    v = torch.cat([torch.full((1, 13), 0.5), torch.tensor([[0.0, 1.0, 0.5, 1.0]])], 1)
    curves, jac = model.curves_jacobian(v)
    assert torch.isfinite(curves).all() and torch.isfinite(jac).all()
    torch.testing.assert_close(model.curves(v), curves)


def test_composite_jacobian_matches_finite_differences(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["facet_contact", "ligament_tension", "neutral_zone"])
    model.net = copy.deepcopy(model.net).double()
    model.moments = model.moments.double()
    v = torch.rand(3, model.dim, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    v[1, : model.n_disc] = v[0, : model.n_disc]  # one disc, two effect starts (computed once)
    _, jac = model.curves_jacobian(v)
    eps = 1e-6
    for i in range(model.dim):
        dv = torch.zeros_like(v)
        dv[:, i] = eps
        fd = (model.curves(v + dv) - model.curves(v - dv)) / (2 * eps)
        torch.testing.assert_close(jac[..., i], fd, rtol=1e-5, atol=1e-7)


def test_rows_sharing_their_disc_get_the_jacobian_each_gets_alone(surrogate):
    # The starts of one grid share the disc's parameters: its network tangents are computed
    # once per distinct disc and handed to every row (float32: a batch of another size may
    # round the last bit otherwise).
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, BUILTIN)
    v = torch.rand(5, model.dim, generator=torch.Generator().manual_seed(8))
    v[[1, 3], : model.n_disc] = v[0, : model.n_disc]
    got_f, got_j = model.curves_jacobian(v)
    for i in range(len(v)):
        want_f, want_j = EffectModel(base, BUILTIN).curves_jacobian(v[i : i + 1])
        torch.testing.assert_close(got_f[i], want_f[0], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(got_j[i], want_j[0], rtol=1e-5, atol=1e-5)


def test_the_jacobian_reuses_the_shares_of_the_last_curves_call_exactly(surrogate):
    # Gauss-Newton evaluates the curves at a new point, then the Jacobian there: the disc's
    # share of the moment solved for the curves is reused, row by row: the same values up to
    # float32 rounding (a batch of another size may round a product's last bit otherwise).
    base = SurrogateCurveModel(surrogate, MOMENTS)
    v = torch.rand(6, EffectModel(base, BUILTIN).dim, generator=torch.Generator().manual_seed(4))
    fresh = EffectModel(base, BUILTIN)
    want_f, want_j = fresh.curves_jacobian(v[2:])
    warm = EffectModel(base, BUILTIN)
    with torch.no_grad():
        warm.curves(v[:4])  # rows 2, 3 solved here; rows 4, 5 not
    got_f, got_j = warm.curves_jacobian(v[2:])
    torch.testing.assert_close(got_f, want_f, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(got_j, want_j, rtol=1e-5, atol=1e-5)
    assert warm.n_evaluations - 4 == fresh.n_evaluations  # the cache changes no count


def test_the_share_cache_tells_apart_float64_rows_that_float32_would_merge(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["facet_contact"])
    model.net = copy.deepcopy(model.net).double()
    model.moments = model.moments.double()
    v = torch.rand(2, model.dim, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    near = v + 1e-12  # the same float32 numbers, other float64 ones
    assert torch.equal(near.float(), v.float())
    model.curves(v)
    keys = {r.tobytes() for r in near.numpy()}
    assert not keys & set(model._shares)  # v's rows only
    assert model._share_of(near) is not None  # solved afresh, kept under near's own bytes
    assert keys | {r.tobytes() for r in v.numpy()} <= set(model._shares)


def test_the_jacobian_is_finite_far_from_contact(surrogate):
    # A gap far beyond the rotations (unit 1 = 6 deg) puts the facet ramp in softplus
    # underflow; the derivative in the exponent must still be finite (0, not 0 * log 0).
    base = SurrogateCurveModel(surrogate, [0.02, 0.05])  # rotations well below a degree
    model = EffectModel(base, BUILTIN)
    v = torch.rand(4, model.dim, generator=torch.Generator().manual_seed(5))
    v[:, base.dim] = 1.0  # facet gap at its upper bound
    v[:, base.dim + 4] = 1.0  # ligament slack at its upper bound
    _, jac = model.curves_jacobian(v)
    assert torch.isfinite(jac).all()


def test_joint_calibration_recovers_a_planted_effect_inside_the_bounds(surrogate):
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["facet_contact"])
    rng = np.random.default_rng(3)
    x = np.concatenate([study_space().sample_uniform(4, rng), [[1.0, 1.0]] * 4], axis=1)
    targets = model.predict(x)
    res = calibrate(
        model, targets, method="pgd", options={"n_bank_uniform": 512, "fit_tolerance": 0.0}
    )
    assert np.all(res.exceedance == 0) and res.mae_deg.max() < 0.02
    assert res.parameter_names[-4:] == (
        "facet_gap_deg",
        "facet_stiffness",
        "facet_exponent",
        "facet_onset_deg",
    )


def test_a_second_round_of_starts_finds_two_effects_at_once(surrogate):
    # Facet contact and ligament tension both on (the model's own curves, no noise): the first
    # round starts one effect at a time; the second adds each effect to the best found.
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["facet_contact", "ligament_tension", "neutral_zone"])
    rng = np.random.default_rng(8)
    n = 6
    facet = np.column_stack(
        [rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 2.0, n), [1.5] * n, [0.2] * n]
    )
    ligament = np.column_stack([rng.uniform(0.5, 2.0, n), rng.uniform(0.1, 0.5, n), [1.5] * n])
    nz = np.array([[0.0, 0.5, 1.0]] * n)  # off
    x = np.concatenate([study_space().sample_uniform(n, rng), facet, ligament, nz], axis=1)
    targets = model.predict(x)
    # (a stiff contact with a small gap can leave the moment balance unsolved: NaN curves,
    # a known limitation of EffectModel; such draws are left out)
    targets = targets[np.isfinite(targets).all(axis=(1, 2))]
    assert len(targets) >= 4
    opts = {"n_bank_uniform": 512, "fit_tolerance": 0.0, "effect_bank_starts": 0}
    one = calibrate(model, targets, method="pgd", options={**opts, "effect_rounds": 1})
    two = calibrate(model, targets, method="pgd", options=opts)
    assert np.all(two.exceedance == 0)
    # The second round starts from the first's best: never worse (float32 rounding), and
    # better on average (measured: 0.21-0.38 -> 0.0004-0.009 deg).
    assert np.all(two.mae_deg <= one.mae_deg + 1e-5)
    assert two.mae_deg.mean() < 0.5 * one.mae_deg.mean(), (one.mae_deg, two.mae_deg)


def test_fe_rotation_interpolates_and_extends_as_a_power_law():
    m = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    rom = 2.0 * m**0.5
    np.testing.assert_allclose(fe_rotation(m, rom, m), rom)
    np.testing.assert_allclose(
        fe_rotation(m, rom, np.array([0.5, 2.5, 6.0])),
        2.0 * np.array([0.5, 2.5, 6.0]) ** 0.5,
        rtol=1e-12,
    )


def test_planted_parallel_effect_balances_the_moment():
    m = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    fe = np.tile(3.0 * m**0.6, (4, 1))
    p = {
        "facet_gap_deg": 2.0,
        "facet_stiffness": 1.0,
        "facet_exponent": 2.0,
        "facet_onset_deg": 0.05,
    }
    q = np.array([1.0, 3.0, 5.0])
    phi = plant("facet_contact", p, m, fe, q)
    eff = get_effect("facet_contact")()
    carried = eff.moment(torch.tensor(phi[None]), {k: torch.tensor([v]) for k, v in p.items()})
    disc_moment = (phi / 3.0) ** (1 / 0.6)  # inverse of the FE curve
    total = disc_moment + carried[0].numpy()
    np.testing.assert_allclose(total[[1, 3]], np.tile(q, (2, 1)), rtol=1e-6)
    np.testing.assert_allclose(phi[[0, 2]], 3.0 * np.tile(q, (2, 1)) ** 0.6)  # untouched cases


def test_make_cohort_is_seeded_and_balanced():
    m = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    fe = np.stack([np.tile((2 + i % 3) * m**0.6, (4, 1)) for i in range(20)])
    a = make_cohort(m, fe, n_per_class=4, noise_deg=0.05, rng=np.random.default_rng(0))
    b = make_cohort(m, fe, n_per_class=4, noise_deg=0.05, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(a.rom_deg, b.rom_deg)
    assert a.truth["effect"].value_counts().to_dict() == {
        "none": 4,
        "facet_contact": 4,
        "ligament_tension": 4,
        "neutral_zone": 4,
    }
    noise = a.rom_deg - a.clean_deg
    assert 0.03 < noise.std() < 0.07
    with pytest.raises(ConfigError, match="needs 24 FE configurations; got 20"):
        make_cohort(m, fe, n_per_class=6, rng=np.random.default_rng(0))


def test_effect_starts_hold_the_weak_end_and_one_grid_per_effect(surrogate):
    from femcal.calibration.starts import effect_starts

    model = EffectModel(SurrogateCurveModel(surrogate, MOMENTS), ["facet_contact", "neutral_zone"])
    starts = effect_starts(model, (0.2, 0.8))
    weak = torch.tensor([q.start for e in model.effects for q in e.parameters])
    # facet 4 parameters, neutral zone 3; shape parameters (after the first two) not gridded.
    assert starts.shape == (1 + 4 + 4, 7)
    torch.testing.assert_close(starts[0], weak)
    # The facet grid leaves the neutral zone at its weak end, and the other way round.
    torch.testing.assert_close(starts[1:5, 4:], weak[4:].expand(4, -1))
    torch.testing.assert_close(starts[5:, :4], weak[:4].expand(4, -1))
    grid = torch.tensor([[a, b] for a in (0.2, 0.8) for b in (0.2, 0.8)])
    torch.testing.assert_close(starts[1:5, :2], grid)
    torch.testing.assert_close(starts[1:5, 2:4], weak[2:4].expand(4, -1))


def test_shape_starts_cover_every_parameter_of_each_effect_seeded(surrogate):
    from femcal.calibration.starts import effect_starts, shape_design

    model = EffectModel(SurrogateCurveModel(surrogate, MOMENTS), ["facet_contact", "neutral_zone"])
    starts = effect_starts(model, (0.2, 0.8), shape_starts=8)
    weak = torch.tensor([q.start for e in model.effects for q in e.parameters])
    # weak end; facet grid (4) + its design (8); neutral-zone grid (4) + its design (8)
    assert starts.shape == (1 + 4 + 8 + 4 + 8, 7)
    facet = starts[5:13]
    torch.testing.assert_close(facet[:, :4], torch.tensor(shape_design(4, 8), dtype=torch.float32))
    torch.testing.assert_close(facet[:, 4:], weak[4:].expand(8, -1))  # the other effect weak
    # The design spreads the shape parameters over their box (not the classic member only).
    assert float(facet[:, 2].min()) < 0.25 and float(facet[:, 2].max()) > 0.75
    np.testing.assert_array_equal(shape_design(4, 8), shape_design(4, 8))  # fixed seed
    assert shape_design(3, 0).shape == (0, 3)


def test_the_weak_end_of_every_effect_leaves_the_disc_curves_unchanged(surrogate):
    # Effects the data do not need must be able to switch off, even at large rotations.
    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, BUILTIN)
    v_disc = torch.rand((16, base.dim), generator=torch.Generator().manual_seed(0))
    weak = torch.tensor([q.start for e in model.effects for q in e.parameters])
    with torch.no_grad():
        disc = base.curves(v_disc)
        both = model.curves(torch.cat([v_disc, weak.expand(16, -1)], 1))
    # 0.025 deg: half the measurement noise of the planted cohorts (0.05 deg), at rotations up
    # to those of this synthetic surrogate (AR beyond 20 deg, where a weak facet still touches).
    assert float((both - disc).abs().max()) < 0.025


def test_adding_an_unneeded_effect_does_not_worsen_the_fit(surrogate):
    # Targets without any effect: the disc with all effects must fit them as well as the disc.
    base = SurrogateCurveModel(surrogate, MOMENTS)
    rng = np.random.default_rng(11)
    targets = base.predict(study_space().sample_uniform(6, rng))
    targets = targets + rng.normal(0, 0.05, targets.shape)
    opts = {"n_bank_uniform": 512}
    disc = calibrate(base, targets, method="pgd", options=opts, seed=0)
    full = calibrate(EffectModel(base, BUILTIN), targets, method="pgd", options=opts)
    assert np.all(full.exceedance == 0)
    # Staged starts begin at the disc-alone solution with every effect at its weak end, and that
    # start is kept whenever the steps from it do not lower the MAE: no specimen may end worse
    # than the disc alone with its effects weak. The weak end is not exactly off (a facet at
    # 1e-4 Nm/deg^n still touches at large rotations; measured here: up to 2.1e-4 deg of MAE),
    # so the tolerance is 5e-4 deg, 1 % of the 0.05 deg noise.
    assert np.all(full.mae_deg <= disc.mae_deg + 5e-4)


def test_effect_bank_is_seeded_inside_the_box_and_mixes_effects_on_and_off(surrogate):
    from femcal.calibration.starts import effect_bank

    base = SurrogateCurveModel(surrogate, np.arange(1.0, 5.01))
    model = EffectModel(base, ["facet_contact", "neutral_zone"])
    bank = surrogate.space.sample_uniform(32, np.random.default_rng(0))
    v1, p1 = effect_bank(model, bank, np.random.default_rng(7), 256)
    v2, p2 = effect_bank(model, bank, np.random.default_rng(7), 256)
    torch.testing.assert_close(v1, v2)  # same seed, same bank
    torch.testing.assert_close(p1, p2)
    assert v1.shape[1] == model.dim and p1.shape[1:] == (4, 5)
    assert float(v1.min()) >= 0.0 and float(v1.max()) <= 1.0
    assert torch.isfinite(p1).all()
    # nz_range_deg starts at 0 (off); about half the rows have the laxity on.
    on = (v1[:, model.n_disc + 4] > 0).float().mean()
    assert 0.3 < float(on) < 0.8
