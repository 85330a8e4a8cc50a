"""The box's own answer for a disc the disc alone fits at its edge (femcal.diagnose.box_edge)."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from femcal.diagnose.box_edge import (
    AT_BOUND,
    EDGE_DRAWS,
    EDGE_MAX_DRAWS,
    EDGE_STOP,
    SOFTER,
    STIFFER,
    _draw,
    _exceeding,
    bounds_pressed,
    edge_probability,
    edge_reading,
    edge_words,
    fitted_unit,
    margins,
)
from femcal.diagnose.outside import NAMED, REPORTED
from femcal.reachability import build_envelope

LOWER = np.ones((4, 3))
UPPER = np.full((4, 3), 5.0)


def test_margin_is_the_nearest_edge_in_sigma_and_names_its_side():
    rom = np.stack([np.full((4, 3), 1.5), np.full((4, 3), 4.0)])
    rom[0, 2] = 3.0  # one load case deeper inside: the smallest load case counts
    rom[1, 1, 0] = np.nan  # a point not measured does not count
    margin, side = margins(rom, LOWER, UPPER, np.full((4, 3), 0.25))
    np.testing.assert_allclose(margin, [2.0, 4.0])  # (1.5 - 1) / 0.25 and (5 - 4) / 0.25
    assert side == [STIFFER, SOFTER]


def test_margin_is_negative_beyond_the_envelope():
    rom = np.full((1, 4, 3), 0.5)
    margin, side = margins(rom, LOWER, UPPER, np.full((1, 4, 3), 0.1))
    np.testing.assert_allclose(margin, [-5.0])
    assert side == [STIFFER]


def test_bounds_pressed_counts_coordinates_within_the_tolerance_of_a_bound():
    unit = np.array([[0.0, 1.0, 0.5, 0.9995, 0.002], [0.3, 0.4, 0.5, 0.6, 0.7]])
    assert bounds_pressed(unit).tolist() == [3, 0]


def test_edge_probability_is_prior_odds_times_the_likelihood_ratio_bound():
    odds = math.exp(-10.0 / 2)  # min_delta's prior odds
    assert edge_probability(odds, odds) == pytest.approx(0.5)  # p = 1 in 148
    assert edge_probability(1.0, odds) < 0.01  # every disc of the box looks so: no evidence
    # p resolves to 1 / (1 + EDGE_MAX_DRAWS): the largest probability the draws can give
    assert edge_probability(1 / (1 + EDGE_MAX_DRAWS), odds) == pytest.approx(
        odds / (odds + 1 / (1 + EDGE_MAX_DRAWS))
    )
    assert EDGE_MAX_DRAWS % EDGE_DRAWS == 0


def test_edge_words_say_the_count_the_margin_and_how_often_the_box_does_it():
    text = edge_words(
        {
            "bounds_pressed": 7,
            "margin_sigma": 0.91,
            "side": STIFFER,
            "exceeding": 1,
            "draws": 512,
            "likelihood_ratio": 256.5,
        }
    )
    assert "presses 7 bounds" in text and "stiffer edge" in text and "1 of 512" in text


@pytest.fixture(scope="module")
def edge_world():
    """A small surrogate of the synthetic study, a disc at the centre of its box and the
    stiffest training disc made 15 % stiffer (just beyond the box), each with noise, and their
    disc-alone fits."""
    from femcal.calibration import SurrogateCurveModel
    from femcal.diagnose import DiagnoseOptions
    from femcal.diagnose.search import disc_fit
    from femcal.surrogates.nn import NeuralSurrogate

    from synth import study_space, tidy_table, true_curves

    moments = np.arange(1.0, 5.01, 0.5)
    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    base = SurrogateCurveModel(surrogate, moments)
    space = study_space()
    x = table.groupby("config_id")[list(space.names)].first().to_numpy()
    fe = true_curves(x, moments=moments)
    stiffest = fe[np.argmin(fe.reshape(len(fe), -1).mean(axis=1))]
    centre = base.predict(space.from_unit(np.full((1, space.dim), 0.5)))[0]
    noise = 0.02
    rng = np.random.default_rng(5)
    rom = np.stack([centre, 0.85 * stiffest]) + rng.normal(0, noise, (2, 4, len(moments)))
    sigma = np.full(rom.shape, noise)
    state = types.SimpleNamespace(
        base=base,
        specimens=["centre", "beyond"],
        measured=rom,
        mask=np.isfinite(rom),
        sigma=sigma,
        weight=np.ones(rom.shape),
        start_bank=None,
        options=DiagnoseOptions(),
        rng=np.random.default_rng(0),
    )
    v, _ = disc_fit(state, state.weight)
    unit = base.space.to_unit(base.to_physical(v.double().numpy()))
    env = build_envelope(base, sigma_model=np.zeros(len(moments)))
    return state, env, unit


def test_the_box_answers_how_often_its_discs_look_as_much_at_its_edge(edge_world):
    state, env, unit = edge_world
    centre, beyond = (edge_reading(state, i, env, unit[i]) for i in range(2))
    # The centre disc: its fit presses few bounds, deep inside the envelope; many box discs
    # look as much at the edge (14 of 32 when written), so the test stops at the first draws.
    assert centre["draws"] == EDGE_DRAWS and centre["exceeding"] >= EDGE_STOP
    assert centre["probability"] < REPORTED
    # 15 % stiffer than the stiffest training disc: 11 bounds, beyond the envelope; no box disc
    # of 512 looks so (0 when written), so only the prior and the draws' resolution cap it.
    assert centre["side"] == beyond["side"] == STIFFER
    assert beyond["margin_sigma"] < 0 < centre["margin_sigma"]
    assert beyond["bounds_pressed"] > centre["bounds_pressed"]
    assert beyond["draws"] == EDGE_MAX_DRAWS and beyond["exceeding"] <= 2
    p = (1 + beyond["exceeding"]) / (1 + beyond["draws"])
    assert beyond["p_inside"] == pytest.approx(p, rel=1e-3)
    assert beyond["probability"] == pytest.approx(edge_probability(p, math.exp(-5.0)), rel=1e-6)
    assert beyond["probability"] > NAMED


# How far a float32 disc-alone fit of a draw moves when other rows are fitted beside it (unit
# coordinates): the batch's rounding steers the fit along the directions the curves do not
# fix (8.7e-4 at most over the draws below when written, on an AVX-512 CPU at one thread).
FIT_ROUNDING = 2e-3


@pytest.mark.parametrize("quantile", [None, 0.0, 0.3, 1.0])
def test_fitting_only_the_draws_that_can_exceed_counts_as_fitting_them_all(edge_world, quantile):
    """The exceedances of two successive rounds (the generator carried on) from the fits of
    the draws whose margin is at most the specimen's equal those from fitting every draw:
    a draw's margin needs no fit, and the fit draws the same numbers for any rows (None: a
    margin below every draw's, so that no draw is fitted but the generator moves on). The
    count is read at the draws' own median of bounds pressed, so that it counts some fits
    and not others. A draw whose fit has a coordinate within FIT_ROUNDING of AT_BOUND's
    threshold may count either way (the fits agree to float32 rounding, not bit for bit)."""
    state, env, _ = edge_world
    counted = []
    for i in range(2):
        probe = _draw(state, i, np.random.default_rng(7), EDGE_DRAWS)
        mr0, _ = margins(probe, env.lower, env.upper, state.sigma[i])
        margin = float(mr0.min() - 1.0 if quantile is None else np.quantile(mr0, quantile))
        full, some = np.random.default_rng(7), np.random.default_rng(7)
        for _round in range(2):
            sim = _draw(state, i, full, EDGE_DRAWS)
            mr, _ = margins(sim, env.lower, env.upper, state.sigma[i])
            unit = fitted_unit(state, i, sim, full)
            kr = bounds_pressed(unit)
            k = int(np.median(kr))
            near = mr <= margin
            expected = int(np.sum((kr >= k) & near))
            edge = np.minimum(np.abs(unit - AT_BOUND), np.abs(unit - (1 - AT_BOUND)))
            either_way = int(np.sum(near & (edge < FIT_ROUNDING).any(axis=1)))
            got = _exceeding(state, i, env, some, EDGE_DRAWS, k, margin)
            assert abs(got - expected) <= either_way
            counted.append(0 < expected < np.sum(near))
        assert full.random() == some.random()  # both generators at the same place
    assert any(counted) or quantile in (None, 0.0)
