"""pgd (projected Gauss-Newton) and pgd-study (the study's projected Adam) on a real surrogate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from femcal.calibration import (
    CalibrationProblem,
    SurrogateCurveModel,
    available_calibrators,
    calibrate,
)
from femcal.calibration.pgd_study import _BETA1, _BETA2, _EPS
from femcal.errors import ConfigError, InputDataError


def test_registry_lists_the_calibrators():
    assert {"pgd", "pgd-study", "ga", "inverse"} <= set(available_calibrators())


def test_unknown_method_lists_the_choices(curve_model, truth):
    with pytest.raises(
        ConfigError, match=r"Unknown calibration method 'nope'; choose one of .*pgd"
    ):
        calibrate(curve_model, truth[1], method="nope")


def test_pgd_fits_reachable_targets_inside_the_bounds(curve_model, truth):
    x_true, targets = truth
    bank = curve_model.space.sample_lhs(256, np.random.default_rng(0))
    res = calibrate(
        curve_model, targets, method="pgd", options={"start_bank": bank, "fit_tolerance": 0.0}
    )
    # Targets are the surrogate's own curves, so an exact fit exists; 1e-3 deg is far below
    # the 0.01-0.1 deg spread of the curves' values across the box.
    assert res.mae_deg.max() < 1e-3
    assert res.r2_mean.min() > 0.9999
    assert np.all(res.exceedance == 0)
    assert curve_model.space.contains(res.x).all()
    assert res.x.shape == x_true.shape
    # success = the optimiser's own convergence test (relative decrease, step or RMS < 1e-4 deg)
    assert res.success.sum() >= 3 and f"{res.success.sum()}/6 converged" in res.message

    assert res.parameters_frame().columns.tolist() == ["specimen", *curve_model.space.names]
    # The identifiability ranges hold the calibrated point; most hold the truth.
    assert np.all((res.x_low <= res.x) & (res.x <= res.x_high))
    inside = (res.x_low <= x_true) & (x_true <= res.x_high)
    assert inside.mean() > 0.8


def test_fit_tolerance_stops_at_the_noise_floor(curve_model, truth):
    noise = 0.02
    res = calibrate(curve_model, truth[1], method="pgd", options={"noise_deg": noise})
    rms = np.sqrt(np.nanmean((res.prediction - res.measured) ** 2, axis=(1, 2)))
    # Every specimen reached RMS < 0.25 x noise and stopped there (not far below it).
    assert res.success.all() and np.all(rms < 0.25 * noise)
    assert rms.max() > 0.25 * noise / 50


def test_pgd_never_leaves_the_box_for_unreachable_targets(curve_model, truth):
    # Twice the RoM of a reachable curve is far outside what the box can produce.
    res = calibrate(curve_model, 2.5 * truth[1], method="pgd", options={"n_bank_uniform": 64})
    assert np.all(res.exceedance == 0)
    assert curve_model.space.contains(res.x).all()
    at_bound = np.isclose(res.x, curve_model.space.lower) | np.isclose(
        res.x, curve_model.space.upper
    )
    assert at_bound.any()  # the optimum sits on the boundary and was stopped there


def test_same_seed_same_result_other_seed_differs(curve_model, truth):
    opts = {"n_starts": 0, "n_random_starts": 2, "n_bank_uniform": 0, "max_iter": 2}
    a = calibrate(curve_model, truth[1], method="pgd", seed=5, options=opts)
    b = calibrate(curve_model, truth[1], method="pgd", seed=5, options=opts)
    c = calibrate(curve_model, truth[1], method="pgd", seed=6, options=opts)
    np.testing.assert_array_equal(a.x, b.x)
    assert not np.array_equal(a.x, c.x)


@pytest.mark.parametrize("optimizer", ["adam", "lbfgsb"])
def test_other_optimizers_stay_inside(curve_model, truth, optimizer):
    res = calibrate(
        curve_model,
        truth[1],
        method="pgd",
        options={"optimizer": optimizer, "steps": 30, "max_iter": 30, "n_bank_uniform": 128},
    )
    assert np.all(res.exceedance == 0)
    start = calibrate(
        curve_model, truth[1], method="pgd", options={"max_iter": 0, "n_bank_uniform": 128}
    )
    assert res.mae_deg.mean() < start.mae_deg.mean()


def test_missing_load_case_is_calibrated_and_reported(curve_model, truth):
    targets = truth[1].copy()
    targets[0, 2] = np.nan  # specimen 0: no lateral bending
    res = calibrate(curve_model, targets, method="pgd", options={"n_bank_uniform": 256})
    assert np.isfinite(res.mae_deg).all() and res.mae_deg.max() < 1e-2
    assert np.isnan(res.r2_per_load_case[0, 2])
    frame = res.metrics_frame()
    assert frame.loc[0, "missing_load_cases"] == "LateralBending"
    assert (frame.loc[1:, "missing_load_cases"] == "").all()


def test_bad_targets_and_options(curve_model, truth):
    with pytest.raises(InputDataError, match=r"Targets must have shape \(n, 4, 5\)"):
        calibrate(curve_model, truth[1][:, :, :3], method="pgd")
    empty = truth[1].copy()
    empty[1] = np.nan
    with pytest.raises(InputDataError, match=r"Specimens at positions \[1\] have no measured"):
        calibrate(curve_model, empty, method="pgd")
    with pytest.raises(ConfigError, match="pgd: unknown optimizer 'sgd'; choose one of"):
        calibrate(curve_model, truth[1], method="pgd", options={"optimizer": "sgd"})
    with pytest.raises(ConfigError, match=r"pgd: effect_max_iter must be an integer >= 1 or None"):
        calibrate(curve_model, truth[1], method="pgd", options={"effect_max_iter": 0})
    with pytest.raises(ConfigError, match="pgd-study: unknown projection 'x'"):
        calibrate(curve_model, truth[1], method="pgd-study", options={"projection": "x"})
    with pytest.raises(ConfigError, match="start_bank must have shape"):
        calibrate(curve_model, truth[1], method="pgd", options={"start_bank": np.ones((3, 2))})


def test_jacobian_matches_finite_differences(small_surrogate):
    net = small_surrogate.torch_module()
    import copy

    net64 = copy.deepcopy(net).double()
    moments = torch.tensor([1.0, 2.5, 5.0], dtype=torch.float64)
    v = torch.rand(4, net.n_params, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    values, jac = net64.curves_jacobian(v, moments)
    eps = 1e-6
    for i in range(net.n_params):
        dv = torch.zeros_like(v)
        dv[:, i] = eps
        fd = (net64.curves(v + dv, moments) - net64.curves(v - dv, moments)) / (2 * eps)
        torch.testing.assert_close(jac[..., i], fd, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(values, net64.curves(v, moments))


def _study_reference(problem: CalibrationProblem, u0: torch.Tensor, steps: int, lr: float):
    """The study's Algorithm 1 written literally: one parameter copy per row, autograd on each
    row's own copy, Adam on the search matrix, projection = mean over rows then clip."""
    model = problem.model
    n_rows = problem.mask[0].sum()
    lc_idx, m_idx = torch.nonzero(problem.mask[0], as_tuple=True)
    y = problem.target[0][lc_idx, m_idx]
    search = u0.repeat(int(n_rows), 1).clone().requires_grad_(True)  # (k, d)
    opt = torch.optim.Adam([search], lr=lr, betas=(_BETA1, _BETA2), eps=_EPS)
    for _ in range(steps):
        opt.zero_grad()
        curves = model.curves(model.from_linear_unit(search))  # (k, 4, m)
        pred = curves[torch.arange(int(n_rows)), lc_idx, m_idx]
        (pred - y).abs().mean().backward()
        opt.step()
        with torch.no_grad():
            search[:] = search.mean(0).clamp(0, 1)
    return search[0].detach()


