"""The MLflow runs of a calibration and a diagnosis as steps of picklable arguments, and the
in-process tracker.

:func:`femcal.jobs.calibrate.run_calibration` and :func:`femcal.jobs.diagnose.run_diagnosis`
log their run through a tracker: each step is a function of picklable arguments
(:data:`TRACKING_CALLS`) that runs where the tracking store is configured.
:class:`LocalTracking` runs them in this process, in the store and experiment MLflow is
pointed at; ``femcal calibrate`` and ``femcal diagnose`` run them in a child process
(:class:`femcal.stages.tracking_process.TrackingProcess`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol


def log_artifacts(folder: Path, artifact_path: str, *, progress: bool = False) -> None:
    """``mlflow.log_artifacts(folder, artifact_path)`` file by file, with a progress bar.

    The same artifact layout: ``<artifact_path>/<path of the file in folder>``.
    """
    import mlflow

    files: Any = sorted(p for p in Path(folder).rglob("*") if p.is_file())
    if progress and len(files) > 1:
        from tqdm.auto import tqdm

        files = tqdm(files, desc="MLflow artifacts", unit="file")
    for path in files:
        parent = path.parent.relative_to(folder).as_posix()
        mlflow.log_artifact(
            str(path), f"{artifact_path}/{parent}" if parent != "." else artifact_path
        )


def compare_with_previous(
    measurements: Path,
    logged: Mapping[str, Any],
    figures: Mapping[str, Any],
    out_dir: Path,
    compare_to: str | None = None,
) -> dict[str, str]:
    """Before and after (:mod:`femcal.compare`): this run against ``compare_to`` (a folder or
    run id), else against the baseline :data:`femcal.compare.BASELINE_RULE` picks.

    Writes ``comparison.md`` and ``comparison.json`` into ``out_dir`` and tags the run
    ``femcal.compared_to``. Returns what was compared with (``source``) and how it was chosen
    (``chosen``); when nothing was compared, only ``none``: why not.
    """
    import mlflow

    from femcal.compare import (
        BASELINE_RULE,
        DISC_ALONE,
        comparison_frame,
        resolve_baseline,
        write_comparison,
    )

    this = mlflow.active_run().info.run_id
    before = resolve_baseline(
        compare_to,
        measurements=str(measurements),
        effects=logged["effects"],
        exclude_run_id=this,
    )
    if before is None:
        why = (
            "this run is of the disc alone, the default baseline itself"
            if logged["effects"] == DISC_ALONE
            else f"no earlier run matches the default rule, {BASELINE_RULE}"
        )
        return {"none": why}
    after = {k: v for k, v in figures.items() if isinstance(v, (int, float))}
    frame = comparison_frame(before["metrics"], after)
    write_comparison(
        frame,
        out_dir,
        before=before,
        after={
            "run_id": this,
            "effects": logged["effects"],
            "model": logged.get("model_version", ""),
        },
    )
    mlflow.set_tag("femcal.compared_to", before["run_id"] or before["source"])
    return {"source": before["source"], "chosen": before["chosen"]}


def start_calibration_run(run_name: str) -> str:
    """Start the calibration's MLflow run (tagged ``femcal.stage = calibrate``); its id."""
    import mlflow

    run = mlflow.start_run(run_name=run_name)
    mlflow.set_tag("femcal.stage", "calibrate")
    return run.info.run_id


def log_calibration(
    *,
    tags: Mapping[str, str],
    params: Mapping[str, Any],
    metrics: Mapping[str, float],
    parameters: Any,
    measurements: Path,
    figures: Mapping[str, Any],
    out_dir: Path,
    compare_to: str | None = None,
) -> dict[str, str]:
    """Tags, parameters, metrics and the two tables of the active run; the comparison with
    ``compare_to`` or the default baseline (written into ``out_dir``; what was compared with
    is returned, :func:`compare_with_previous`)."""
    import mlflow
    import pandas as pd

    mlflow.set_tags(dict(tags))
    mlflow.log_params(dict(params))
    mlflow.log_metrics(dict(metrics))
    metrics_df = pd.read_csv(Path(out_dir) / "metrics.csv")
    metrics_df["missing_load_cases"] = metrics_df["missing_load_cases"].fillna("")
    mlflow.log_table(metrics_df, artifact_file="tables/metrics.json")
    mlflow.log_table(parameters, artifact_file="tables/parameters.json")
    return compare_with_previous(measurements, params, figures, out_dir, compare_to)


def start_diagnosis_run(run_name: str) -> str:
    """Start the diagnosis' MLflow run (tagged ``femcal.stage = diagnose``); its id."""
    import mlflow

    run = mlflow.start_run(run_name=run_name)
    mlflow.set_tag("femcal.stage", "diagnose")
    return run.info.run_id


def log_run(
    *, tags: Mapping[str, str], params: Mapping[str, Any], metrics: Mapping[str, float]
) -> None:
    """Tags, parameters and metrics of the active run."""
    import mlflow

    mlflow.set_tags(dict(tags))
    mlflow.log_params(dict(params))
    mlflow.log_metrics(dict(metrics))


def end_calibration_run(status: str, run_id: str | None = None) -> None:
    """End the run ``run_id`` (None: the active one) with ``status`` (FINISHED, FAILED), if it
    is the active run (a calibration's or a diagnosis')."""
    import mlflow

    active = mlflow.active_run()
    if active is not None and run_id in (None, active.info.run_id):
        mlflow.end_run(status=status)


class LocalTracking:
    """The MLflow calls of a calibration or a diagnosis in this process: the store and
    experiment MLflow is pointed at (the library's default; the caller configures them).

    :meth:`submit` runs the call at once (its error is raised there); :meth:`result` returns
    the results in the order submitted.
    """

    def __init__(self) -> None:
        self._results: deque[Any] = deque()
        self._run_id: str | None = None

    def submit(self, fn: Callable[..., Any], /, **kwargs: Any) -> None:
        value = fn(**kwargs)
        if fn in (start_calibration_run, start_diagnosis_run):
            self._run_id = value
        self._results.append(value)

    def result(self) -> Any:
        return self._results.popleft()

    def call(self, fn: Callable[..., Any], /, **kwargs: Any) -> Any:
        self.submit(fn, **kwargs)
        return self.result()

    def check(self) -> None:
        """Nothing to check: a store error is raised by the call that meets it."""

    def use_store_here(self) -> None:
        """The store is this process's already."""

    def abort(self) -> None:
        """End the run this tracker started (if it is still active) as FAILED."""
        self._results.clear()
        if self._run_id is not None:
            end_calibration_run("FAILED", self._run_id)


#: The calls a tracker makes on request, by name.
TRACKING_CALLS: dict[str, Callable[..., Any]] = {
    f.__name__: f
    for f in (
        start_calibration_run,
        log_calibration,
        log_artifacts,
        end_calibration_run,
        start_diagnosis_run,
        log_run,
    )
}


class Tracker(Protocol):
    """What :func:`femcal.jobs.calibrate.run_calibration` and
    :func:`femcal.jobs.diagnose.run_diagnosis` ask of a tracker: the calls of
    :data:`TRACKING_CALLS` submitted in order, their results in that order."""

    def submit(self, fn: Callable[..., Any], /, **kwargs: Any) -> None: ...

    def result(self) -> Any: ...

    def call(self, fn: Callable[..., Any], /, **kwargs: Any) -> Any: ...

    def check(self) -> None: ...

    def use_store_here(self) -> None: ...

    def abort(self) -> None: ...
