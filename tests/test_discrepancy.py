"""The GP discrepancy: joint fit, posterior against a direct computation, words, runs test."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from femcal.calibration import CurveModel, SurrogateCurveModel
from femcal.diagnose.discrepancy import (
    _covariance,
    _kernel,
    describe,
    discrepancy_posterior,
    fit_discrepancy,
    runs_p_value,
    similarity,
)
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = np.arange(1.0, 5.01, 0.5)
NOISE = 0.02


@pytest.fixture(scope="module")
def base() -> CurveModel:
    table = tidy_table(40, seed=5)
    model = NeuralSurrogate(study_space(), hidden=(24, 24), max_epochs=30, batch_size=16, seed=0)
    return SurrogateCurveModel(model.fit(table, table["rom_deg"].to_numpy()), MOMENTS)


def _softened(base: CurveModel, n: int, seed: int):
    """Surrogate curves + a softening in flexion (0.4 deg at 5 Nm, cubic) + noise."""
    rng = np.random.default_rng(seed)
    x = base.space.sample_uniform(n, rng)
    clean = base.predict(x)
    extra = np.zeros_like(clean)
    extra[:, 0] = 0.4 * (MOMENTS / 5.0) ** 3
    return x, clean + extra + rng.normal(0, NOISE, clean.shape), extra


def test_posterior_matches_a_direct_gp_computation(base):
    x, meas, _ = _softened(base, 3, seed=0)
    meas[1, 2, 4:] = np.nan  # a specimen with missing points
    v0 = base.from_physical(x)
    fit = fit_discrepancy(base, v0, meas, np.full(len(MOMENTS), NOISE), max_iter=0)
    mask = np.isfinite(meas)
    mean, _ = discrepancy_posterior(fit, MOMENTS, MOMENTS, mask)
    # Direct kriging of the residual at the same v: k*^T (K + s^2 I)^-1 r, measured points only.
    lx = np.log(MOMENTS)
    for i in range(3):
        ok = mask[i].reshape(-1)
        r = (meas[i] - fit.pred[i].double().numpy()).reshape(-1)[ok]
        k = _kernel(lx, lx, fit.amplitude_deg[i : i + 1], 0.5)[0]
        c = k[np.ix_(ok, ok)] + NOISE**2 * np.eye(ok.sum())
        direct = k[:, ok] @ np.linalg.solve(c, r)
        np.testing.assert_allclose(mean[i].reshape(-1), direct, atol=1e-8)
    cov = _covariance(mask, np.full(len(MOMENTS), NOISE), lx, fit.amplitude_deg, 0.5)
    gone = ~mask[1].reshape(-1)
    np.testing.assert_allclose(cov[1][np.ix_(gone, gone)], np.eye(5))  # decoupled, unit


def test_the_joint_fit_finds_the_missing_softening_inside_its_band(base):
    x, meas, extra = _softened(base, 6, seed=1)
    v0 = base.from_physical(x)
    sigma = np.full(len(MOMENTS), NOISE)
    fit = fit_discrepancy(base, v0, meas, sigma)
    mean, sd = discrepancy_posterior(fit, MOMENTS, MOMENTS, np.isfinite(meas))
    # The disc parameters are fitted jointly, so the disc may take up part of the softening;
    # the truth must lie inside the band where the band is narrow, and flexion must show it.
    inside = np.abs(mean - extra) <= 3 * sd + 1e-9
    assert inside.mean() >= 0.9
    assert np.all(mean[:, 0, -1] > 0.1)  # flexion at 5 Nm: more rotation than the model
    assert np.all(fit.mae_deg < 2 * NOISE)
    assert np.all(sd >= 0)


def test_describe_says_where_what_and_how_large():
    q = np.linspace(1, 7.5, 14)
    mean = np.zeros((4, q.size))
    sd = np.full((4, q.size), 0.02)
    mean[3] = -0.3 * np.clip(q - 3.0, 0, None) / 4.5  # stiffening in axial rotation from 3 Nm
    mean[0] = 0.25  # an offset in flexion
    text = describe(q, mean, sd, 0.05)
    assert len(text) == 2
    assert text[0].startswith("Flexion: more rotation than the model")
    assert "offset" in text[0]
    # Detectable (beyond 2 sd and beyond sigma) from 4 Nm: 0.3 * 1 / 4.5 = 0.067 > 0.05 deg.
    assert text[1].startswith(
        "AxialRotation: less rotation than the model (stiffening) from 4 to 7.5 Nm"
    )
    assert "growing with the moment" in text[1] and "up to 0.30 deg (6 sigma)" in text[1]
    assert describe(q, np.zeros((4, q.size)), sd, 0.05) == []


def test_runs_test_flags_one_sign_runs_only():
    alternating = np.tile([1.0, -1.0], (4, 5))
    assert runs_p_value(alternating) > 0.99
    blocks = np.concatenate([np.ones((4, 5)), -np.ones((4, 5))], 1)
    assert runs_p_value(blocks) < 1e-3
    assert runs_p_value(np.full((4, 1), np.nan)) == 1.0


def test_similarity_is_a_cosine_in_sigma_units():
    delta = np.zeros((4, 3))
    delta[1] = [0.1, 0.2, 0.3]
    sig = {"a": 2 * delta, "b": -delta, "c": np.zeros((4, 3))}
    out = similarity(delta, sig, np.full(3, 0.05))
    assert out == pytest.approx({"a": 1.0, "b": -1.0, "c": 0.0})


def test_fit_is_deterministic(base):
    x, meas, _ = _softened(base, 2, seed=3)
    v0 = base.from_physical(x)
    a = fit_discrepancy(base, v0, meas, np.full(len(MOMENTS), NOISE))
    b = fit_discrepancy(base, v0, meas, np.full(len(MOMENTS), NOISE))
    torch.testing.assert_close(a.v, b.v)
    np.testing.assert_array_equal(a.delta_at_points, b.delta_at_points)


def test_ml_amplitude_is_zero_for_noise_and_grows_with_a_smooth_misfit():
    from femcal.diagnose.discrepancy import ml_amplitude

    rng = np.random.default_rng(3)
    n, m = 200, len(MOMENTS)
    sigma = np.full((n, 4, m), NOISE)
    mask = np.ones((n, 4, m), dtype=bool)
    x = np.log(MOMENTS)
    noise = rng.normal(0.0, NOISE, (n, 4, m))
    amp = ml_amplitude(noise, mask, sigma, x)
    # Pure noise: no discrepancy in most load cases (a chance one at most one grid step up).
    assert np.mean(amp == 0.0) > 0.6
    assert np.all(amp <= 2 * NOISE + 1e-12)
    bump = noise.copy()
    bump[:, 0] += 0.5 * (MOMENTS / 5.0) ** 3  # a softening of 0.5 deg at 5 Nm in flexion
    amp = ml_amplitude(bump, mask, sigma, x)
    assert np.median(amp[:, 0]) >= 8 * NOISE  # sized to the misfit
    assert np.mean(amp[:, 1:] == 0.0) > 0.6  # the other load cases are untouched


def test_ml_fit_compares_models_by_their_marginal_likelihood(base):
    x, meas, _ = _softened(base, 4, seed=2)
    v0 = base.from_physical(x)
    sigma = np.full(len(MOMENTS), NOISE)
    ml = fit_discrepancy(base, v0, meas, sigma, amplitude_deg="ml")
    assert ml.log_det is not None and ml.neg2_log_ml.shape == (4,)
    assert np.all(ml.amplitude_deg[:, 0] > NOISE)  # the softened load case gets a GP
    # Forcing a GP nobody needs everywhere costs marginal likelihood (log det C).
    big = fit_discrepancy(base, ml.v, meas, sigma, amplitude_deg=np.full((4, 4), 1.0))
    assert np.all(big.neg2_log_ml > ml.neg2_log_ml)
    with pytest.raises(ValueError, match="'ml'"):
        fit_discrepancy(base, v0, meas, sigma, amplitude_deg="max")


def test_ml_amplitude_respects_a_cap_per_load_case():
    from femcal.diagnose.discrepancy import ml_amplitude

    rng = np.random.default_rng(4)
    n, m = 50, len(MOMENTS)
    sigma = np.full((n, 4, m), NOISE)
    mask = np.ones((n, 4, m), dtype=bool)
    x = np.log(MOMENTS)
    bump = rng.normal(0.0, NOISE, (n, 4, m))
    bump[:, :2] += 0.5 * (MOMENTS / 5.0) ** 3  # a misfit in flexion and extension
    free = ml_amplitude(bump, mask, sigma, x)
    cap = np.full((n, 4), np.inf)
    cap[:, 0] = 2 * NOISE  # capped in flexion only
    capped = ml_amplitude(bump, mask, sigma, x, cap=cap)
    assert np.all(capped[:, 0] <= 2 * NOISE + 1e-12) and np.all(free[:, 0] > 2 * NOISE)
    np.testing.assert_array_equal(capped[:, 1:], free[:, 1:])  # the rest stays free
    np.testing.assert_array_equal(ml_amplitude(bump, mask, sigma, x, cap=np.inf), free)
    # A cap of 0 still allows no discrepancy at all.
    assert np.all(ml_amplitude(bump, mask, sigma, x, cap=0.0) == 0.0)


def test_ml_fit_keeps_the_amplitude_under_its_cap(base):
    x, meas, _ = _softened(base, 4, seed=2)
    v0 = base.from_physical(x)
    sigma = np.full(len(MOMENTS), NOISE)
    cap = np.full((4, 4), np.inf)
    cap[:, 0] = NOISE
    fit = fit_discrepancy(base, v0, meas, sigma, amplitude_deg="ml", amplitude_cap=cap)
    assert np.all(fit.amplitude_deg[:, 0] <= NOISE + 1e-12)
    free = fit_discrepancy(base, v0, meas, sigma, amplitude_deg="ml")
    # Held below what it needs, the discrepancy explains less: a worse marginal likelihood.
    assert np.all(fit.neg2_log_ml >= free.neg2_log_ml - 1e-6)
