"""The calibrate stage end to end: registry -> measurements file -> outputs + one MLflow run."""

from __future__ import annotations

import json
import re

import mlflow
import numpy as np
import pandas as pd
import pytest
import yaml
from calibration_helpers import MOMENTS

from femcal.cli import main
from femcal.errors import InputDataError, ModelRegistryError
from femcal.jobs.calibrate import CalibrationJob, run_calibration

from synth import long_csv


def _calibrate(measurements, out_dir, **overrides):
    """``run_calibration`` with this file's defaults: pgd against the registered champion, no
    held-out surrogate, no start bank, seed 0, the moment policy above."""
    kwargs = dict(
        method="pgd",
        model_uri="models:/ivd-rom-surrogate@champion",
        holdout_uri=None,
        start_bank=None,
        options={},
        seed=0,
        **MOMENTS,
    )
    tracker = overrides.pop("tracker", None)
    settings = CalibrationJob(measurements=measurements, out_dir=out_dir, **(kwargs | overrides))
    return run_calibration(settings, tracker=tracker)


def test_run_calibration_logs_one_run_with_tables(registry, truth):
    tmp = registry
    curves = truth[1].copy()
    curves[1, 0] = np.nan  # spec-1 has no flexion
    meas = long_csv(tmp / "meas.csv", curves)
    result, figures = _calibrate(
        meas,
        tmp / "out",
        holdout_uri="models:/ivd-rom-surrogate-holdout@champion",
        options={"n_bank_uniform": 256},
    )
    assert result.specimens == tuple(f"spec-{i}" for i in range(6))
    # Reachable targets: the fit stops at a quarter of the noise (the small surrogate's error).
    assert figures["mae_deg"] < 0.05 and figures["n_outside_bounds"] == 0
    assert figures["holdout_mae_deg"] == pytest.approx(figures["mae_deg"], abs=1e-9)
    runs = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'calibrate'")
    assert len(runs) == 1
    run = runs.iloc[0]
    assert run["params.model_version"] == "ivd-rom-surrogate/1"
    assert run["metrics.mae_deg"] == pytest.approx(figures["mae_deg"])
    assert "Flexion" in run["tags.femcal.missing_load_cases"]
    client = mlflow.MlflowClient()
    arts = {a.path for a in client.list_artifacts(run["run_id"], "calibration")}
    assert {"calibration/parameters.csv", "calibration/metrics.csv"} <= arts
    table = mlflow.load_table("tables/metrics.json", run_ids=[run["run_id"]])
    assert len(table) == 6 and set(table["specimen"]) == set(result.specimens)


def test_run_calibration_shows_plotting_and_logging_progress(registry, truth, capsys):
    """On a terminal (progress=True): bars over the plots and the files logged to MLflow."""
    _calibrate(
        long_csv(registry / "meas.csv", truth[1][:3]),
        registry / "out",
        options={"n_bank_uniform": 64},
        progress=True,
    )
    err = capsys.readouterr().err
    assert "plots: 100%" in err and "3/3" in err
    files = sorted(p for p in (registry / "out").rglob("*") if p.is_file())
    assert "MLflow artifacts: 100%" in err and f"{len(files)}/{len(files)}" in err
    # The artifacts mirror the output folder, sub-folders included.
    run_id = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'calibrate'")["run_id"][0]
    client = mlflow.MlflowClient()
    plots = {a.path for a in client.list_artifacts(run_id, "calibration/plots")}
    assert plots == {f"calibration/plots/spec-{i}.png" for i in range(3)}
    top = {a.path for a in client.list_artifacts(run_id, "calibration")}
    assert {"calibration/summary.md", "calibration/plots"} <= top


def test_points_far_outside_the_trained_range_are_dropped_and_listed(registry, truth):
    meas = long_csv(registry / "m.csv", truth[1][:1], moments=(1, 2, 3, 4, 9))
    with pytest.warns(UserWarning, match=r"m\.csv: dropped 4 measured point\(s\) at moments 9 Nm"):
        _, figures = _calibrate(meas, registry / "out")
    assert figures["n_dropped_points"] == 4
    dropped = pd.read_csv(registry / "out" / "dropped_points.csv")
    assert set(dropped["moment_nm"]) == {9.0} and set(dropped["specimen"]) == {"spec-0"}
    only_far = long_csv(registry / "far.csv", truth[1][:1, :, :1], moments=(9,))
    with pytest.raises(
        InputDataError,
        match=r"far\.csv: no measured point is usable: every measured moment \(field moment_nm: "
        r"9 Nm\) lies outside the moments the surrogate is used at, \[0\.6, 8\.33\] Nm",
    ):
        _calibrate(only_far, registry / "out2")


