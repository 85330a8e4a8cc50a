"""The diagnosis' MLflow run through a tracker (:func:`femcal.jobs.diagnose.run_diagnosis`).

``femcal diagnose`` hands its MLflow calls to a child process
(:class:`femcal.stages.tracking_process.TrackingProcess`); a library caller's run is logged in
its own process (:class:`femcal.jobs.mlflow_steps.LocalTracking`). Either way the run is
started once the diagnosis is done, holds its tags, parameters, metrics and every output file,
and ends FINISHED.
"""

from __future__ import annotations

import mlflow

from femcal.jobs.diagnose import DiagnosisJob, run_diagnosis
from femcal.jobs.mlflow_steps import LocalTracking

from synth import long_csv


class _Noting(LocalTracking):
    """The in-process tracker (MLflow itself), noting each call's name."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[str] = []

    def submit(self, fn, /, **kwargs):
        self.calls.append(fn.__name__)
        super().submit(fn, **kwargs)


def test_the_diagnosis_logs_its_run_through_the_tracker(registry, truth, diagnosis_keywords):
    tracker = _Noting()
    job = DiagnosisJob(
        measurements=long_csv(registry / "d.csv", truth[1][:2]),
        **{**diagnosis_keywords, "plots": True},
    )
    diag, summary = run_diagnosis(job, tracker=tracker)
    assert tracker.calls == [
        "start_diagnosis_run",
        "log_run",
        "log_artifacts",
        "end_calibration_run",
    ]
    run = mlflow.search_runs(search_all_experiments=True, output_format="list")[0]
    assert run.info.status == "FINISHED" and run.data.tags["femcal.stage"] == "diagnose"
    assert run.data.params["candidates"] == "neutral_zone"
    assert run.data.metrics["seconds"] == diag.seconds
    logged = {a.path for a in mlflow.MlflowClient().list_artifacts(run.info.run_id, "diagnosis")}
    assert {"diagnosis/diagnosis.json", "diagnosis/plots", "diagnosis/summary.md"} <= logged
    assert summary["n_specimens"] == 2
