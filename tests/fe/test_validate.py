"""FE re-simulation of calibrated parameters (the study's step 4), on the real solver."""

from __future__ import annotations

import json

import mlflow
import numpy as np
import pandas as pd
import pytest
import yaml
from fe_helpers import COARSE, MOMENTS, requires_ccx

from femcal.cli import main
from femcal.errors import ConfigError, InputDataError
from femcal.fe.dataset import write_dataset
from femcal.fe.validate import literature_ranges
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

from synth import study_space

LITERATURE = {
    300: {"low": 0.0, "mean": 0.3, "high": 10.0},
    1000: {"low": 0.0, "mean": 1.0, "high": 10.0},
    2000: {"low": 50.0, "mean": 60.0, "high": 70.0},  # out of reach: nobody is in range
}


PUBLISHED = [
    {
        "source": "test",
        "condition": "lying (test)",
        "idp_mpa": 1e-3,
        "kind": "in vivo",
        "subjects": 1,
        "level": "L4-L5",
    },
    {
        "source": "test",
        "condition": "out of reach (test)",
        "idp_mpa": 500.0,
        "kind": "in vivo",
        "subjects": 1,
        "level": "L4-L5",
    },
]


def _idp_head(tmp_path):
    """A tiny IDP head (a pressure surrogate, linear target) exported as a model folder."""
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.tracking import export_model, log_surrogate

    from synth import tidy_table

    table = tidy_table(24, seed=4)
    head = NeuralSurrogate(
        study_space(), hidden=(8,), max_epochs=3, batch_size=16, log_target=False, seed=0
    ).fit(table, table["idp_mpa"].to_numpy())
    with mlflow.start_run():
        info = log_surrogate(head, head.space)
    return export_model(info.model_uri, tmp_path / "idp-head")


def test_literature_ranges_are_checked():
    ranges = literature_ranges(LITERATURE)
    assert [r.force_n for r in ranges] == [300.0, 1000.0, 2000.0]
    assert ranges[0].contains(np.array([0.2, 11.0])).tolist() == [True, False]
    with pytest.raises(ConfigError, match=r"at 300 N need force > 0 and low <= mean <= high"):
        literature_ranges({300: {"low": 0.5, "mean": 0.3, "high": 1.0}})
    with pytest.raises(ConfigError, match="must be a force in N mapping to"):
        literature_ranges({300: [0.1, 0.2]})