def test_cli_calibrate_with_version_and_errors(registry, truth, capsys, monkeypatch):
    tmp = registry
    monkeypatch.chdir(tmp)
    meas = long_csv(tmp / "meas.csv", truth[1][:2])
    params = {
        "mlflow": {
            "store_dir": str(tmp / "mlruns"),
            "experiment": "test",
            "model_name": "ivd-rom-surrogate",
        },
        "moments": MOMENTS,
        "calibrate": {
            "datasets": {
                "mine": str(meas),
                "with_facets": {"measurements": str(meas), "effects": ["facet_contact"]},
                "broken": {"effects": []},
            },
            "out_dir": str(tmp / "cal"),
            "method": "pgd",
            "model_uri": "models:/ivd-rom-surrogate@champion",
            "holdout_uri": None,
            "start_bank": None,
            "seed": 0,
            "plots": False,
            "options": {"pgd": {"n_bank_uniform": 128}},
        },
    }
    (tmp / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    args = ["--params", str(tmp / "params.yaml"), "calibrate"]
    stage = ["--metrics-file", "reports/calibrate-mine.json"]  # as the DVC stage passes it
    assert main([*args, "--dataset", "mine", "--model-version", "1", *stage]) == 0
    out = capsys.readouterr().out
    assert "calibrated 2 specimens with pgd against models:/ivd-rom-surrogate/1" in out
    assert json.loads((tmp / "reports/calibrate-mine.json").read_text())["n"] == 2
    assert (tmp / "cal/mine/parameters.csv").exists() and not (tmp / "cal/mine/plots").exists()
    # A version that does not exist: exit code 2 and a message naming the URI.
    assert main([*args, "--model-version", "7"]) == 2
    assert "models:/ivd-rom-surrogate/7" in capsys.readouterr().err
    assert main([*args, "--dataset", "theirs"]) == 2
    assert "Unknown dataset 'theirs'" in capsys.readouterr().err
    bad = tmp / "bad.csv"
    bad.write_text("specimen,load_case,moment_nm,rom_deg\nA,twist,1,2.0\n")
    assert main([*args, "--measurements", str(bad)]) == 2
    assert "unknown load case 'twist'" in capsys.readouterr().err
    # A dataset's effects, and --effects overriding them.
    assert main([*args, "--dataset", "with_facets"]) == 0
    capsys.readouterr()
    names = pd.read_csv(tmp / "cal/with_facets/parameters.csv").columns
    assert "facet_gap_deg" in names
    assert main([*args, "--dataset", "with_facets", "--effects", ""]) == 0
    capsys.readouterr()
    assert "facet_gap_deg" not in pd.read_csv(tmp / "cal/with_facets/parameters.csv").columns
    assert main([*args, "--dataset", "broken"]) == 2
    assert "calibrate.datasets.broken in" in capsys.readouterr().err
    assert main([*args, "--measurements", str(meas), "--effects", "cartilage"]) == 2
    assert "cartilage" in capsys.readouterr().err


def test_measurement_noise_is_counted_in_pgd_error_scale(registry, truth, small_surrogate):
    # pgd's error scale of one RoM value (its ranges, near-optimal starts and fit tolerance)
    # is hypot(noise, the surrogate's error) with a measurement noise, the surrogate's alone
    # without; the MLflow run records both.
    meas = long_csv(registry / "m.csv", truth[1][:2])
    for noise in (None, 0.2):
        _calibrate(meas, registry / f"out-{noise}", options={"n_bank_uniform": 64}, noise_deg=noise)
    runs = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'calibrate'")
    scale = dict(zip(runs["params.noise_deg"], runs["params.option.noise_deg"].astype(float)))
    sd = small_surrogate.best_val_mae_deg_ * np.sqrt(np.pi / 2)
    assert scale["none"] == pytest.approx(sd, rel=1e-6)
    assert scale["0.2"] == pytest.approx(np.hypot(0.2, sd), rel=1e-6)


def test_cli_calibrate_takes_the_noise_from_the_dataset_or_the_command_line(
    registry, truth, capsys, monkeypatch, small_surrogate
):
    tmp = registry
    monkeypatch.chdir(tmp)
    meas = long_csv(tmp / "meas.csv", truth[1][:1])
    params = {
        "mlflow": {"store_dir": str(tmp / "mlruns"), "experiment": "test"},
        "moments": MOMENTS,
        "calibrate": {
            "datasets": {"noisy": {"measurements": str(meas), "noise_deg": 0.05}},
            "out_dir": str(tmp / "cal"),
            "method": "pgd",
            "model_uri": "models:/ivd-rom-surrogate@champion",
            "plots": False,
            "options": {"pgd": {"n_bank_uniform": 64}},
        },
    }
    (tmp / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    args = ["--params", str(tmp / "params.yaml"), "calibrate", "--no-holdout"]
    assert main([*args, "--dataset", "noisy"]) == 0
    assert "(measurement noise 0.05 deg counted): MAE" in capsys.readouterr().out
    assert main([*args, "--dataset", "noisy", "--noise-deg", "0.1"]) == 0
    assert "(measurement noise 0.1 deg counted)" in capsys.readouterr().out
    assert main([*args, "--measurements", str(meas), "--out", str(tmp / "other")]) == 0
    assert "counted" not in capsys.readouterr().out
    runs = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'calibrate'")
    assert sorted(runs["params.noise_deg"]) == ["0.05", "0.1", "none"]
    assert main([*args, "--dataset", "noisy", "--noise-deg", "-1"]) == 2
    assert re.search(
        r"--noise-deg: the measurement noise sd must be a number > 0 in degrees; got -1\.0",
        capsys.readouterr().err,
    )
    # A specimen the model cannot follow (every other flexion point 8 sd up; the sd of a point is
    # hypot(noise, the small surrogate's error)) is reported as not explained within the
    # noise: the printed note, the flag and the metrics file's columns.
    sd = np.hypot(0.05, small_surrogate.best_val_mae_deg_ * np.sqrt(np.pi / 2))
    curves = np.concatenate([truth[1][:1], truth[1][:1]])
    curves[1, 0, ::2] += 8 * sd
    zigzag = long_csv(tmp / "zigzag.csv", curves)
    out = tmp / "zz"
    assert (
        main([*args, "--measurements", str(zigzag), "--noise-deg", "0.05", "--out", str(out)]) == 0
    )
    assert re.search(
        r"NOTE: 1 of 2 specimens are not explained within the noise \(median residual "
        r"[0-9.]+ sd\): see .*metrics\.csv \(columns flag, rms_z, p_value\); `femcal diagnose`",
        capsys.readouterr().out,
    )
    metrics = pd.read_csv(out / "metrics.csv", keep_default_na=False)
    assert metrics.loc[0, "flag"] == "" and "beyond noise" in metrics.loc[1, "flag"]
    assert metrics.loc[1, "rms_z"] > 2 > 1 > metrics.loc[0, "rms_z"]
    assert metrics.loc[1, "p_value"] < 0.01 < metrics.loc[0, "p_value"]


def test_missing_registered_model(registry, truth):
    meas = long_csv(registry / "m.csv", truth[1][:1])
    with pytest.raises(
        ModelRegistryError, match="Could not load the model 'models:/nope@champion'"
    ):
        _calibrate(meas, registry / "out", model_uri="models:/nope@champion")


def test_adding_an_effect_writes_before_and_after(registry, small_surrogate):
    # Targets with a planted facet contact: the disc alone, then the disc with the effect.
    from femcal.calibration import SurrogateCurveModel
    from femcal.effects.composite import EffectModel

    tmp = registry
    moments = (1.0, 2.0, 3.0, 4.0, 5.0)
    model = EffectModel(SurrogateCurveModel(small_surrogate, moments), ["facet_contact"])
    x = small_surrogate.space.sample_uniform(4, np.random.default_rng(2))
    curves = model.predict(np.concatenate([x, [[0.5, 2.0]] * 4], axis=1))
    meas = long_csv(tmp / "meas.csv", curves, moments)
    common = dict(options={"n_bank_uniform": 256}, plots=False)
    _, disc = _calibrate(meas, tmp / "disc", **common)
    assert not (tmp / "disc" / "comparison.md").exists()  # nothing to compare with yet
    _, facet = _calibrate(meas, tmp / "facet", effects=["facet_contact"], **common)
    table = json.loads((tmp / "facet" / "comparison.json").read_text())
    rows = {r["metric"]: r for r in table["metrics"]}
    assert table["before"]["effects"] == "none" and table["after"]["effects"] == "facet_contact"
    assert rows["mae_deg"]["before"] == pytest.approx(disc["mae_deg"])
    assert rows["mae_deg"]["after"] == pytest.approx(facet["mae_deg"])
    # The planted effect acts on extension and axial rotation: there the error must fall.
    for lc in ("Extension", "AxialRotation"):
        assert rows[f"mae_deg_{lc}"]["after"] < rows[f"mae_deg_{lc}"]["before"]
    runs = mlflow.search_runs(
        filter_string="tags.`femcal.stage` = 'calibrate'", order_by=["attributes.start_time DESC"]
    )
    assert runs.iloc[0]["tags.femcal.compared_to"] == runs.iloc[1]["run_id"]
    assert "| mae_deg_Extension |" in (tmp / "facet" / "comparison.md").read_text()


def test_extrapolated_moments_warn_and_weigh_less(registry, small_surrogate, monkeypatch):
    # The common in vitro protocol, 1.25 .. 7.5 Nm, against a surrogate trained on 1..5 Nm.
    import femcal.calibration
    from femcal.calibration import SurrogateCurveModel

    moments = (1.25, 2.5, 5.0, 7.5)
    x = small_surrogate.space.sample_uniform(2, np.random.default_rng(4))
    meas = long_csv(
        registry / "vitro.csv", SurrogateCurveModel(small_surrogate, moments).predict(x), moments
    )
    seen = {}
    real = femcal.calibration.calibrate

    def spy(*args, **kwargs):
        seen["weight"] = kwargs["weight"]
        return real(*args, **kwargs)

    monkeypatch.setattr(femcal.calibration, "calibrate", spy)
    with pytest.warns(
        UserWarning,
        match=r"vitro\.csv: measured moments 7\.5 Nm lie outside the surrogate's trained moment "
        r"range \[1, 5\] Nm .* deg at 7\.5 Nm, counted in sigma",
    ):
        _, figures = _calibrate(
            meas, registry / "out", options={"n_bank_uniform": 128}, plots=False
        )
    assert figures["n_specimens"] == 2
    # 1 / sd(M)^2 relative to the trained range: exp(-2 g L), L = log(7.5 / 5).
    expected = np.array([1.0, 1.0, 1.0, 1.5 ** (-2 * MOMENTS["error_growth"])])
    np.testing.assert_allclose(seen["weight"], np.broadcast_to(expected, (2, 4, 4)))


def test_run_diagnosis_checks_moments_and_counts_the_error_per_moment(
    registry, small_surrogate, truth, monkeypatch, diagnosis_keywords
):
    from femcal.jobs.diagnose import DiagnosisJob, run_diagnosis
    from femcal.moments import MomentPolicy

    common = diagnosis_keywords
    moments = (1, 2, 3, 4, 5, 6)
    curves = np.concatenate([truth[1][:1], truth[1][:1, :, -1:]], axis=2)
    with pytest.warns(UserWarning, match=r"measured moments 6 Nm lie outside"):
        diag, summary = run_diagnosis(
            DiagnosisJob(measurements=long_csv(registry / "d.csv", curves, moments), **common)
        )
    policy = MomentPolicy.for_surrogate(
        small_surrogate, growth=MOMENTS["error_growth"], max_log_ratio=MOMENTS["max_log_ratio"]
    )
    sur = policy.sigma_surrogate(np.array(moments, dtype=float))
    sigma = diag.sigma_by_moment
    assert sigma.shape == (6,) and sur[-1] > sur[0] == sur[4] == pytest.approx(policy.error_deg)
    np.testing.assert_allclose(sigma, np.sqrt(0.05**2 + sur**2), rtol=1e-6)
    assert summary["n_specimens"] == 1 and (registry / "diag" / "diagnosis.json").exists()
    far = long_csv(registry / "far.csv", truth[1][:1], moments=(1, 2, 3, 4, 12))
    with pytest.warns(UserWarning, match=r"far\.csv: dropped 4 measured point\(s\) at moments 12"):
        diag, summary = run_diagnosis(DiagnosisJob(measurements=far, **common))
    assert diag.sigma_by_moment.shape == (4,) and summary["n_dropped_points"] == 4
    listed = pd.read_csv(registry / "diag" / "dropped_points.csv")
    assert set(listed["moment_nm"]) == {12.0} and len(listed) == 4
    only_far = long_csv(registry / "only.csv", truth[1][:1, :, :1], moments=(12,))
    with pytest.raises(InputDataError, match=r"only\.csv: no measured point is usable"):
        run_diagnosis(DiagnosisJob(measurements=only_far, **common))
