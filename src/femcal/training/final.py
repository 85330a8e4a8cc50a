"""The parent MLflow run of a training and its final model: logged, registered, timed.

The surrogate (:func:`femcal.train.train_surrogate`) and the inverse model
(:func:`femcal.inverse.train.train_inverse`) train alike: a parent run holds the Optuna study
(:func:`femcal.training.study.search_settings`), then the final model is fitted, its per-epoch
history logged, the model logged and registered, and the wall time logged. The data, the
models and their metrics differ; these steps are shared.

MLflow is imported inside the functions, as everywhere in :mod:`femcal.training`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np


@contextlib.contextmanager
def training_run(run_name: str, stage: str, params: Mapping[str, Any]) -> Iterator[Any]:
    """A parent MLflow run for a training, with its parameters and the ``femcal.stage`` tag.

    Parameters
    ----------
    run_name : str
        The run's name (in the active experiment).
    stage : str
        The pipeline stage, tagged ``femcal.stage``.
    params : mapping
        Logged as the run's parameters.

    Yields
    ------
    mlflow.ActiveRun
        The run; it ends when the block does (FAILED on an exception).
    """
    import mlflow

    with mlflow.start_run(run_name=run_name) as run:
        mlflow.log_params(dict(params))
        mlflow.set_tag("femcal.stage", stage)
        yield run


def log_history(
    history: Sequence[Mapping[str, Any]], keys: Sequence[str], *, by_member: bool = False
) -> None:
    """Log a final fit's per-epoch metrics to the active MLflow run.

    Parameters
    ----------
    history : sequence of mapping
        One row per epoch (and member), with ``epoch`` and metric values.
    keys : sequence of str
        The metrics logged, as ``final.<key>`` at step ``epoch``; a value missing, None or
        not finite is left out.
    by_member : bool
        Log as ``final.member<k>.<key>``, ``k`` being the row's ``member`` (default 0).
    """
    import mlflow

    for row in history:
        step = int(row["epoch"])
        prefix = f"final.member{int(row.get('member', 0))}." if by_member else "final."
        for key in keys:
            value = row.get(key)
            if value is not None and np.isfinite(value):
                mlflow.log_metric(f"{prefix}{key}", float(value), step=step)


class Registration(NamedTuple):
    """What :func:`register_final` did: fields of every training's result.

    Attributes
    ----------
    version : str or None
        The registered version (None when not registered).
    promoted : bool
        Whether the champion alias moved to it.
    seconds : float
        The training's wall time.
    """

    version: str | None
    promoted: bool
    seconds: float


def register_final(
    model_uri: str,
    register_as: str | None,
    *,
    val_metric: float,
    study: str,
    run_id: str,
    started: float,
    tags: Mapping[str, str] | None = None,
) -> Registration:
    """Register the final model logged by the active run; log the training's wall time.

    Parameters
    ----------
    model_uri : str
        The logged model.
    register_as : str or None
        Registered model name; None registers nothing. The champion alias moves only on a
        better ``val_metric`` (:func:`femcal.tracking.register_run_model`).
    val_metric : float
        The validation metric that decides promotion (lower is better).
    study : str
        The Optuna study's full name, tagged ``optuna_study`` on the version.
    run_id : str
        The training's parent run, tagged ``train_run_id`` on the version.
    started : float
        :func:`time.perf_counter` at the training's start; the time since is logged as
        ``train_seconds``.
    tags : mapping, optional
        More tags of the version.

    Returns
    -------
    Registration
        ``(version, promoted, seconds)``: the registered version (None when not registered),
        whether the champion alias moved to it, the training's wall time.
    """
    import mlflow

    from femcal.tracking import register_run_model

    version, promoted = register_run_model(
        model_uri,
        register_as,
        val_metric=val_metric,
        tags={"optuna_study": study, "train_run_id": run_id, **(tags or {})},
    )
    seconds = time.perf_counter() - started
    mlflow.log_metric("train_seconds", seconds)
    return Registration(version, promoted, seconds)
