"""The moment policy through the real `femcal diagnose` and `femcal calibrate` commands.

A file on the study's grid from 0.5 Nm (and a few points at 0.25 Nm, beyond the measured low
end) against a small surrogate trained on 1..5 Nm: 0.5 Nm is used (with the larger error
counted), the 0.25 Nm points are dropped with a warning naming them and listed in
``dropped_points.csv``, and a file with no usable point is refused with the file, the field and
the fix.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
import yaml

from femcal.calibration import SurrogateCurveModel
from femcal.cli import main
from femcal.errors import InputDataError
from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.jobs.diagnose import DiagnosisJob, run_diagnosis
from femcal.moments import DROPPED_COLUMNS
from femcal.schema import LOAD_CASES
from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import (
    configure_tracking,
    ensure_experiment,
    log_surrogate,
    register_and_promote,
)

from synth import study_space, tidy_table

NOISE = 0.02
#: The study's grid from 0.5 Nm; 0.25 Nm lies beyond the low end's limit below.
MOMENTS = np.array([0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0])
#: params.yaml ``moments``: one growth rate and one limit per side of the trained range.
POLICY = {
    "error_growth": {"below": 0.8, "above": 2.99},
    "max_log_ratio": {"below": 1.1, "above": 0.51},
}
POLICY_ARGS = {"error_growth": (0.8, 2.99), "max_log_ratio": (1.1, 0.51)}


@pytest.fixture(scope="module")
def surrogate() -> NeuralSurrogate:
    table = tidy_table(48, seed=3)  # 1..5 Nm
    model = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    model.best_val_mae_deg_ = 1e-3  # its curves are the truth of this world
    model.val_error_profile_ = None  # the same error at every moment
    return model


@pytest.fixture(scope="module")
def registry_store(tmp_path_factory, surrogate) -> Path:
    """An MLflow store with ``surrogate`` the champion of ivd-rom-surrogate, built once; each
    test's project gets a copy (its locations resolved by configure_tracking)."""
    store = tmp_path_factory.mktemp("moments-registry") / "mlruns"
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        configure_tracking(store_dir=store)
        ensure_experiment("moments", store_dir=store)
        with mlflow.start_run():
            info = log_surrogate(surrogate, surrogate.space)
        register_and_promote(info.model_uri, name="ivd-rom-surrogate", val_metric=0.1)
        mlflow.set_tracking_uri(None)
    return store


