"""Train the surrogate under an Optuna study, every trial an MLflow run, and register the winner.

The Optuna study lives in an RDB storage (a SQLite file by default, any SQLAlchemy URL for a
shared database), so several workers can join one study and a killed study resumes: trials
already complete are not run again, and trials left running by a killed worker are failed by
the heartbeat and retried.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Unpack

import numpy as np
import pandas as pd

from femcal.datasets import ok_rows
from femcal.errors import ConfigError
from femcal.schema import TARGETS
from femcal.space import ParameterSpace
from femcal.training.final import log_history, register_final, training_run
from femcal.training.search import StudyKeywords, StudySearch
from femcal.training.study import TrialRun, hidden_from_width_depth

logger = logging.getLogger(__name__)


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
        The final model's MAE on the validation configurations, in the target's unit (degrees
        for the RoM; MPa for ``target="idp_mpa"``: :attr:`val_metric` names it).
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
    target : str
        The output predicted (:data:`femcal.schema.TARGETS`).
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
    target: str = "rom_deg"

    @property
    def val_metric(self) -> str:
        """The validation error's name with its unit: ``val_mae_deg`` or ``val_mae_mpa``."""
        return f"val_mae_{TARGETS[self.target]}"


def surrogate_kwargs(params: Mapping[str, Any]) -> dict[str, Any]:
    """Turn flat hyper-parameters (``width``, ``depth``) into NeuralSurrogate keywords."""
    return hidden_from_width_depth(params, width=256, depth=4)


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


def table_fingerprint(table: pd.DataFrame) -> str:
    """Short content hash of a tidy table."""
    h = pd.util.hash_pandas_object(table, index=False).to_numpy()
    return hashlib.sha256(h.tobytes()).hexdigest()[:12]


def _checked_rows(
    table: pd.DataFrame, target: str, search: StudySearch, final_members: int
) -> pd.DataFrame:
    """The rows of ``table`` that :func:`train_surrogate` learns ``target`` from: those that
    did not fail and, for a target other than ``rom_deg``, where it is finite.

    Raises
    ------
    ConfigError
        On a negative ``n_trials``, ``final_members < 1``, an unknown ``target``, a table
        without the target's column, or ``idp_mpa`` with a log target (fixed or searched).
    """
    if search.n_trials < 0 or final_members < 1:
        raise ConfigError(
            f"n_trials must be >= 0 and final_members >= 1; got {search.n_trials} and "
            f"{final_members}."
        )
    if target not in TARGETS:
        raise ConfigError(
            f"train: target {target!r} is not an output a surrogate can learn; use one of "
            f"{sorted(TARGETS)}."
        )
    data = ok_rows(table)
    if target != "rom_deg":
        if target not in data.columns:
            raise ConfigError(
                f"train: the table has no column {target!r} to learn; an FE campaign's prepared "
                "split has it (femcal simulate, then femcal prepare)."
            )
        data = data[np.isfinite(data[target].to_numpy(dtype=float))].reset_index(drop=True)
    searched = "log_target" in search.search_space
    if target == "idp_mpa" and (search.fixed.get("log_target", True) or searched):
        raise ConfigError(
            "train: target 'idp_mpa' needs fixed log_target: false (a nucleus pressure under a "
            f"pure moment can be <= 0); got fixed log_target={search.fixed.get('log_target')!r}"
            f"{' and log_target in the search space' if searched else ''}. Set it in the "
            "train section's fixed keywords."
        )
    return data


