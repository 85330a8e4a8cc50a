"""Calibration outputs: tables, figures, summary, held-out re-evaluation, coverage."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from femcal.calibration import CurveModel, calibrate
from femcal.calibration.report import coverage, holdout_scores, identifiability, write_outputs
from femcal.schema import LOAD_CASES


def test_write_outputs(tmp_path, curve_model, truth, small_surrogate):
    x_true, targets = truth
    targets = targets.copy()
    targets[2, 3] = np.nan  # specimen 2 without axial rotation
    res = calibrate(
        curve_model,
        targets,
        specimens=[f"S{i}" for i in range(len(targets))],
        method="pgd",
        options={"n_bank_uniform": 256},
    )
    holdout = CurveModel(small_surrogate, curve_model.moments.numpy())
    figures = write_outputs(res, tmp_path / "out", holdout=holdout, max_plots=4)
    out = tmp_path / "out"
    params = pd.read_csv(out / "parameters.csv")
    assert params.columns.tolist() == ["specimen", *curve_model.space.names]
    np.testing.assert_allclose(params[list(curve_model.space.names)].to_numpy(), res.x)
    metrics = pd.read_csv(out / "metrics.csv", keep_default_na=False)
    expected = ["specimen", "method", "mae_deg", "r2_mean"]
    assert metrics.columns.tolist()[:4] == expected
    for lc in LOAD_CASES:
        assert f"mae_{lc}" in metrics and f"r2_{lc}" in metrics
    assert {"exceedance", "seconds", "holdout_mae_deg"} <= set(metrics.columns)
    assert metrics["seconds"].nunique() == 1
    assert metrics.loc[2, "missing_load_cases"] == "AxialRotation"
    # The "held-out" model is the same surrogate here, so it must agree exactly.
    np.testing.assert_allclose(metrics["holdout_mae_deg"], metrics["mae_deg"], atol=1e-9)
    assert sorted(p.name for p in (out / "plots").iterdir()) == [f"S{i}.png" for i in range(4)]
    assert (out / "summary.png").stat().st_size > 1000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_specimens"] == 6 and summary["n_plotted"] == 4
    assert summary["mae_deg"] == figures["mae_deg"]
    assert "S2: no AxialRotation" in (out / "summary.md").read_text()
    curves = pd.read_csv(out / "curves.csv")
    assert len(curves) == np.isfinite(targets).sum()
    ranges = pd.read_csv(out / "ranges.csv")
    assert len(ranges) == 6 * curve_model.dim
    assert (ranges["low"] <= ranges["value"] + 1e-12).all()


def test_coverage_and_identifiability(curve_model, truth):
    x_true, targets = truth
    res = calibrate(curve_model, targets, method="pgd", options={"n_bank_uniform": 256})
    cov = coverage(res, x_true)
    assert cov.shape == (curve_model.dim,) and np.all((cov >= 0) & (cov <= 1))
    # A range that is the box itself always covers; a point range at a wrong value never does.
    res.x_low, res.x_high = (
        np.tile(curve_model.space.lower, (6, 1)),
        np.tile(curve_model.space.upper, (6, 1)),
    )
    assert np.all(coverage(res, x_true) == 1)
    assert np.all(identifiability(res)["determined"] == 0)
    res.x_low = res.x_high = np.tile(curve_model.space.lower, (6, 1))
    assert np.all(coverage(res, x_true) == 0)


def test_holdout_scores_detect_a_different_model(curve_model, truth, small_surrogate):
    res = calibrate(curve_model, truth[1], method="pgd", options={"n_bank_uniform": 256})
    other = CurveModel(small_surrogate, [1.5, 2.5, 3.5, 4.5, 5.5])  # another grid = other curves
    held = holdout_scores(res, other)
    assert np.all(held["mae"] > res.mae_deg)


def test_write_outputs_shows_the_plots_progress_only_when_asked(
    tmp_path, curve_model, truth, capsys
):
    res = calibrate(curve_model, truth[1][:3], method="pgd", options={"n_bank_uniform": 64})
    write_outputs(res, tmp_path / "quiet", max_plots=2)
    assert "plots" not in capsys.readouterr().err
    write_outputs(res, tmp_path / "shown", max_plots=2, progress=True)
    err = capsys.readouterr().err
    assert "plots: 100%" in err and "2/2" in err
    assert len(list((tmp_path / "shown" / "plots").glob("*.png"))) == 2
