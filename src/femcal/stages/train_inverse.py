"""Stage ``train-inverse``: the study's inverse network on samples of the surrogate, under Optuna.

Registered as ``inverse.register_as``; ``models/inverse`` is the logged MLflow model.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.dvc_metrics import write as write_dvc_metrics
from femcal.paths import setting_path, setting_uri
from femcal.stages.common import StageSettings, typed
from femcal.stages.store import export_folder, registry_figures, study_search, tracking
from femcal.training.search import StudySearch


@dataclass(frozen=True)
class TrainInverseSettings(StageSettings):
    """The ``inverse`` section of params.yaml."""

    surrogate_uri: str
    moments: Sequence[float]
    out_dir: Path
    metrics_path: Path
    study: StudySearch
    n_samples: int
    register_as: str | None

    @classmethod
    def from_params(
        cls, params: Mapping[str, Any], args: Mapping[str, Any]
    ) -> TrainInverseSettings:
        cfg = typed(params, "inverse")
        return cls(
            surrogate_uri=setting_uri(params, cfg.surrogate_uri),
            moments=list(cfg.moments),
            out_dir=setting_path(params, "models/inverse"),
            metrics_path=setting_path(params, "reports/train-inverse.json"),
            study=study_search(
                params,
                args,
                cfg,
                study_name=cfg.study_name,
                seed=cfg.seed,
            ),
            n_samples=cfg.n_samples,
            register_as=cfg.register_as,
            params=params,
        )


def run(settings: TrainInverseSettings) -> dict[str, Any]:
    """Train, register and export; returns the validation errors, trials and seconds."""
    tracking(settings.params)
    result = run_train_inverse(**settings.call_args())
    return {
        "val_mae": result.val_mae,
        "val_rom_mae_deg": result.val_rom_mae_deg,
        **registry_figures(result),
    }


def describe(figures: Mapping[str, Any]) -> list[str]:
    reg = f"; registered as version {figures['version']}" if figures["version"] else ""
    return [
        f"inverse model: validation MAE {figures['val_mae']:.4f} (unit box), "
        f"{figures['val_rom_mae_deg']:.4f} deg through the surrogate, {figures['n_trials']} "
        f"trials in {figures['seconds']:.0f} s{reg}"
    ]


def run_train_inverse(
    *,
    surrogate_uri: str,
    moments: Sequence[float],
    out_dir: Path,
    metrics_path: Path,
    study: StudySearch,
    n_samples: int,
    register_as: str | None,
):
    """Train the study's inverse network on samples of the surrogate; register it.

    ``surrogate_uri`` is a model folder (``models/surrogate-large``) or an MLflow model URI;
    the training run's tags ``femcal.surrogate.*`` name it (URI, SHA-256, registered
    version). ``study`` is the Optuna search of ``n_samples`` surrogate samples. ``out_dir``
    receives the logged MLflow model file for file, as for :func:`run_train`.
    """
    import mlflow

    from femcal.calibration import SurrogateCurveModel
    from femcal.inverse import train_inverse
    from femcal.tracking import load_surrogate, open_model

    source = open_model(surrogate_uri)
    surrogate = load_surrogate(source)
    result = train_inverse(
        SurrogateCurveModel(surrogate, moments),
        n_samples=n_samples,
        register_as=register_as,
        run_name="train-inverse",
        **study.keywords(),
    )
    client = mlflow.MlflowClient()
    for key, value in source.tags("surrogate").items():
        client.set_tag(result.run_id, key, value)
    export_folder(result, out_dir, register_as)
    write_dvc_metrics(
        metrics_path,
        "train",
        {
            "val_mae_unit": result.val_mae,
            "val_rom_mae_deg": result.val_rom_mae_deg,
            "n_trials": result.n_trials,
            "seconds": round(result.seconds, 1),
            "mlflow_run_id": result.run_id,
            "registered_version": result.version,
            "promoted": result.promoted,
            "surrogate_uri": surrogate_uri,
            "surrogate_sha256": source.sha256,
            "surrogate_version": source.version,
            "best_params": result.best_params,
        },
        details=True,
    )  # the headline; every figure in train-inverse.details.json
    return result