def test_pgd_study_matches_the_literal_algorithm(curve_model, truth):
    targets = truth[1][:1]
    problem = CalibrationProblem.from_arrays(curve_model, targets)
    rng = np.random.default_rng(0)
    u0 = torch.tensor(rng.random((1, curve_model.dim)), dtype=torch.float32)
    ref = _study_reference(problem, u0[0], steps=25, lr=0.0971)
    res = calibrate(
        curve_model,
        targets,
        method="pgd-study",
        seed=np.random.default_rng(0),
        options={"n_starts": 1, "steps": 25},
    )
    ours = curve_model.space.to_unit(res.x)[0]
    np.testing.assert_allclose(ours, ref.numpy(), atol=2e-5)


def test_pgd_study_ablations(curve_model, truth):
    far = 2.5 * truth[1][:2]
    common = {"n_starts": 4, "steps": 60}
    projected = calibrate(curve_model, far, method="pgd-study", options=common)
    unprojected = calibrate(
        curve_model, far, method="pgd-study", options={**common, "projection": "average"}
    )
    penalised = calibrate(
        curve_model,
        far,
        method="pgd-study",
        options={**common, "projection": "average", "bounds_penalty": 0.05},
    )
    assert np.all(projected.exceedance == 0)
    assert np.all(unprojected.exceedance > 0)  # the study's "no projection" leaves the box
    assert penalised.exceedance.sum() < unprojected.exceedance.sum()
    lbfgs = calibrate(
        curve_model, far, method="pgd-study", options={**common, "optimizer": "lbfgs"}
    )
    assert np.all(lbfgs.exceedance == 0)