@requires_ccx
@pytest.mark.slow  # real CalculiX runs (minutes): CI runs it in its slow step
def test_validate_resimulates_calibrated_parameters(coarse_campaign, tmp_path, mlflow_store):
    _, design_df, result = coarse_campaign
    write_dataset(
        design_df,
        result.records.to_dict(orient="records"),
        tmp_path / "ds",
        space=study_space(),
        moments=MOMENTS,
    )
    measurements = tmp_path / "ds" / "Test"  # the held-out FE curves: specimen "0"
    truth = design_df[design_df["split"] == "test"]
    # A perfect calibration (the true parameters) whose surrogate is 0.01 deg off everywhere.
    cal = tmp_path / "cal"
    cal.mkdir()
    params = truth[list(PARAMETER_NAMES)].assign(specimen="0")
    params[["specimen", *PARAMETER_NAMES]].to_csv(cal / "parameters.csv", index=False)
    fe_rows = result.records[result.records["config_id"] == int(truth["config_id"].iloc[0])]
    curves = [
        ("0", r.load_case, m, v, v + 0.01)
        for r in fe_rows.itertuples()
        for m, v in zip(MOMENTS, r.rom_deg)
        if v is not None
    ]
    pd.DataFrame(
        curves,
        columns=["specimen", "load_case", "moment_nm", "measured_rom_deg", "calibrated_rom_deg"],
    ).to_csv(cal / "curves.csv", index=False)

    settings = {
        "mlflow": {"store_dir": str(mlflow_store), "experiment": "fe-test"},
        "fe": {"solver": "calculix", "settings": COARSE, "n_workers": 2},
        "validate": {
            "calibration_dir": str(cal),
            "measurements": str(measurements),
            "out_dir": str(tmp_path / "val"),
            "metrics_file": str(tmp_path / "validate.json"),
            "store": str(tmp_path / "val-runs.jsonl"),
            "forces": [300, 1000, 2000],
            "idp_literature": LITERATURE,
            "idp_published": PUBLISHED,
            "idp_model_uri": str(_idp_head(tmp_path)),
        },
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(settings))
    stage = ["validate", "--metrics-file", str(tmp_path / "validate.json")]  # as dvc.yaml
    assert main(["--params", str(tmp_path / "params.yaml"), *stage]) == 0
    runs = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'validate'")
    assert len(runs) == 1 and runs["metrics.fe_mae_deg"].iloc[0] < 1e-6
    table = pd.read_csv(tmp_path / "val" / "validation.csv", dtype={"specimen": str})
    row = table.iloc[0]
    assert row["specimen"] == "0"
    assert row["fe_mae_deg"] < 1e-6  # the FE model reproduces its own curves
    assert row["surrogate_mae_deg"] == pytest.approx(0.01, abs=1e-9)
    assert row["fe_vs_surrogate_mae_deg"] == pytest.approx(0.01, abs=1e-6)
    idp = [row[f"idp_mpa_{f}N"] for f in (300, 1000, 2000)]
    assert np.all(np.isfinite(idp)) and idp[0] > 0 and np.all(np.diff(idp) > 0)
    assert bool(row["idp_in_range_300N"]) and not bool(row["idp_in_range_2000N"])
    summary = json.loads((tmp_path / "val" / "validation.json").read_text())
    assert summary["idp"][2]["n_in_range"] == 0 and summary["idp"][0]["n_in_range"] == 1
    assert set(summary["fe_mae_deg_per_load_case"]) == set(LOAD_CASES)
    assert summary["solver_versions"] and summary["n_specimens"] == 1
    assert json.loads((tmp_path / "validate.json").read_text())["n"] == 1
    # A published pressure below the disc's pressure at 300 N is reached by interpolation,
    # one beyond its pressure at 2000 N is not (nothing is extrapolated).
    low, high = summary["idp_published"]
    assert low["n_reached"] == 1 and 0 < low["force_n_median"] < 300
    assert high["n_reached"] == 0 and high["n_beyond"] == 1
    published = pd.read_csv(tmp_path / "val" / "idp_published.csv", dtype={"specimen": str})
    assert published["condition"].tolist() == ["lying (test)", "out of reach (test)"]
    # The IDP head against FE's pressures under the four moments, where FE has them.
    head = pd.read_csv(tmp_path / "val" / "idp_head.csv", dtype={"specimen": str})
    assert set(head["load_case"]) == set(LOAD_CASES) and head["head_idp_mpa"].notna().all()
    assert summary["idp_head"]["n_points"] == len(head)
    assert summary["idp_head"]["mae_mpa"] == pytest.approx(
        float(np.mean(np.abs(head["head_idp_mpa"] - head["fe_idp_mpa"])))
    )
    assert runs["metrics.idp_head_mae_mpa"].iloc[0] == pytest.approx(summary["idp_head"]["mae_mpa"])
    # Five FE jobs: four moment load cases and one compression; a rerun recomputes nothing.
    assert len((tmp_path / "val-runs.jsonl").read_text().splitlines()) == 5
    assert main(["--params", str(tmp_path / "params.yaml"), "validate"]) == 0
    assert len((tmp_path / "val-runs.jsonl").read_text().splitlines()) == 5


def test_validate_names_a_missing_calibration(tmp_path):
    from femcal.fe.options import ValidateOptions
    from femcal.fe.runtime import FeRuntime
    from femcal.fe.validate import validate_calibration

    fe = FeRuntime("calculix", COARSE, tmp_path / "runs.jsonl")
    with pytest.raises(InputDataError, match=r"parameters.csv do not exist; run the calibrate"):
        validate_calibration(tmp_path, tmp_path, fe, tmp_path / "out", ValidateOptions((300,)))
    with pytest.raises(TypeError, match="unexpected keyword argument 'force'"):
        validate_calibration(tmp_path, tmp_path, fe, tmp_path / "out", force=[300])