@pytest.fixture
def project(tmp_path, monkeypatch, surrogate, registry_store):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert tuple(surrogate.moment_range_) == (1.0, 5.0)
    shutil.copytree(registry_store, tmp_path / "mlruns")
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("moments", store_dir=tmp_path / "mlruns")
    rng = np.random.default_rng(5)
    x = study_space().sample_uniform(3, rng)
    rom = SurrogateCurveModel(surrogate, MOMENTS).predict(x) + rng.normal(0, NOISE, (3, 4, 7))
    rows = [
        (f"S{i}", lc, m, abs(rom[i, k, j]))
        for i in range(3)
        for k, lc in enumerate(LOAD_CASES)
        for j, m in enumerate(MOMENTS)
        if m > 0.3 or (i == 1 and lc == "Flexion")  # two points at 0.25 Nm: S1 flexion only
    ]
    rows.append(("S1", "Extension", 0.25, abs(rom[1, 1, 0])))
    pd.DataFrame(rows, columns=["specimen", "load_case", "moment_nm", "rom_deg"]).to_csv(
        "meas.csv", index=False
    )
    params = {
        "mlflow": {
            "store_dir": "mlruns",
            "experiment": "moments",
            "model_name": "ivd-rom-surrogate",
        },
        "moments": POLICY,
        "effects": {"modules": []},
        "calibrate": {
            "datasets": {},
            "out_dir": "cal",
            "method": "pgd",
            "model_uri": "models:/ivd-rom-surrogate@champion",
            "holdout_uri": None,
            "start_bank": None,
            "seed": 0,
            "plots": False,
            "options": {"pgd": {"n_bank_uniform": 256, "noise_deg": NOISE}},
        },
        "diagnose": {
            "measurements": "meas.csv",
            "out_dir": "diag",
            "metrics_file": None,
            "noise_deg": NOISE,
            "candidates": ["facet_contact"],
            "min_delta": 10.0,
            "seed": 0,
            "plots": False,
        },
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    yield tmp_path
    mlflow.set_tracking_uri(None)


def _dropped(folder) -> pd.DataFrame:
    table = pd.read_csv(folder / "dropped_points.csv")
    assert list(table.columns) == list(DROPPED_COLUMNS)
    return table


def _assert_the_two_points_at_a_quarter(table: pd.DataFrame) -> None:
    assert sorted(zip(table["specimen"], table["load_case"], table["moment_nm"])) == [
        ("S1", "Extension", 0.25),
        ("S1", "Flexion", 0.25),
    ]
    assert set(table["source"]) == {"meas.csv"}
    assert table["reason"].str.startswith("0.25 Nm below the accepted 0.333..8.33 Nm").all()


def _warned(caplog) -> list[str]:
    """The moment policy's warnings: log lines (the command line prints each once)."""
    return [r.getMessage() for r in caplog.records if r.name == "femcal.moments"]


def test_diagnose_uses_half_a_newton_metre_and_lists_what_it_dropped(project, capsys, caplog):
    assert main(["diagnose", "--out", "d"]) == 0
    messages = _warned(caplog)
    dropped = next(m for m in messages if "dropped" in m)
    assert dropped.startswith(
        "meas.csv: dropped 2 measured point(s) at moments 0.25 Nm, outside the moments the "
        "surrogate is used at, [0.333, 8.33] Nm (moments.max_log_ratio below 1.1, above 0.51): "
        "specimen 'S1' Flexion 0.25 Nm; specimen 'S1' Extension 0.25 Nm."
    )
    assert any("measured moments 0.5 Nm lie outside" in m for m in messages)
    printed = capsys.readouterr().out
    assert "WARNING: 2 measured points lie beyond the moments" in printed
    assert "d/dropped_points.csv" in printed
    _assert_the_two_points_at_a_quarter(_dropped(project / "d"))
    residuals = pd.read_csv(project / "d" / "residuals.csv")
    assert 0.5 in set(residuals["moment_nm"]) and 0.25 not in set(residuals["moment_nm"])
    assert set(residuals["specimen"]) == {"S0", "S1", "S2"}
    # 0.5 Nm counts its larger surrogate error: sigma there is hypot(noise, sd(0.5 Nm))
    at = residuals[residuals["moment_nm"] == 0.5].iloc[0]
    sd = 1e-3 * np.sqrt(np.pi / 2) * 2.0**0.8
    assert at["residual_deg"] / at["residual_sigma"] == pytest.approx(np.hypot(NOISE, sd), 1e-3)


def test_calibrate_uses_half_a_newton_metre_and_lists_what_it_dropped(project, capsys, caplog):
    assert main(["calibrate", "--measurements", "meas.csv", "--out", "c"]) == 0
    assert any("dropped 2 measured point(s) at moments 0.25 Nm" in m for m in _warned(caplog))
    printed = capsys.readouterr().out
    assert "WARNING: 2 measured points lie beyond the moments" in printed
    _assert_the_two_points_at_a_quarter(_dropped(project / "c"))
    curves = pd.read_csv(project / "c" / "curves.csv")
    assert 0.5 in set(curves["moment_nm"]) and 0.25 not in set(curves["moment_nm"])
    metrics = pd.read_csv(project / "c" / "metrics.csv")
    assert list(metrics["specimen"]) == ["S0", "S1", "S2"]
    assert metrics["mae_deg"].max() < 4 * NOISE  # the surrogate's own curves, with noise
    run = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'calibrate'").iloc[0]
    assert run["params.moments.max_log_ratio.below"] == "1.1"
    assert run["metrics.n_dropped_points"] == 2


def test_a_file_without_a_usable_point_is_refused_by_both(project, capsys):
    pd.DataFrame(
        [("S0", lc, m, 0.1 * m) for lc in LOAD_CASES for m in (0.1, 0.2)],
        columns=["specimen", "load_case", "moment_nm", "rom_deg"],
    ).to_csv("tiny.csv", index=False)
    match = (
        r"^tiny\.csv: no measured point is usable: every measured moment \(field moment_nm: "
        r"0\.1, 0\.2 Nm\) lies outside the moments the surrogate is used at, \[0\.333, 8\.33\] "
        r"Nm .* Give the moments in Nm within that interval, or train the surrogate on a wider "
        r"moment range\.$"
    )
    common = dict(
        measurements="tiny.csv",
        model_uri="models:/ivd-rom-surrogate@champion",
        start_bank=None,
        **POLICY_ARGS,
    )
    calibrate = CalibrationJob(
        out_dir=project / "c", method="pgd", holdout_uri=None, options={}, seed=0, **common
    )
    with pytest.raises(InputDataError, match=match):
        run_calibration(calibrate)
    diagnose = DiagnosisJob(out_dir=project / "d", noise_deg=NOISE, candidates=None, **common)
    with pytest.raises(InputDataError, match=match):
        run_diagnosis(diagnose)
    assert main(["calibrate", "--measurements", "tiny.csv", "--out", "c"]) == 2
    assert (
        "femcal calibrate: error: tiny.csv: no measured point is usable" in capsys.readouterr().err
    )
    assert not (project / "c").exists() and not (project / "d").exists()