def test_curve_model_rejects_non_differentiable_surrogates():
    with pytest.raises(ConfigError, match="needs a differentiable surrogate with torch_module"):
        SurrogateCurveModel(object(), [1.0])


def test_member_subset_jacobian(small_surrogate):
    """With every member it is the exact Jacobian; with fewer, the members' mean Jacobian
    (checked against the members' own exact Jacobians) and the ensemble's values."""
    import copy

    ens = copy.deepcopy(small_surrogate.torch_module())
    # Two members: the fitted one and a perturbed copy, so they differ.
    second = copy.deepcopy(ens.members[0])
    with torch.no_grad():
        for p in second.parameters():
            p.mul_(1.1)
    ens.members.append(second)
    ens.n_members = 2
    sur = copy.copy(small_surrogate)
    sur.net_ = ens
    model = SurrogateCurveModel(sur, [1.0, 3.0, 5.0])
    v = torch.rand(5, ens.n_params, generator=torch.Generator().manual_seed(1))
    exact_values, exact = model.curves_jacobian(v)
    values, approx = model.curves_jacobian(v, jacobian_members=1)
    torch.testing.assert_close(values, exact_values)
    first_only = copy.deepcopy(ens)
    first_only.members = first_only.members[:1]
    first_only.n_members = 1
    _, member0 = first_only.curves_jacobian(v, model.moments)
    torch.testing.assert_close(approx, member0)
    assert not torch.allclose(approx, exact)


def test_problem_keeps_each_specimens_error_scale(curve_model, truth):
    rom = truth[1][:2].copy()
    weight = np.ones_like(rom)
    weight[1] = 4.0  # inverse variances: the second specimen's points have half the sd
    weight[1, 0, 0] = np.nan  # a point left out does not count in the mean
    rom[1, 0, 0] = np.nan
    problem = CalibrationProblem.from_arrays(curve_model, rom, weight, weight_sd=0.06)
    # point_sd = weight_sd / sqrt(mean weight over the measured points)
    np.testing.assert_allclose(problem.point_sd.numpy(), [0.06, 0.03])
    # the fit weights are still scaled to a mean of 1 per specimen
    assert torch.allclose(problem.weight[1][problem.mask[1]].mean(), torch.tensor(1.0))
    np.testing.assert_allclose(problem.subset(slice(1, 2)).point_sd.numpy(), [0.03])
    assert CalibrationProblem.from_arrays(curve_model, rom, weight).point_sd is None
    with pytest.raises(ConfigError, match=r"weight_sd must be a finite sd > 0 .*got -1"):
        CalibrationProblem.from_arrays(curve_model, rom, weight, weight_sd=-1)