@requires_ccx
@pytest.mark.slow  # real CalculiX runs (minutes): CI runs it in its slow step
def test_validate_refines_with_fe_in_the_loop(coarse_campaign, tmp_path, mlflow_store):
    """The stage with ``validate.refine``: FE runs per specimen within the budget, never a
    worse FE error than the calibration's, the refinement's tables, and a rerun from the store.

    The steering surrogate is the synthetic study's (not this FE model's), so its steps may be
    refused: this test is about the stage, tests/fe/test_refine.py about the algorithm.
    """
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.tracking import export_model, log_surrogate

    from synth import tidy_table

    _, design_df, result = coarse_campaign
    write_dataset(
        design_df,
        result.records.to_dict(orient="records"),
        tmp_path / "ds",
        space=study_space(),
        moments=MOMENTS,
    )
    truth = design_df[design_df["split"] == "test"]
    cal = tmp_path / "cal"
    cal.mkdir()
    params = truth[list(PARAMETER_NAMES)].assign(specimen="0")
    params["C10Annulus"] *= 1.3  # a calibration FE does not confirm
    params[["specimen", *PARAMETER_NAMES]].to_csv(cal / "parameters.csv", index=False)
    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(16,), max_epochs=5, patience=5, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    with mlflow.start_run():
        info = log_surrogate(surrogate, surrogate.space)
    export_model(info.model_uri, tmp_path / "model")
    settings = {
        "mlflow": {"store_dir": str(mlflow_store), "experiment": "fe-test"},
        "fe": {"solver": "calculix", "settings": COARSE, "n_workers": 2},
        "validate": {
            "calibration_dir": str(cal),
            "measurements": str(tmp_path / "ds" / "Test"),
            "out_dir": str(tmp_path / "val"),
            "store": str(tmp_path / "val-runs.jsonl"),
            "refine": {"model_uri": str(tmp_path / "model"), "max_fe_runs": 2, "tol_deg": 1e-4},
        },
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(settings))
    metrics = tmp_path / "validate.json"
    stage = ["validate", "--metrics-file", str(metrics)]
    assert main(["--params", str(tmp_path / "params.yaml"), *stage]) == 0
    runs = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'validate'")
    assert runs["metrics.fe_runs_per_specimen_max"].iloc[0] == 2
    assert json.loads(metrics.read_text())["n"] == 1  # the DVC metrics; every figure:
    figures = json.loads((tmp_path / "validate.details.json").read_text())
    assert figures["n_specimens"] == 1 and figures["fe_runs_per_specimen_max"] == 2
    assert figures["fe_fit_residual_deg_before_refine"] > 0.05  # the perturbed calibration misses
    assert figures["fe_fit_residual_deg"] <= figures["fe_fit_residual_deg_before_refine"]
    refine = pd.read_csv(tmp_path / "val" / "refine.csv", dtype={"specimen": str})
    assert refine["fe_runs"].tolist() == [2]
    assert refine["C10Annulus_start"].iloc[0] == pytest.approx(params["C10Annulus"].iloc[0])
    history = pd.read_csv(tmp_path / "val" / "refine_history.csv", dtype={"specimen": str})
    assert history["run"].tolist() == [1, 2]
    validation = pd.read_csv(tmp_path / "val" / "validation.csv", dtype={"specimen": str})
    assert validation["fe_mae_deg"].iloc[0] == pytest.approx(figures["fe_fit_residual_deg"])
    # Two refinement runs x 4 load cases; the validation of the best point replays its moment
    # runs from the store (no compression forces here): 8 jobs, and a rerun adds none.
    assert len((tmp_path / "val-runs.jsonl").read_text().splitlines()) == 8
    assert main(["--params", str(tmp_path / "params.yaml"), "validate"]) == 0
    assert len((tmp_path / "val-runs.jsonl").read_text().splitlines()) == 8


def test_refinement_needs_its_surrogate(tmp_path):
    from femcal.stages.validate import run_validate

    with pytest.raises(ConfigError, match=r"refinement needs validate\.refine\.model_uri"):
        run_validate(
            calibration_dir=tmp_path,
            measurements=tmp_path,
            solver="calculix",
            settings=COARSE,
            forces=[],
            literature={},
            store=tmp_path / "runs.jsonl",
            out_dir=tmp_path / "out",
            refine={"max_fe_runs": 3},
        )
