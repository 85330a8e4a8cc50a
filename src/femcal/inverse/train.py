"""Train the inverse model: samples from the surrogate, an Optuna study, MLflow, the registry.

The study is :func:`femcal.training.study.run_study` (the surrogate's too): an RDB storage with
heartbeats, the fixed recipe as trial 0, every trial a nested MLflow run; the final model is
logged as an MLflow pyfunc (:func:`femcal.inverse.store.log_inverse`) and registered.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Unpack

import numpy as np

from femcal.errors import ConfigError
from femcal.inverse.data import make_inverse_dataset, rom_mae_deg, surrogate_fingerprint
from femcal.inverse.model import INVERSE_SETTINGS, InverseModel
from femcal.training.final import log_history, register_final, training_run
from femcal.training.search import StudyKeywords, StudySearch
from femcal.training.study import TrialRun, hidden_from_width_depth

if TYPE_CHECKING:
    from femcal.calibration.model import CurveModel


@dataclass
class InverseTrainResult:
    """What :func:`train_inverse` produced.

    Attributes
    ----------
    model : InverseModel
        The final fitted model.
    best_params : dict
        Its settings (fixed ones merged with the best trial's).
    val_mae : float
        Validation MAE in the unit box.
    run_id : str
        The MLflow run of this training.
    model_uri : str or None
        The logged MLflow pyfunc model.
    version : str or None
        The registered model version (None when not registered).
    promoted : bool
        Whether the champion alias moved to ``version``.
    seconds : float
        Wall time of the whole call.
    val_rom_mae_deg : float
        Validation MAE in degrees of the curves re-evaluated through the surrogate at the
        predicted parameters (the Optuna objective and the promotion metric).
    n_trials : int
        Complete trials in the study after this call.
    extra : dict
        Anything else (study name, sample count).
    """

    model: InverseModel
    best_params: dict
    val_mae: float
    run_id: str
    model_uri: str | None = None
    version: str | None = None
    promoted: bool = False
    seconds: float = 0.0
    val_rom_mae_deg: float = math.nan
    n_trials: int = 0
    extra: dict = field(default_factory=dict)


def inverse_kwargs(params: Mapping[str, Any]) -> dict[str, Any]:
    """Flat hyper-parameters (``width``/``depth`` allowed) -> :class:`InverseModel` keywords."""
    kw = hidden_from_width_depth(params, width=256, depth=5)
    allowed = set(INVERSE_SETTINGS) - {"seed"}
    unknown = sorted(set(kw) - allowed)
    if unknown:
        raise ConfigError(
            f"Unknown inverse-model settings {unknown}; use width/depth or {sorted(allowed)} "
            "(the seed comes from train_inverse's seed)."
        )
    return kw


def _check_arguments(search: StudySearch, n_samples: int, val_fraction: float) -> None:
    """Refuse the arguments of :func:`train_inverse` before any sampling: a negative
    ``n_trials``, a search without storage, ``val_fraction`` outside (0, 1), fewer than 10
    samples, or an unknown setting in ``fixed``.

    Raises
    ------
    ConfigError
    """
    if search.n_trials < 0:
        raise ConfigError(f"n_trials must be >= 0; got {search.n_trials}.")
    if search.n_trials > 0 and not search.storage:
        raise ConfigError("An Optuna search (n_trials > 0) needs an RDB storage URL (sqlite:///…).")
    if not 0.0 < val_fraction < 1.0:
        raise ConfigError(f"val_fraction must lie in (0, 1); got {val_fraction}.")
    if int(n_samples) < 10:
        raise ConfigError(f"n_samples must be >= 10; got {n_samples}.")
    inverse_kwargs(search.fixed)  # fail early on unknown settings


def train_inverse(
    curve_model: CurveModel,
    *,
    n_samples: int = 50_000,
    val_fraction: float = 0.1,
    sampling: str = "lhs",
    register_as: str | None = None,
    run_name: str = "train-inverse",
    **study: Unpack[StudyKeywords],
) -> InverseTrainResult:
    """Sample a training set from the surrogate, search settings with Optuna, fit, log, register.

    Parameters
    ----------
    curve_model : CurveModel
        The surrogate on the moment grid the inverse model will accept (the study: 1..5 Nm).
    n_samples : int
        Configurations sampled in the unit box (the study: 50,000).
    val_fraction : float
        Fraction of the samples held out for validation and early stopping.
    sampling : {"lhs", "uniform"}
        How the configurations are drawn.
    register_as : str, optional
        Registered model name (e.g. "ivd-inverse"); the champion alias moves only on a better
        validation MAE in degrees.
    run_name : str
        Name of the parent MLflow run (in the active experiment).
    **study
        The Optuna search (:class:`~femcal.training.search.StudySearch`) over
        :class:`InverseModel` settings (``width``/``depth`` allowed): ``study_name`` (default
        "inverse"; a hash of the problem, surrogate, grid and samples included, is appended),
        ``search_space``, ``fixed``, ``n_trials`` (default 0: the final model on ``fixed``
        alone), ``storage`` (needed when ``n_trials > 0``), ``seed`` (also seeds the samples,
        the validation split and every fit), ``heartbeat_seconds`` and ``progress``.

    Returns
    -------
    InverseTrainResult
    """
    import mlflow

    from femcal.inverse.store import log_inverse

    search = StudySearch(**{"study_name": "inverse", **study})
    seed = search.seed
    t0 = time.perf_counter()
    _check_arguments(search, n_samples, val_fraction)

    rng = np.random.default_rng(seed)
    rom, unit = make_inverse_dataset(curve_model, n_samples, rng, sampling=sampling)
    perm = rng.permutation(rom.shape[0])
    n_val = max(1, int(round(val_fraction * rom.shape[0])))
    X_va, U_va = rom[perm[:n_val]], unit[perm[:n_val]]
    X_tr, U_tr = rom[perm[n_val:]], unit[perm[n_val:]]
    moments = curve_model.moments.double().numpy()
    space = curve_model.space
    data_id = f"{surrogate_fingerprint(curve_model)}-{n_samples}-{seed}-{sampling}-{val_fraction}"
    full_name = search.named(data_id)

    def fit(params: Mapping[str, Any], fit_seed: int, **kw: Any) -> InverseModel:
        model = InverseModel(space, **inverse_kwargs(params), seed=fit_seed)
        return model.fit(X_tr, U_tr, moments=moments, X_val=X_va, U_val=U_va, **kw)

    params = {
        "n_trials": search.n_trials,
        "n_samples": n_samples,
        "sampling": sampling,
        "seed": seed,
        "val_fraction": val_fraction,
        "n_train": X_tr.shape[0],
        "n_val": X_va.shape[0],
        "moments": json.dumps(moments.tolist()),
        "optuna_study": full_name,
    }
    with training_run(run_name, "train-inverse", params) as parent:
        mlflow.log_metric("dataset_seconds", time.perf_counter() - t0)

        def train_trial(trial: TrialRun) -> float:
            model = fit(
                trial.params, seed + trial.number, logger=trial.logger, callbacks=trial.callbacks
            )
            value = rom_mae_deg(model, curve_model, X_va)
            mlflow.log_metrics({"best_val_mae": model.best_val_mae_, "val_rom_mae_deg": value})
            return value

        best_params, n_complete = search.run(
            train_trial, name=full_name, metric="val_rom_mae_deg", monitor="val_mae"
        )

        mlflow.log_params({f"final.{k}": v for k, v in best_params.items()})
        model = fit(best_params, seed, progress=search.progress)
        log_history(model.history_, ("train_loss", "val_mae", "lr"))
        val_mae = float(model.best_val_mae_)
        val_rom = rom_mae_deg(model, curve_model, X_va)
        mlflow.log_metrics({"val_mae": val_mae, "val_rom_mae_deg": val_rom})

        with tempfile.TemporaryDirectory() as tmp:
            model.save(Path(tmp) / "inverse_model")
            mlflow.log_artifacts(str(Path(tmp) / "inverse_model"), artifact_path="inverse_model")
        info = log_inverse(model)
        registered = register_final(
            info.model_uri,
            register_as,
            val_metric=val_rom,
            study=full_name,
            run_id=parent.info.run_id,
            started=t0,
            tags={"val_mae_unit": repr(val_mae)},
        )
        return InverseTrainResult(
            model=model,
            best_params=best_params,
            val_mae=val_mae,
            val_rom_mae_deg=val_rom,
            n_trials=n_complete,
            extra={"optuna_study": full_name, "n_samples": int(n_samples)},
            run_id=parent.info.run_id,
            model_uri=info.model_uri,
            **registered._asdict(),
        )