def test_pgd_counts_each_specimens_own_error_scale(curve_model, truth):
    # Two copies of one specimen's curves: the second measured as the mean of 16 repeats
    # (inverse variance 16, sd / 4). Its identifiability ranges must be narrower; with one
    # scale for the batch (no weight_sd) both get the same ranges.
    rom = np.repeat(truth[1][:1], 2, axis=0)
    weight = np.ones_like(rom)
    weight[1] = 16.0
    bank = curve_model.space.sample_lhs(128, np.random.default_rng(0))
    opts = {"start_bank": bank, "noise_deg": 0.05}
    own = calibrate(curve_model, rom, weight=weight, options=opts, weight_sd=0.05)
    one = calibrate(curve_model, rom, weight=weight, options=opts)
    width_own = (own.x_high - own.x_low) / curve_model.space.width
    width_one = (one.x_high - one.x_low) / curve_model.space.width
    np.testing.assert_allclose(width_one[0], width_one[1], atol=1e-4)  # float32 batches
    assert width_own[1].sum() < 0.8 * width_own[0].sum()
    # the first specimen's scale is 0.05 either way: the same ranges
    np.testing.assert_allclose(width_own[0], width_one[0], atol=1e-4)
    assert "each specimen's own" in own.message and own.info["error_scale_deg"] > 0


def test_pgd_refits_the_specimens_the_noise_does_not_explain(curve_model, truth):
    # Settings too light to fit (one start, one iteration): most specimens end beyond the
    # noise, and the retry calibrates those again from more starts; the better fit is kept.
    rng = np.random.default_rng(1)
    rom = truth[1] + rng.normal(0.0, 0.02, truth[1].shape)
    light = {"n_starts": 1, "keep_after": 0, "max_iter": 1, "n_bank_uniform": 64}
    plain = calibrate(
        curve_model, rom, options={**light, "retry_alpha": 0.0}, weight_sd=0.02, seed=3
    )
    again = calibrate(curve_model, rom, options=light, weight_sd=0.02, seed=3)
    flagged = plain.p_value < 0.01
    assert flagged.sum() >= 3  # the premise: one iteration does not fit
    assert again.info["n_refitted"] == flagged.sum()
    assert 1 <= again.info["n_refit_improved"] <= flagged.sum()
    assert "not explained within the noise refitted from 4 starts" in again.message
    # never worse; better where refitted and improved; untouched elsewhere
    assert np.all(again.chi2 <= plain.chi2 + 1e-9)
    assert again.chi2[flagged].sum() < 0.5 * plain.chi2[flagged].sum()
    np.testing.assert_array_equal(again.x[~flagged], plain.x[~flagged])
    assert np.all(again.exceedance == 0)
    # Without an error scale there is no test to retry on.
    none = calibrate(curve_model, rom, options=light, seed=3)
    assert "n_refitted" not in none.info
    with pytest.raises(ConfigError, match=r"pgd: retry_alpha must be in \[0, 1\).*got 1\.5"):
        calibrate(curve_model, rom, options={"retry_alpha": 1.5}, weight_sd=0.02)


def test_chunks_add_up_the_refit_counts(curve_model, truth):
    rom = truth[1] + np.random.default_rng(1).normal(0.0, 0.02, truth[1].shape)
    light = {"n_starts": 1, "keep_after": 0, "max_iter": 1, "n_bank_uniform": 64}
    whole = calibrate(curve_model, rom, options=light, weight_sd=0.02, seed=3, chunk_size=2)
    assert whole.info["n_chunks"] == 3
    # Each chunk refits its own unexplained specimens; the counts are the batch's: the same
    # three chunks calibrated one by one from one generator (as the chunks draw from it).
    rng = np.random.default_rng(3)
    parts = [
        calibrate(curve_model, rom[i : i + 2], options=light, weight_sd=0.02, seed=rng)
        for i in (0, 2, 4)
    ]
    np.testing.assert_array_equal(whole.x, np.concatenate([p.x for p in parts]))
    for key in ("n_refitted", "n_refit_improved"):
        assert whole.info[key] == sum(p.info[key] for p in parts)
    assert whole.info["n_refitted"] > parts[0].info["n_refitted"]


def test_chi2_needs_an_error_scale(curve_model, truth):
    problem = CalibrationProblem.from_arrays(curve_model, truth[1])
    with pytest.raises(ConfigError, match=r"chi2 needs each specimen's error scale: .*weight_sd"):
        problem.chi2(truth[1])
    scaled = CalibrationProblem.from_arrays(curve_model, truth[1], weight_sd=0.1)
    chi2, n_points = scaled.chi2(truth[1] + 0.1)  # every point 1 sd off
    np.testing.assert_allclose(chi2, n_points)
    assert n_points.tolist() == [20] * 6


