"""Train the surrogate under an Optuna study, every trial an MLflow run, and register the winner.

The Optuna study lives in an RDB storage (a SQLite file by default, any SQLAlchemy URL for a
shared database), so several workers can join one study and a killed study resumes: trials
already complete are not run again, and trials left running by a killed worker are failed by
the heartbeat and retried.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytorch_lightning as pl

from femcal.errors import ConfigError
from femcal.schema import STATUS_OK
from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

_SUGGEST_TYPES = ("float", "int", "categorical")


@dataclass
class TrainResult:
    """What :func:`train_surrogate` produced.

    Attributes
    ----------
    surrogate : NeuralSurrogate
        The final fitted model (an ensemble when ``n_members > 1``).
    best_params : dict
        Hyper-parameters of the final model (fixed ones merged with the best trial's).
    val_mae_deg : float
        The final model's MAE on the validation configurations, in degrees.
    n_trials : int
        Complete trials in the study after this call.
    run_id : str
        The MLflow run of this training.
    model_uri : str or None
        The logged MLflow model.
    version : str or None
        The registered model version (None when not registered).
    promoted : bool
        Whether the champion alias moved to ``version``.
    """

    surrogate: Any
    best_params: dict
    val_mae_deg: float
    n_trials: int
    run_id: str
    model_uri: str | None = None
    version: str | None = None
    promoted: bool = False
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)


def suggest(trial: Any, search_space: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Draw one value per entry of ``search_space`` from an Optuna trial.

    Parameters
    ----------
    trial : optuna.Trial
    search_space : mapping
        ``{name: {"type": "float"|"int"|"categorical", "low":…, "high":…, "log": bool,
        "choices": [...]}}``, as written in params.yaml.
    """
    out: dict[str, Any] = {}
    for name, spec in search_space.items():
        kind = spec.get("type")
        if kind not in _SUGGEST_TYPES:
            raise ConfigError(
                f"params.yaml train.search_space.{name}.type is {kind!r}; use one of "
                f"{', '.join(_SUGGEST_TYPES)}."
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


def surrogate_kwargs(params: Mapping[str, Any]) -> dict[str, Any]:
    """Turn flat hyper-parameters (``width``, ``depth``) into NeuralSurrogate keywords."""
    kw = dict(params)
    if "width" in kw or "depth" in kw:
        width = int(kw.pop("width", 256))
        depth = int(kw.pop("depth", 4))
        kw["hidden"] = tuple([width] * depth)
    if "hidden" in kw:
        kw["hidden"] = tuple(int(h) for h in kw["hidden"])
    return kw


def ok_rows(table: pd.DataFrame) -> pd.DataFrame:
    """Rows of a tidy table whose simulation succeeded (failed ones are kept in the data, not
    trained on)."""
    n_failed = int((table["status"] != STATUS_OK).sum())
    if n_failed:
        logger.info("Leaving %d failed simulation rows out of training.", n_failed)
    return table[table["status"] == STATUS_OK].reset_index(drop=True)


def validation_split(
    table: pd.DataFrame, *, fraction: float, seed: int
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Split a tidy table by configuration: (train rows, validation rows)."""
    if not 0.0 < fraction < 1.0:
        raise ConfigError(f"Validation fraction must lie in (0, 1); got {fraction}.")
    configs = np.unique(table["config_id"].to_numpy())
    rng = np.random.default_rng(seed)
    n_val = max(1, int(round(fraction * len(configs))))
    val = set(rng.choice(configs, size=n_val, replace=False).tolist())
    is_val = table["config_id"].isin(val).to_numpy()
    return table[~is_val].reset_index(drop=True), table[is_val].reset_index(drop=True)


def study_name_for(base: str, *, search_space: Mapping, fixed: Mapping, data_id: str) -> str:
    """A study name that changes when the search space, fixed settings or data change, so a
    resumed study never mixes trials of different problems."""
    blob = json.dumps(
        {"space": search_space, "fixed": fixed, "data": data_id}, sort_keys=True, default=str
    )
    return f"{base}-{hashlib.sha256(blob.encode()).hexdigest()[:10]}"


def table_fingerprint(table: pd.DataFrame) -> str:
    """Short content hash of a tidy table."""
    h = pd.util.hash_pandas_object(table, index=False).to_numpy()
    return hashlib.sha256(h.tobytes()).hexdigest()[:12]


class _OptunaPruning(pl.Callback):
    """Report the validation MAE to Optuna after each epoch and stop hopeless trials."""

    def __init__(self, trial: Any, monitor: str = "val_mae_deg") -> None:
        self.trial = trial
        self.monitor = monitor
        self.pruned = False

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        value = trainer.callback_metrics.get(self.monitor)
        if value is None:
            return
        self.trial.report(float(value), step=trainer.current_epoch)
        if self.trial.should_prune():
            self.pruned = True
            trainer.should_stop = True


def _mlflow_logger(run_id: str, prefix: str = "") -> Any:
    import mlflow
    from pytorch_lightning.loggers import MLFlowLogger

    return MLFlowLogger(tracking_uri=mlflow.get_tracking_uri(), run_id=run_id, prefix=prefix)


def train_surrogate(
    table: pd.DataFrame,
    space: ParameterSpace,
    *,
    search_space: Mapping[str, Mapping[str, Any]],
    fixed: Mapping[str, Any],
    n_trials: int,
    final_members: int,
    storage: str,
    study_name: str,
    seed: int = 0,
    val_fraction: float = 0.15,
    register_as: str | None = None,
    run_name: str = "train",
    progress: bool = False,
    heartbeat_seconds: int = 30,
) -> TrainResult:
    """Search hyper-parameters with Optuna, fit the final ensemble, log and register it.

    Parameters
    ----------
    table : DataFrame
        Tidy training table (see :mod:`femcal.prepare`); failed rows are left out.
    space : ParameterSpace
        The parameter box.
    search_space : mapping
        Optuna search space (see :func:`suggest`).
    fixed : mapping
        Fixed NeuralSurrogate keywords (``width``/``depth`` allowed), overridden by the search.
    n_trials : int
        Complete trials the study should hold; a resumed study only runs the missing ones.
        0 trains the final model on ``fixed`` alone.
    final_members : int
        Ensemble members of the final model.
    storage : str
        Optuna RDB storage URL (``sqlite:///…`` or any SQLAlchemy URL).
    study_name : str
        Base name of the study; a hash of the problem is appended (:func:`study_name_for`).
    seed : int
        Seeds the sampler, the validation split and every member.
    register_as : str or None
        Registered model name; the champion alias moves only on a better validation MAE.
    heartbeat_seconds : int
        Trials send a heartbeat this often; a trial silent for three periods (its worker was
        killed) is marked failed and retried by the next worker.

    Returns
    -------
    TrainResult
    """
    import mlflow
    import optuna

    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.tracking import log_surrogate, register_and_promote

    t0 = time.perf_counter()
    if n_trials < 0 or final_members < 1:
        raise ConfigError(
            f"n_trials must be >= 0 and final_members >= 1; got {n_trials} and {final_members}."
        )
    data = ok_rows(table)
    train_df, val_df = validation_split(data, fraction=val_fraction, seed=seed)
    feature_cols = ["config_id", "load_case", "moment_nm", *space.names]
    X_tr, y_tr = train_df[feature_cols], train_df["rom_deg"].to_numpy()
    X_va, y_va = val_df[feature_cols], val_df["rom_deg"].to_numpy()
    full_name = study_name_for(
        study_name, search_space=search_space, fixed=fixed, data_id=table_fingerprint(table)
    )

    with mlflow.start_run(run_name=run_name) as parent:
        mlflow.log_params(
            {
                "n_trials": n_trials,
                "final_members": final_members,
                "seed": seed,
                "val_fraction": val_fraction,
                "n_train_configs": train_df["config_id"].nunique(),
                "n_val_configs": val_df["config_id"].nunique(),
                "optuna_study": full_name,
            }
        )
        mlflow.set_tag("femcal.stage", "train")

        best_params: dict[str, Any] = dict(fixed)
        n_complete = 0
        if n_trials > 0:
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
            study = optuna.create_study(
                study_name=full_name,
                storage=rdb,
                load_if_exists=True,
                direction="minimize",
                sampler=optuna.samplers.TPESampler(seed=seed),
                pruner=optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=20),
            )

            def objective(trial: optuna.Trial) -> float:
                hp = {**fixed, **suggest(trial, search_space)}
                with mlflow.start_run(run_name=f"trial-{trial.number}", nested=True) as run:
                    mlflow.log_params({**hp, "trial": trial.number, "optuna_study": full_name})
                    pruning = _OptunaPruning(trial)
                    model = NeuralSurrogate(
                        space, **surrogate_kwargs(hp), n_members=1, seed=seed + trial.number
                    )
                    model.fit(
                        X_tr,
                        y_tr,
                        X_val=X_va,
                        y_val=y_va,
                        logger=_mlflow_logger(run.info.run_id),
                        callbacks=[pruning],
                    )
                    value = float(model.best_val_mae_deg_)
                    mlflow.log_metric("best_val_mae_deg", value)
                    if pruning.pruned:
                        mlflow.set_tag("optuna.state", "PRUNED")
                        raise optuna.TrialPruned()
                    mlflow.set_tag("optuna.state", "COMPLETE")
                return value

            if not study.trials:
                start = _fixed_as_trial(fixed, search_space)
                if start:
                    study.enqueue_trial(start)  # the known recipe is trial 0
            done = _n_complete(study)
            if done < n_trials:
                logger.info("Optuna study %s: %d of %d trials done", full_name, done, n_trials)
                study.optimize(
                    objective,
                    callbacks=[
                        optuna.study.MaxTrialsCallback(
                            n_trials, states=(optuna.trial.TrialState.COMPLETE,)
                        )
                    ],
                    n_trials=n_trials - done + 4,  # headroom for pruned/failed trials
                    show_progress_bar=progress,
                )
            n_complete = _n_complete(study)
            best_params.update(study.best_trial.params)
            mlflow.log_metric("best_trial_val_mae_deg", float(study.best_value))

        final_kw = surrogate_kwargs(best_params)
        mlflow.log_params({f"final.{k}": v for k, v in best_params.items()})
        model = NeuralSurrogate(space, **final_kw, n_members=final_members, seed=seed)
        model.fit(X_tr, y_tr, X_val=X_va, y_val=y_va, progress=progress)
        for row in model.history_:
            step = int(row["epoch"])
            member = int(row.get("member", 0))
            for key in ("train_loss", "val_loss", "val_mae_deg"):
                if key in row and row[key] is not None and np.isfinite(row[key]):
                    mlflow.log_metric(f"final.member{member}.{key}", float(row[key]), step=step)
        val_mae = float(np.mean(np.abs(model.predict(X_va) - y_va)))
        mlflow.log_metric("val_mae_deg", val_mae)

        info = log_surrogate(model, space)
        version, promoted = None, False
        if register_as:
            version, promoted = register_and_promote(
                info.model_uri,
                name=register_as,
                val_metric=val_mae,
                tags={"optuna_study": full_name, "train_run_id": parent.info.run_id},
            )
            mlflow.set_tags({"registered_version": version, "promoted": str(promoted)})
        seconds = time.perf_counter() - t0
        mlflow.log_metric("train_seconds", seconds)
        return TrainResult(
            surrogate=model,
            best_params=best_params,
            val_mae_deg=val_mae,
            n_trials=n_complete,
            run_id=parent.info.run_id,
            model_uri=info.model_uri,
            version=version,
            promoted=promoted,
            seconds=seconds,
        )


def _fixed_as_trial(
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


def _n_complete(study: Any) -> int:
    import optuna

    return len(study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)))


def write_summary(result: TrainResult, path: str | Path) -> None:
    """Write the training summary (DVC metrics file)."""
    summary = {
        "val_mae_deg": result.val_mae_deg,
        "n_trials": result.n_trials,
        "seconds": round(result.seconds, 1),
        "mlflow_run_id": result.run_id,
        "registered_version": result.version,
        "promoted": result.promoted,
        "best_params": {k: v for k, v in result.best_params.items()},
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(summary, indent=2, default=str) + "\n")
