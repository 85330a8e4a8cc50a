"""Calibration outputs: tables, figures, summary, held-out re-evaluation, coverage."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2 as chi2_dist

from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.calibration.plots import FigureCurves, plot_specimen, plot_specimens
from femcal.calibration.report import (
    coverage,
    figure_names,
    holdout_scores,
    identifiability,
    plot_mode,
    write_outputs,
)
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
    holdout = SurrogateCurveModel(small_surrogate, curve_model.moments.numpy())
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
    assert {"exceedance", "holdout_mae_deg"} <= set(metrics.columns)
    assert "seconds" not in metrics  # the run's wall time: in the figures, not in the files
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
    other = SurrogateCurveModel(
        small_surrogate, [1.5, 2.5, 3.5, 4.5, 5.5]
    )  # another grid = other curves
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


@pytest.mark.parametrize(
    ("plots", "pngs"),
    [
        (True, {"summary.png", "plots/S0.png", "plots/S1.png"}),
        ("all", None),
        ("summary", {"summary.png"}),
        ("none", set()),
        (False, set()),
    ],
)
def test_write_outputs_plots_choose_the_figures_not_the_tables(
    tmp_path, curve_model, truth, plots, pngs
):
    pngs = {"summary.png", "plots/S0.png", "plots/S1.png"} if pngs is None else pngs
    res = calibrate(
        curve_model,
        truth[1][:3],
        specimens=["S0", "S1", "S2"],
        method="pgd",
        options={"n_bank_uniform": 64},
    )
    out = tmp_path / "out"
    figures = write_outputs(res, out, plots=plots, max_plots=2)
    assert {p.relative_to(out).as_posix() for p in out.rglob("*.png")} == pngs
    assert figures["n_plotted"] == (2 if "plots/S0.png" in pngs else 0)
    for table in ("parameters.csv", "metrics.csv", "curves.csv", "summary.md", "summary.json"):
        assert (out / table).is_file(), table
    assert len(pd.read_csv(out / "metrics.csv")) == 3


def test_specimens_whose_names_reduce_to_one_file_name_get_a_figure_each(
    tmp_path, curve_model, truth
):
    names = ["a b", "a_b", "a/b"]
    assert figure_names(names) == ["a_b", "a_b_", "a_b__"]
    assert figure_names(["a_b", "a b"]) == ["a_b", "a_b_"]  # the first keeps the plain name
    res = calibrate(
        curve_model, truth[1][:3], specimens=names, method="pgd", options={"n_bank_uniform": 64}
    )
    write_outputs(res, tmp_path / "out", plots="all")
    pngs = sorted(p.name for p in (tmp_path / "out" / "plots").iterdir())
    assert pngs == ["a_b.png", "a_b_.png", "a_b__.png"]


def test_an_unknown_plots_value_is_refused_before_any_file(tmp_path, curve_model, truth):
    res = calibrate(curve_model, truth[1][:2], method="pgd", options={"n_bank_uniform": 64})
    with pytest.raises(ValueError, match=r"plots must be one of all, summary, none .*'some'"):
        write_outputs(res, tmp_path / "out", plots="some")
    assert not (tmp_path / "out").exists()
    assert plot_mode(True) == "all" and plot_mode(False) == "none"
    assert plot_mode("summary") == "summary"


def test_one_redrawn_figure_writes_what_a_figure_per_specimen_writes(
    tmp_path, curve_model, truth, small_surrogate
):
    """plot_specimens reuses one figure: each PNG shows its own specimen (not the previous)."""
    from matplotlib.image import imread

    targets = truth[1][:3].copy()
    targets[1, 2] = np.nan  # specimen 1 without lateral bending: "not measured", then back
    res = calibrate(curve_model, targets, method="pgd", options={"n_bank_uniform": 64})
    held = holdout_scores(res, SurrogateCurveModel(small_surrogate, curve_model.moments.numpy()))
    batch = [tmp_path / f"batch{i}.png" for i in range(3)]
    curves = FigureCurves.at_measured(res, held["prediction"])
    plot_specimens(res, batch, curves)
    images = [imread(p) for p in batch]
    assert all(img.shape == images[0].shape for img in images)
    assert not np.array_equal(images[0], images[1]) and not np.array_equal(images[1], images[2])
    for i in (0, 2):  # alone: the same picture up to the layout of the first specimen
        plot_specimen(res, i, tmp_path / f"alone{i}.png", curves)
        alone = imread(tmp_path / f"alone{i}.png")
        assert alone.shape == images[i].shape
        assert np.mean(np.abs(alone - images[i])) < 0.02
    plot_specimens(res, [])  # nothing to draw: no figure built, no file


def test_the_residuals_are_tested_against_the_noise(tmp_path, curve_model, truth):
    """With an error scale (``weight_sd``) each specimen's residuals are measured in units of
    its points' own sd: chi2 is ``sum w_k r_k^2 / weight_sd^2`` with the weights as given
    (inverse variances), and a specimen the model cannot follow is flagged "beyond noise"."""
    _, clean = truth
    rng = np.random.default_rng(0)
    noise = 0.05
    weight = rng.choice([1.0, 4.0], size=clean.shape)  # some points the mean of 4 repeats
    targets = clean + rng.normal(0.0, noise, clean.shape) / np.sqrt(weight)
    # Specimen 0: a zigzag of 6 sd in flexion that no smooth model follows (missing physics).
    targets[0, 0] += 6 * noise * (-1.0) ** np.arange(targets.shape[2])
    res = calibrate(
        curve_model,
        targets,
        specimens=[f"S{i}" for i in range(len(targets))],
        weight=weight,
        weight_sd=noise,
        options={"n_bank_uniform": 256},
    )
    resid = targets - res.prediction
    np.testing.assert_allclose(res.chi2, (weight * resid**2).sum(axis=(1, 2)) / noise**2)
    assert res.n_points.tolist() == [targets[0].size] * len(targets)
    # a point of average weight has sd noise / sqrt(mean w)
    np.testing.assert_allclose(res.error_scale_deg, noise / np.sqrt(weight.mean(axis=(1, 2))))
    # The fit of 13 parameters to 20 points takes some of them: the residuals' degrees of
    # freedom are the points less the fit's effective parameters (the trace of the hat matrix).
    assert np.all((res.n_effective > 1) & (res.n_effective < 13))
    np.testing.assert_allclose(res.dof, res.n_points - res.n_effective)
    np.testing.assert_allclose(res.p_value, chi2_dist.sf(res.chi2, res.dof))
    # The zigzag alone is chi2 >= 20 * 36 / 2 with the weights >= 1: p far below 0.01. The
    # other five are noise at the sd their weights declare: p > 0.01 each with probability
    # 0.99, and this seed's draw passes.
    assert res.p_value[0] < 1e-6 and res.rms_z[0] > 2
    assert np.all(res.p_value[1:] > 0.01) and np.all(res.rms_z[1:] < 1.5)
    figures = write_outputs(res, tmp_path / "out", plots="none")
    assert figures["n_beyond_noise"] == 1
    assert figures["rms_z_max"] == pytest.approx(res.rms_z[0])
    metrics = pd.read_csv(tmp_path / "out" / "metrics.csv", keep_default_na=False)
    assert {"error_scale_deg", "rms_z", "dof", "p_value"} <= set(metrics.columns)
    assert metrics["flag"].tolist() == ["beyond noise"] + [""] * 5
    text = (tmp_path / "out" / "summary.md").read_text()
    assert "1 of 6 specimens are not explained within the noise" in text
    # Without an error scale there is nothing to test against: no columns, no figures.
    plain = calibrate(curve_model, targets, weight=weight, options={"n_bank_uniform": 256})
    assert plain.chi2 is None and plain.rms_z is None and plain.p_value is None
    assert plain.n_effective is None and plain.dof is None
    assert "rms_z" not in plain.metrics_frame()
    assert "n_beyond_noise" not in write_outputs(plain, tmp_path / "plain", plots="none")


def _two_specimens(curve_model, truth):
    """A pgd calibration of the first two specimens (a small bank: about a second)."""
    return calibrate(
        curve_model,
        truth[1][:2],
        specimens=["S0", "S1"],
        method="pgd",
        options={"n_bank_uniform": 64},
    )


def test_before_figures_is_called_with_the_tables_written_and_no_figure_yet(
    tmp_path, curve_model, truth
):
    result = _two_specimens(curve_model, truth)
    out, seen = tmp_path / "out", {}

    def hook(figures):
        seen["files"] = sorted(p.name for p in out.rglob("*") if p.is_file())
        seen["figures"] = dict(figures)

    figures = write_outputs(result, out, before_figures=hook)
    assert {"parameters.csv", "metrics.csv", "curves.csv", "summary.json"} <= set(seen["files"])
    assert not [name for name in seen["files"] if name.endswith(".png")]
    assert seen["figures"] == figures
    assert json.loads((out / "summary.json").read_text()) == {
        k: v for k, v in figures.items() if k != "seconds"
    }
    assert (out / "summary.png").exists() and len(list((out / "plots").glob("*.png"))) == 2


def test_a_rerun_writes_the_same_files(tmp_path, curve_model, truth):
    """Two calibrations of the same specimens write the same bytes (what DVC hashes), though
    their wall times differ: the time is in the returned figures only."""
    folders, times = [], []
    for name in ("first", "second"):
        result = _two_specimens(curve_model, truth)
        figures = write_outputs(result, tmp_path / name, plots="summary")
        folders.append(tmp_path / name)
        times.append(figures["seconds"])
    files = [
        {p.relative_to(f): p.read_bytes() for p in f.rglob("*") if p.is_file()} for f in folders
    ]
    assert "summary.png" in {p.name for p in files[0]}
    assert files[0] == files[1]
    assert all(t > 0 for t in times)