def test_effective_parameters_are_the_hat_trace_of_the_fit(curve_model, truth):
    """The effective parameters at x are ``tr(I (I + 1)^-1)`` with ``I = J^T Σ^-1 J`` in the
    network's unit coordinates, every point weighed by its own sd: checked against a central
    finite-difference Jacobian of the curves (float32 network: steps of 1e-3 in the unit box,
    the trace agrees to 1e-2). More noise makes the data see fewer parameters; the trace never
    exceeds the parameters or the points."""
    x, clean = truth
    weight = np.ones_like(clean)
    weight[:, :, -1] = 4.0  # the 5 Nm points the mean of four repeats
    problem = CalibrationProblem.from_arrays(curve_model, clean, weight, weight_sd=0.05)
    with pytest.raises(ConfigError, match=r"effective_parameters needs each specimen's error"):
        CalibrationProblem.from_arrays(curve_model, clean).effective_parameters(x)
    k = problem.effective_parameters(x, batch=4)  # two batches
    v = curve_model.from_physical(x).double()
    h = 1e-3
    d = v.shape[1]
    jac = np.zeros((*clean.shape, d))
    with torch.no_grad():
        for j in range(d):
            step = torch.zeros_like(v)
            step[:, j] = h
            up = curve_model.curves((v + step).float()).double()
            down = curve_model.curves((v - step).float()).double()
            jac[..., j] = ((up - down) / (2 * h)).numpy()
    w = problem.weight.double().numpy()
    sd = problem.point_sd.double().numpy()[:, None, None] / np.sqrt(w)
    j = (jac / sd[..., None]).reshape(len(x), -1, d)
    info = np.einsum("npi,npj->nij", j, j)
    expected = np.einsum("nij,nji->n", info, np.linalg.inv(info + np.eye(d)))
    np.testing.assert_allclose(k, expected, atol=1e-2)
    assert np.all((k > 0) & (k < min(d, clean[0].size)))
    noisier = CalibrationProblem.from_arrays(curve_model, clean, weight, weight_sd=0.5)
    assert np.all(noisier.effective_parameters(x) < k)


def test_gauss_newton_settles_on_the_exact_jacobian(small_surrogate):
    """The cheaper Jacobian only shortens the way: with ``settle_exact`` each row stops where
    the exact loss is stationary, at the loss the exact Jacobian reaches from the same start;
    the residuals returned are those of the final parameters."""
    import copy

    from femcal.calibration.gauss_newton import gauss_newton_residuals
    from femcal.calibration.pgd_options import GaussNewtonOptions

    ens = copy.deepcopy(small_surrogate.torch_module())
    second = copy.deepcopy(ens.members[0])  # a second member that differs from the first
    with torch.no_grad():
        for p in second.parameters():
            p.mul_(1.1)
    ens.members.append(second)
    ens.n_members = 2
    sur = copy.copy(small_surrogate)
    sur.net_ = ens
    model = SurrogateCurveModel(sur, [1.0, 2.0, 3.0, 5.0])
    x = model.space.sample_uniform(4, np.random.default_rng(2))
    # off the model's curves (0.05 deg noise): the loss at the optimum is not zero
    targets = model.predict(x) + np.random.default_rng(3).normal(0, 0.05, (4, 4, 4))
    problem = CalibrationProblem.from_arrays(model, targets)
    v0 = torch.rand(4, model.dim, generator=torch.Generator().manual_seed(5))
    rows = torch.arange(4)
    runs = {}
    for name, extra in {"exact": {}, "cheap": dict(jacobian_members=1, settle_exact=True)}.items():
        options = GaussNewtonOptions(max_iter=100, loss="l2", tol=1e-6, **extra)
        runs[name] = gauss_newton_residuals(problem, v0, rows, options)
    v, _, converged, res = runs["cheap"]
    with torch.no_grad():
        pred = model.curves(v)
    torch.testing.assert_close(res, ((pred - problem.target) * problem.mask).reshape(4, -1))
    w = problem.weight.reshape(4, -1)
    loss = {k: (w * r[3] ** 2).sum(1) for k, r in runs.items()}
    assert converged.all() and runs["exact"][2].all()
    # the same minimum to 1e-3 of the loss (float32 curves; steps stop below 1e-6 of it)
    torch.testing.assert_close(loss["cheap"], loss["exact"], rtol=1e-3, atol=1e-8)
