"""The calibration's MLflow tables and comparison are logged while its figures are drawn.

:func:`femcal.jobs.calibrate.run_calibration` hands ``log_calibration`` to the tracker as soon
as the tables are written (:func:`femcal.calibration.report.write_outputs`' ``before_figures``):
in ``femcal calibrate`` the MLflow process logs them while the figures are drawn. The run
still holds every output file.
"""

from __future__ import annotations

from pathlib import Path

import mlflow
import pytest

from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.jobs.mlflow_steps import LocalTracking
from femcal.tracking import configure_tracking, ensure_experiment, export_model, log_surrogate

from synth import long_csv


class _Noting(LocalTracking):
    """The in-process tracker (MLflow itself), noting the PNGs on disk at each call."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[str, list[str] | None]] = []

    def submit(self, fn, /, **kwargs):
        out = kwargs.get("out_dir") or kwargs.get("folder")
        pngs = None if out is None else sorted(p.name for p in Path(out).rglob("*.png"))
        self.calls.append((fn.__name__, pngs))
        super().submit(fn, **kwargs)


@pytest.fixture
def model_folder(tmp_path, monkeypatch, small_surrogate) -> Path:
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("overlap", store_dir=tmp_path / "mlruns")
    with mlflow.start_run():
        info = log_surrogate(small_surrogate, small_surrogate.space)
    export_model(info.model_uri, tmp_path / "surrogate")
    yield tmp_path / "surrogate"
    mlflow.set_tracking_uri(None)


def test_the_tables_are_logged_before_the_figures_are_drawn(tmp_path, model_folder, truth):
    long_csv(tmp_path / "meas.csv", truth[1][:3])
    job = CalibrationJob(
        measurements=tmp_path / "meas.csv",
        out_dir=tmp_path / "out",
        method="pgd",
        model_uri=str(model_folder),
        holdout_uri=None,
        start_bank=None,
        options={"n_bank_uniform": 64},
        seed=0,
        plots="all",
        error_growth=3.2,
        max_log_ratio=0.51,
    )
    tracker = _Noting()
    _, figures = run_calibration(job, tracker=tracker)
    names = [name for name, _ in tracker.calls]
    assert names == [
        "start_calibration_run",
        "log_calibration",
        "log_artifacts",
        "end_calibration_run",
    ]
    assert tracker.calls[1][1] == []  # no figure drawn yet when the tables are logged
    assert len(tracker.calls[2][1]) == 4  # the summary page and 3 specimens, all logged
    run_id = mlflow.last_active_run().info.run_id
    client = mlflow.MlflowClient()
    assert client.get_run(run_id).data.metrics["n_dropped_points"] == figures["n_dropped_points"]
    plots = {a.path for a in client.list_artifacts(run_id, "calibration/plots")}
    assert len(plots) == 3