def train_surrogate(
    table: pd.DataFrame,
    space: ParameterSpace,
    *,
    final_members: int,
    val_fraction: float = 0.15,
    register_as: str | None = None,
    run_name: str = "train",
    target: str = "rom_deg",
    heldout: pd.DataFrame | None = None,
    **study: Unpack[StudyKeywords],
) -> TrainResult:
    """Search hyper-parameters with Optuna, fit the final ensemble, log and register it.

    Parameters
    ----------
    table : DataFrame
        Tidy training table (see :mod:`femcal.prepare`); failed rows are left out.
    space : ParameterSpace
        The parameter box.
    final_members : int
        Ensemble members of the final model.
    val_fraction : float
        Fraction of the configurations held out for validation and early stopping.
    register_as : str or None
        Registered model name; the champion alias moves only on a better validation MAE.
    run_name : str
        Name of the parent MLflow run.
    target : {"rom_deg", "idp_mpa"}
        The output predicted (:data:`femcal.schema.TARGETS`): the RoM, or an FE campaign's
        intradiscal pressure (linear: it can be negative under a pure moment); rows without it
        are left out. The error's name carries its unit (:attr:`TrainResult.val_metric`).
    heldout : DataFrame, optional
        Rows of configurations never trained on, drawn like the specimens: their errors become
        the stated error (the sd calibrate and diagnose count; ``heldout_<metric>`` in MLflow)
        instead of the validation rows'. Promotion still compares validation errors.
    **study
        The Optuna search (:class:`~femcal.training.search.StudySearch`): ``study_name``
        (required; a hash of the problem is appended), ``search_space``, ``fixed`` (fixed
        NeuralSurrogate keywords, ``width``/``depth`` allowed, overridden by the search),
        ``n_trials``, ``storage``, ``seed`` (also seeds the validation split and every
        member), ``heartbeat_seconds`` and ``progress``.

    Returns
    -------
    TrainResult
    """
    import mlflow

    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.tracking import log_surrogate

    search = StudySearch(**study)
    seed = search.seed
    t0 = time.perf_counter()
    data = _checked_rows(table, target, search, final_members)
    metric = f"val_mae_{TARGETS[target]}"
    train_df, val_df = validation_split(data, fraction=val_fraction, seed=seed)
    feature_cols = ["config_id", "load_case", "moment_nm", *space.names]
    X_tr, y_tr = train_df[feature_cols], train_df[target].to_numpy(dtype=float)
    X_va, y_va = val_df[feature_cols], val_df[target].to_numpy(dtype=float)
    full_name = search.named(table_fingerprint(table))

    params = {
        "n_trials": search.n_trials,
        "final_members": final_members,
        "seed": seed,
        "val_fraction": val_fraction,
        "n_train_configs": train_df["config_id"].nunique(),
        "n_val_configs": val_df["config_id"].nunique(),
        "optuna_study": full_name,
        "target": target,
    }
    with training_run(run_name, "train", params) as parent:

        def train_trial(trial: TrialRun) -> float:
            model = NeuralSurrogate(
                space, **surrogate_kwargs(trial.params), n_members=1, seed=seed + trial.number
            )
            model.fit(
                X_tr, y_tr, X_val=X_va, y_val=y_va, logger=trial.logger, callbacks=trial.callbacks
            )
            # the estimator's ``best_val_mae_deg_``: its MAE in the target's own unit
            value = float(model.best_val_mae_deg_)
            mlflow.log_metric(f"best_{metric}", value)
            return value

        best_params, n_complete = search.run(
            train_trial, name=full_name, metric="val_mae_deg", monitor="val_mae_deg"
        )

        final_kw = surrogate_kwargs(best_params)
        mlflow.log_params({f"final.{k}": v for k, v in best_params.items()})
        model = NeuralSurrogate(space, **final_kw, n_members=final_members, seed=seed)
        model.fit(X_tr, y_tr, X_val=X_va, y_val=y_va, progress=search.progress)
        history = [{**row, metric: row.get("val_mae_deg")} for row in model.history_]
        log_history(history, ("train_loss", "val_loss", metric), by_member=True)
        val_mae = float(np.mean(np.abs(model.predict(X_va) - y_va)))
        mlflow.log_metric(metric, val_mae)
        _state_heldout_error(model, heldout, target, metric)

        info = log_surrogate(model, space)
        registered = register_final(
            info.model_uri,
            register_as,
            val_metric=val_mae,
            study=full_name,
            run_id=parent.info.run_id,
            started=t0,
        )
        return TrainResult(
            surrogate=model,
            best_params=best_params,
            val_mae_deg=val_mae,
            n_trials=n_complete,
            target=target,
            run_id=parent.info.run_id,
            model_uri=info.model_uri,
            **registered._asdict(),
        )


def _state_heldout_error(
    model: Any, heldout: pd.DataFrame | None, target: str, metric: str
) -> None:
    """Record ``heldout``'s errors as ``model``'s stated error and log their MAE to the active
    MLflow run as ``heldout_<metric>`` (nothing when ``heldout`` is None)."""
    if heldout is None:
        return
    import mlflow

    rows = heldout[np.isfinite(pd.to_numeric(heldout[target], errors="coerce"))]
    if rows.empty:
        raise ConfigError(
            f"The held-out table for the stated error has no finite {target}; give a split "
            "of configurations the surrogate never saw (train.<split>.stated_error_split)."
        )
    pred = np.asarray(model.predict(rows), dtype=float)
    error = pred - rows[target].to_numpy(dtype=float)
    model.record_validation_error(rows["moment_nm"].to_numpy(dtype=float), error, pred)
    mlflow.log_metric(f"heldout_{metric}", float(np.mean(np.abs(error))))


def write_summary(result: TrainResult, path: str | Path) -> None:
    """Write the training's DVC metrics file ``path`` (its headline on the shared vocabulary,
    :mod:`femcal.dvc_metrics`) and every figure beside it (``<name>.details.json``: the
    validation error, trials, time, MLflow run, version, promotion and best parameters)."""
    from femcal.dvc_metrics import write

    summary = {
        result.val_metric: result.val_mae_deg,
        "n_trials": result.n_trials,
        "seconds": round(result.seconds, 1),
        "mlflow_run_id": result.run_id,
        "registered_version": result.version,
        "promoted": result.promoted,
        "best_params": {k: v for k, v in result.best_params.items()},
    }
    write(path, "train", summary, details=True)
