"""The stores of the tracked stages: MLflow's, which they log to and export model folders
from, and the training stages' Optuna search in ``train.storage``.

Only the stages whose DVC deps hold :mod:`femcal.training` import it
(tests/stages/test_stage_deps.py); the others read their settings through
:mod:`femcal.stages.common`.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from femcal.paths import store_path
from femcal.stages.common import optuna_storage, typed
from femcal.training.search import StudySearch


def tracking(params: Mapping[str, Any]) -> None:
    """Point MLflow at the store; tag this process's runs; close runs of killed processes.

    ``mlflow.store_dir`` is relative to the repository's root (:func:`femcal.paths.store_path`).
    """
    from femcal.tracking import configure_tracking, ensure_experiment
    from femcal.tracking_runs import close_killed_runs, tag_runs_with_process

    mlflow = typed(params, "mlflow", "store_dir", "experiment")
    store = store_path(params, mlflow.store_dir)
    configure_tracking(store_dir=store)
    experiment = ensure_experiment(mlflow.experiment, store_dir=store)
    tag_runs_with_process()  # pid + host on every run this command starts
    close_killed_runs([experiment])  # logs each run it closes as KILLED


def registry_figures(result: Any) -> dict[str, Any]:
    """What a training stage reports of a training ``result`` besides its errors.

    Parameters
    ----------
    result : TrainResult or InverseTrainResult
        A training's outcome (:func:`femcal.train.train_surrogate`,
        :func:`femcal.inverse.train.train_inverse`).

    Returns
    -------
    dict
        ``n_trials`` (complete Optuna trials), ``seconds`` (wall time), ``version`` (the
        registered version, None when not registered) and ``promoted`` (the champion alias
        moved to it).
    """
    return {
        "n_trials": result.n_trials,
        "seconds": result.seconds,
        "version": result.version,
        "promoted": result.promoted,
    }


def export_folder(result, out_dir: Path, registered_model: str | None) -> None:
    """The logged MLflow model of a training ``result`` (``model_uri``, ``run_id``, ``version``,
    ``promoted``) exported to ``out_dir``, which appears complete or not at all."""
    import mlflow

    from femcal.tracking import export_model

    tmp = out_dir.with_name(out_dir.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    export_model(
        result.model_uri,
        tmp,
        record={
            "registered_model": registered_model,
            "version": result.version,
            "promoted": result.promoted,
        },
        run={
            "tracking_uri": mlflow.get_tracking_uri(),
            "run_id": result.run_id,
            "model_uri": result.model_uri,
        },
    )
    if out_dir.exists():
        shutil.rmtree(out_dir)
    tmp.rename(out_dir)


def study_search(
    params: Mapping[str, Any],
    args: Mapping[str, Any],
    cfg: Any,
    *,
    study_name: str,
    seed: int,
) -> StudySearch:
    """A training stage's Optuna search, read once from params.yaml and the command line.

    Parameters
    ----------
    params : mapping
        The parsed params.yaml; the storage is ``train.storage`` (:func:`optuna_storage`).
    args : mapping
        The command line's settings: ``progress``.
    cfg : TrainSplitSettings or InverseSettings
        The stage's typed section: ``search_space``, ``fixed``, ``n_trials``.
    study_name, seed
        The study's base name and seed.

    Returns
    -------
    StudySearch
    """
    return StudySearch(
        study_name=study_name,
        search_space=dict(cfg.search_space),
        fixed=dict(cfg.fixed),
        n_trials=cfg.n_trials,
        storage=optuna_storage(params),
        seed=seed,
        progress=bool(args.get("progress")),
    )
