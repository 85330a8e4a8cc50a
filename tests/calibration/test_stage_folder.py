"""The calibrate stage on the DVC-versioned model folders, in a store that never saw them.

A teammate has ``models/surrogate-large`` and ``models/surrogate-holdout`` from ``dvc pull``,
and a fresh MLflow store; the run records which model ran: its files' SHA-256 and the
registered version the training recorded.
"""

from __future__ import annotations

import mlflow
import numpy as np
import pandas as pd
import pytest
from calibration_helpers import MOMENTS

from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.schema import LOAD_CASES
from femcal.tracking import (
    configure_tracking,
    ensure_experiment,
    export_model,
    folder_sha256,
    log_surrogate,
    register_and_promote,
)


@pytest.fixture
def folders(tmp_path, monkeypatch, small_surrogate):
    """The owner's store: the large surrogate registered, the holdout not; both exported."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    configure_tracking(store_dir=tmp_path / "owner")
    ensure_experiment("test", store_dir=tmp_path / "owner")
    out = {}
    for split, name in (("large", "ivd-rom-surrogate"), ("holdout", None)):
        with mlflow.start_run() as run:
            info = log_surrogate(small_surrogate, small_surrogate.space)
        version = (
            register_and_promote(info.model_uri, name=name, val_metric=0.1)[0] if name else None
        )
        out[split] = export_model(
            info.model_uri,
            tmp_path / "models" / f"surrogate-{split}",
            record={"run_id": run.info.run_id, "registered_model": name, "version": version},
        )
    yield out
    mlflow.set_tracking_uri(None)


def test_calibrate_on_the_folders_in_a_fresh_store_records_which_model_ran(
    folders, truth, tmp_path
):
    rows = [
        (f"spec-{i}", lc, m, truth[1][i, j, k])
        for i in range(3)
        for j, lc in enumerate(LOAD_CASES)
        for k, m in enumerate((1, 2, 3, 4, 5))
    ]
    meas = tmp_path / "meas.csv"
    pd.DataFrame(rows, columns=["specimen", "load_case", "moment_nm", "rom_deg"]).to_csv(
        meas, index=False
    )
    configure_tracking(tracking_uri=f"sqlite:///{tmp_path / 'fresh' / 'mlflow.db'}")
    (tmp_path / "fresh").mkdir()
    ensure_experiment("teammate")
    _, figures = run_calibration(
        CalibrationJob(
            measurements=meas,
            out_dir=tmp_path / "out",
            method="pgd",
            model_uri=str(folders["large"]),
            holdout_uri=str(folders["holdout"]),
            start_bank=None,
            options={"n_bank_uniform": 64},
            seed=0,
            plots=False,
            **MOMENTS,
        )
    )
    assert figures["mae_deg"] < 0.05 and np.isfinite(figures["holdout_mae_deg"])
    run = mlflow.search_runs(filter_string="tags.`femcal.stage` = 'calibrate'").iloc[0]
    assert run["tags.femcal.model.uri"] == str(folders["large"])
    assert run["tags.femcal.model.sha256"] == folder_sha256(folders["large"])
    assert run["tags.femcal.model.version"] == "ivd-rom-surrogate/1"
    assert run["params.model_version"] == "ivd-rom-surrogate/1"
    assert run["tags.femcal.holdout.sha256"] == folder_sha256(folders["holdout"])
    assert run["tags.femcal.holdout.version"] == "unknown"  # trained, never registered
    # The same surrogate logged twice is one content (MLmodel leaves out its run and model id),
    # so its hash names the weights; the URI and the version name the folder that ran.
    assert folder_sha256(folders["large"]) == folder_sha256(folders["holdout"])
