"""``femcal calibrate`` logs its MLflow run from a child process set up beside the calibration.

The command's own process loads the model folders and calibrates; the child imports MLflow,
opens the SQL store and logs the run meanwhile. The run is logged as before, errors of the
store or of a logging call are raised in the command's process, and a failure while writing
the outputs ends the run as FAILED.
"""

from __future__ import annotations

import json
import subprocess
import sys

import mlflow
import pytest
import yaml
from calibration_helpers import MOMENTS

from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.jobs.mlflow_steps import log_calibration, start_calibration_run
from femcal.stages.tracking_process import TrackingProcess
from femcal.tracking import (
    configure_tracking,
    ensure_experiment,
    export_model,
    folder_sha256,
    log_surrogate,
)

from synth import long_csv

#: MLflow and its SQL store, and the model zoo: none is needed to calibrate on model folders.
NOT_HERE = ("mlflow", "sqlalchemy", "alembic", "lightgbm", "sklearn.compose")


@pytest.fixture
def project(tmp_path, monkeypatch, small_surrogate, truth):
    """Two exported model folders, a measurement file and a params.yaml with its own store."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    configure_tracking(store_dir=tmp_path / "owner")
    ensure_experiment("owner", store_dir=tmp_path / "owner")
    for split in ("large", "holdout"):
        with mlflow.start_run() as run:
            info = log_surrogate(small_surrogate, small_surrogate.space)
        export_model(
            info.model_uri,
            tmp_path / "models" / f"surrogate-{split}",
            record={"run_id": run.info.run_id, "registered_model": None, "version": None},
        )
    mlflow.set_tracking_uri(None)
    long_csv(tmp_path / "meas.csv", truth[1][:3])
    params = {
        "mlflow": {
            "store_dir": str(tmp_path / "mlruns"),
            "experiment": "teammate",
            "model_name": "ivd-rom-surrogate",
        },
        "moments": MOMENTS,
        "calibrate": {
            "datasets": {"mine": str(tmp_path / "meas.csv")},
            "out_dir": str(tmp_path / "cal"),
            "method": "pgd",
            "model_uri": str(tmp_path / "models" / "surrogate-large"),
            "holdout_uri": str(tmp_path / "models" / "surrogate-holdout"),
            "start_bank": None,
            "seed": 0,
            "plots": False,
            "options": {"pgd": {"n_bank_uniform": 64}},
        },
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    params["_path"] = str(tmp_path / "params.yaml")
    yield tmp_path, params
    mlflow.set_tracking_uri(None)


def _runs(store):
    mlflow.set_tracking_uri(f"sqlite:///{store / 'mlflow.db'}")
    return mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`femcal.stage` = 'calibrate'"
    )


def test_the_command_logs_its_run_without_importing_mlflow_itself(project):
    tmp, _ = project
    code = (
        "import json, sys\n"
        "from femcal.cli import main\n"
        f"rc = main(['--params', {str(tmp / 'params.yaml')!r}, '-q', 'calibrate'])\n"
        f"print(json.dumps([rc, sorted(m for m in {NOT_HERE!r} if m in sys.modules)]))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err.decode()
    *printed, last = out.decode().strip().splitlines()
    assert json.loads(last) == [0, []], err.decode()
    assert any("calibrated 3 specimens with pgd" in line for line in printed)
    runs = _runs(tmp / "mlruns")
    assert len(runs) == 1
    run = runs.iloc[0]
    assert run["status"] == "FINISHED"
    assert run["tags.femcal.model.sha256"] == folder_sha256(tmp / "models" / "surrogate-large")
    assert run["params.n_specimens"] == "3"
    assert run["tags.femcal.pid"] != str(proc.pid)  # logged by the child
    marker = json.loads((tmp / "cal" / "mine" / ".femcal-run.json").read_text())
    assert marker["mlflow_run_id"] == run["run_id"]
    arts = {a.path for a in mlflow.MlflowClient().list_artifacts(run["run_id"], "calibration")}
    assert {"calibration/parameters.csv", "calibration/.femcal-run.json"} <= arts


def test_a_failure_while_writing_the_outputs_ends_the_run_failed(project, monkeypatch):
    tmp, params = project
    import femcal.calibration.report as report

    def disk_full(*args, **kwargs):
        raise OSError("No space left on device (the test's)")

    monkeypatch.setattr(report, "write_outputs", disk_full)
    with (
        pytest.raises(OSError, match=r"No space left on device \(the test's\)"),
        TrackingProcess(params) as tracker,
    ):
        run_calibration(
            CalibrationJob(
                measurements=tmp / "meas.csv",
                out_dir=tmp / "out",
                method="pgd",
                model_uri=str(tmp / "models" / "surrogate-large"),
                holdout_uri=None,
                start_bank=None,
                options={"n_bank_uniform": 64},
                seed=0,
                plots="none",
                **MOMENTS,
            ),
            tracker=tracker,
        )
    runs = _runs(tmp / "mlruns")
    assert list(runs["status"]) == ["FAILED"]
    assert not (tmp / "out").exists()


def test_an_error_of_a_logging_call_is_raised_here_with_the_childs_traceback(project):
    tmp, params = project
    with TrackingProcess(params) as tracker:
        run_id = tracker.call(start_calibration_run, run_name="calibrate-test")
        with pytest.raises(FileNotFoundError, match=r"metrics\.csv") as info:
            tracker.call(
                log_calibration,
                tags={},
                params={"method": "pgd"},
                metrics={},
                parameters=None,
                measurements=tmp / "meas.csv",
                figures={},
                out_dir=tmp / "no-such-folder",
            )
        assert any("In the MLflow process" in note for note in info.value.__notes__)
        tracker.abort()
    runs = _runs(tmp / "mlruns")
    assert list(runs["run_id"]) == [run_id] and list(runs["status"]) == ["FAILED"]


def test_a_broken_store_is_raised_here(project, monkeypatch):
    tmp, params = project
    (tmp / "a-file").write_text("")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'a-file' / 'mlflow.db'}")
    with (
        pytest.raises(FileExistsError, match="a-file"),
        TrackingProcess(params) as tracker,
    ):
        tracker.call(start_calibration_run, run_name="calibrate-test")


def test_only_the_runs_calls_are_sent(project):
    _, params = project
    with (
        pytest.raises(ValueError, match="print is not one of"),
        TrackingProcess(params) as tracker,
    ):
        tracker.submit(print, value="x")
