"""The Optuna study runner shared by every trained model; each trial a nested MLflow run.

The study lives in an RDB storage (a SQLite file by default, any SQLAlchemy URL for a shared
database), so several workers can join one study and a killed study resumes: trials already
complete are not run again, and trials left running by a killed worker are failed by the
heartbeat and retried. The fixed settings that lie inside the search space are enqueued as
trial 0, so the known recipe is always tried.
"""

from __future__ import annotations

import hashlib
import json
import logging
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from femcal.errors import ConfigError
from femcal.training.lightning import OptunaPruning, mlflow_logger

logger = logging.getLogger(__name__)

#: The ``type`` values of a search-space entry.
SUGGEST_TYPES: tuple[str, ...] = ("float", "int", "categorical")
#: Extra trials ``optimize`` may start beyond the missing ones (pruned or failed trials).
TRIAL_HEADROOM = 4


def suggest(trial: Any, search_space: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Draw one value per entry of ``search_space`` from an Optuna trial.

    Parameters
    ----------
    trial : optuna.Trial
    search_space : mapping
        ``{name: {"type": "float"|"int"|"categorical", "low":…, "high":…, "log": bool,
        "choices": [...]}}``, as written in params.yaml.

    Returns
    -------
    dict
        ``{name: value}``, one entry per entry of ``search_space``.
    """
    out: dict[str, Any] = {}
    for name, spec in search_space.items():
        kind = spec.get("type")
        if kind not in SUGGEST_TYPES:
            raise ConfigError(
                f"params.yaml train.search_space.{name}.type is {kind!r}; use one of "
                f"{', '.join(SUGGEST_TYPES)}."
            )
        try:
            if kind == "float":
                out[name] = trial.suggest_float(
                    name, float(spec["low"]), float(spec["high"]), log=bool(spec.get("log", False))
                )
            elif kind == "int":
                out[name] = trial.suggest_int(
                    name, int(spec["low"]), int(spec["high"]), log=bool(spec.get("log", False))
                )
            else:
                out[name] = trial.suggest_categorical(name, list(spec["choices"]))
        except KeyError as exc:
            raise ConfigError(
                f"params.yaml train.search_space.{name} ({kind}) lacks {exc}; floats and ints "
                "need low and high, categoricals need choices."
            ) from None
    return out


def hidden_from_width_depth(
    params: Mapping[str, Any], *, width: int = 256, depth: int
) -> dict[str, Any]:
    """Flat hyper-parameters with ``width``/``depth`` (as a search space has them) as
    ``hidden``, a tuple of ints; the other entries unchanged.

    Parameters
    ----------
    params : mapping
        Settings; ``width`` or ``depth`` alone takes the other from the defaults.
    width, depth : int
        The defaults.

    Returns
    -------
    dict
        ``params`` without ``width``/``depth``, with ``hidden = (width,) * depth`` (or its own
        ``hidden`` as ints).
    """
    kw = dict(params)
    if "width" in kw or "depth" in kw:
        w = int(kw.pop("width", width))
        d = int(kw.pop("depth", depth))
        kw["hidden"] = tuple([w] * d)
    if "hidden" in kw:
        kw["hidden"] = tuple(int(h) for h in kw["hidden"])
    return kw


def study_name_for(base: str, *, search_space: Mapping, fixed: Mapping, data_id: str) -> str:
    """A study name that changes when the search space, fixed settings or data change, so a
    resumed study never mixes trials of different problems."""
    blob = json.dumps(
        {"space": search_space, "fixed": fixed, "data": data_id}, sort_keys=True, default=str
    )
    return f"{base}-{hashlib.sha256(blob.encode()).hexdigest()[:10]}"


def fixed_as_trial(
    fixed: Mapping[str, Any], search_space: Mapping[str, Mapping[str, Any]]
) -> dict[str, Any]:
    """The fixed settings that lie inside the search space, as an Optuna trial to enqueue."""
    start = {}
    for name, spec in search_space.items():
        if name not in fixed:
            continue
        value = fixed[name]
        if spec.get("type") == "categorical":
            if value in list(spec.get("choices", [])):
                start[name] = value
        elif "low" in spec and "high" in spec and spec["low"] <= value <= spec["high"]:
            start[name] = value
    return start


def n_complete(study: Any) -> int:
    """Number of complete trials of an Optuna study."""
    import optuna

    return len(study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)))


def open_study(storage: str, name: str, *, seed: int, heartbeat_seconds: int = 30) -> Any:
    """Create or load the study ``name`` in an RDB storage, minimising, with heartbeats.

    Parameters
    ----------
    storage : str
        Optuna RDB storage URL (``sqlite:///…`` or any SQLAlchemy URL).
    name : str
        The full study name (see :func:`study_name_for`).
    seed : int
        Seeds the TPE sampler.
    heartbeat_seconds : int
        Trials send a heartbeat this often; a trial silent for three periods (its worker was
        killed) is marked failed and retried (twice at most).

    Returns
    -------
    optuna.Study
        TPE sampler, median pruner (3 startup trials, 20 warm-up steps).
    """
    import optuna

    with warnings.catch_warnings():  # heartbeats are 'experimental' in Optuna
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        rdb = optuna.storages.RDBStorage(
            storage,
            heartbeat_interval=heartbeat_seconds,
            grace_period=3 * heartbeat_seconds,
            heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(
                max_retry=2
            ),
        )
    return optuna.create_study(
        study_name=name,
        storage=rdb,
        load_if_exists=True,
        direction="minimize",
        sampler=optuna.samplers.TPESampler(seed=seed),
        pruner=optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=20),
    )


@dataclass
class TrialRun:
    """One trial as the model's training function sees it.

    Attributes
    ----------
    number : int
        The Optuna trial number (seed offsets use it).
    params : dict
        The fixed settings overridden by the trial's suggestions.
    run_id : str
        The trial's nested MLflow run (active while the training function runs).
    logger : Lightning logger
        An MLFlowLogger into that run, for per-epoch metrics.
    callbacks : list of Lightning callbacks
        The pruning callback; pass them to the Trainer.
    """

    number: int
    params: dict[str, Any]
    run_id: str
    logger: Any
    callbacks: list[Any] = field(default_factory=list)


@dataclass
class StudyOutcome:
    """What :func:`run_study` left in the study.

    Attributes
    ----------
    name : str
        The full study name.
    best_params : dict
        The best complete trial's suggested values (without the fixed settings).
    best_value : float
        Its objective.
    n_complete : int
        Complete trials in the study after this call.
    """

    name: str
    best_params: dict[str, Any]
    best_value: float
    n_complete: int


def run_study(
    train_trial: Callable[[TrialRun], float],
    *,
    storage: str,
    study_name: str,
    search_space: Mapping[str, Mapping[str, Any]],
    fixed: Mapping[str, Any],
    n_trials: int,
    seed: int,
    monitor: str,
    heartbeat_seconds: int = 30,
    progress: bool = False,
) -> StudyOutcome:
    """Run (or resume) an Optuna study until it holds ``n_trials`` complete trials.

    Each trial is a nested MLflow run ``trial-<number>`` (in the active run) with its
    settings and the study's name as parameters and its Optuna state as the tag
    ``optuna.state``. The fixed settings inside the search space are enqueued as trial 0
    of a new study.

    Parameters
    ----------
    train_trial : callable
        ``(TrialRun) -> float``: fits a model with ``TrialRun.params`` (passing
        ``TrialRun.logger`` and ``TrialRun.callbacks`` to Lightning) and returns the
        objective to minimise. A trial the pruner stops is reported as pruned.
    storage : str
        Optuna RDB storage URL.
    study_name : str
        The full study name (see :func:`study_name_for`).
    search_space : mapping
        See :func:`suggest`.
    fixed : mapping
        Settings every trial starts from; the suggestions override them.
    n_trials : int
        Complete trials the study should hold (>= 1); a resumed study only runs the missing
        ones (with :data:`TRIAL_HEADROOM` extra starts for pruned or failed trials).
    seed : int
        Seeds the sampler.
    monitor : str
        The logged validation metric the pruner watches.
    heartbeat_seconds : int
        See :func:`open_study`.
    progress : bool
        Optuna's progress bar.

    Returns
    -------
    StudyOutcome
    """
    import mlflow
    import optuna

    if n_trials < 1:
        raise ConfigError(f"An Optuna study needs n_trials >= 1; got {n_trials}.")
    study = open_study(storage, study_name, seed=seed, heartbeat_seconds=heartbeat_seconds)

    def objective(trial: optuna.Trial) -> float:
        hp = {**fixed, **suggest(trial, search_space)}
        with mlflow.start_run(run_name=f"trial-{trial.number}", nested=True) as run:
            mlflow.log_params({**hp, "trial": trial.number, "optuna_study": study_name})
            pruning = OptunaPruning(trial, monitor=monitor)
            value = train_trial(
                TrialRun(
                    number=trial.number,
                    params=hp,
                    run_id=run.info.run_id,
                    logger=mlflow_logger(run.info.run_id),
                    callbacks=[pruning],
                )
            )
            if pruning.pruned:
                mlflow.set_tag("optuna.state", "PRUNED")
                raise optuna.TrialPruned()
            mlflow.set_tag("optuna.state", "COMPLETE")
        return value

    if not study.trials:
        start = fixed_as_trial(fixed, search_space)
        if start:
            study.enqueue_trial(start)  # the known recipe is trial 0
    done = n_complete(study)
    if done < n_trials:
        logger.info("Optuna study %s: %d of %d trials done", study_name, done, n_trials)
        study.optimize(
            objective,
            callbacks=[
                optuna.study.MaxTrialsCallback(n_trials, states=(optuna.trial.TrialState.COMPLETE,))
            ],
            n_trials=n_trials - done + TRIAL_HEADROOM,
            show_progress_bar=progress,
        )
    return StudyOutcome(
        name=study_name,
        best_params=dict(study.best_trial.params),
        best_value=float(study.best_value),
        n_complete=n_complete(study),
    )


def search_settings(
    train_trial: Callable[[TrialRun], float],
    *,
    fixed: Mapping[str, Any],
    n_trials: int,
    metric: str,
    **study: Any,
) -> tuple[dict[str, Any], int]:
    """The fixed settings overridden by the best trial of a study (:func:`run_study`).

    With ``n_trials == 0`` no study runs: the fixed settings are returned as they are. Else
    the best trial's objective is logged to the active MLflow run as ``best_trial_<metric>``.

    Parameters
    ----------
    train_trial : callable
        See :func:`run_study`.
    fixed : mapping
        The settings every trial starts from.
    n_trials : int
        Complete trials the study should hold (>= 0).
    metric : str
        Name of the objective in the logged metric.
    **study
        The other keywords of :func:`run_study` (storage, study_name, search_space, seed,
        monitor, heartbeat_seconds, progress).

    Returns
    -------
    best_params : dict
        ``fixed`` updated by the best trial's values.
    n_complete : int
        Complete trials in the study (0 without a study).
    """
    best_params = dict(fixed)
    if n_trials <= 0:
        return best_params, 0
    import mlflow

    outcome = run_study(train_trial, fixed=fixed, n_trials=n_trials, **study)
    best_params.update(outcome.best_params)
    mlflow.log_metric(f"best_trial_{metric}", outcome.best_value)
    return best_params, outcome.n_complete
