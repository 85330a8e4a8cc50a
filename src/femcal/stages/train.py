"""Stage ``train@<split>``: the surrogate's Optuna search and final ensemble, logged to MLflow.

The model folder (``models/surrogate-<split>``) is the logged MLflow model, file for file; the
summary goes to ``reports/train-<split>.json``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from femcal.config import section
from femcal.datasets import load_split
from femcal.paths import setting_path
from femcal.stages.common import StageSettings, optuna_storage, path_setting
from femcal.stages.store import export_folder, tracking


@dataclass(frozen=True)
class TrainSettings(StageSettings):
    """One ``train.<split>`` section of params.yaml, with the shared train settings."""

    prepared_dir: Path
    split: str
    out_dir: Path
    metrics_path: Path
    settings: Mapping[str, Any]
    storage: str
    study_name: str
    seed: int
    val_fraction: float
    model_name: str | None
    data_split: str | None = None
    progress: bool = False
    params: Mapping[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> TrainSettings:
        split = args["split"]
        settings = section(params, "train", split)
        return cls(
            prepared_dir=path_setting(params, "data", "prepared_dir"),
            split=split,
            out_dir=setting_path(params, f"models/surrogate-{split}"),
            metrics_path=setting_path(params, f"reports/train-{split}.json"),
            settings=settings,
            storage=optuna_storage(params),
            study_name=section(params, "train", "study_name"),
            seed=int(settings.get("seed", section(params, "train", "seed"))),
            val_fraction=float(section(params, "train", "val_fraction")),
            model_name=settings.get("model_name") or section(params, "mlflow", "model_name"),
            data_split=settings.get("split", split),
            progress=bool(args.get("progress")),
            params=params,
        )


def run(settings: TrainSettings) -> dict[str, Any]:
    """Train and export; returns the validation MAE, trials, seconds and registry outcome."""
    tracking(settings.params)
    result = run_train(**settings.call_args())
    return {
        "split": settings.split,
        "val_mae_deg": result.val_mae_deg,
        "n_trials": result.n_trials,
        "seconds": result.seconds,
        "version": result.version,
        "promoted": result.promoted,
    }


def describe(figures: Mapping[str, Any]) -> list[str]:
    reg = (
        f"; registered as version {figures['version']} ("
        f"{'now champion' if figures['promoted'] else 'champion unchanged'})"
        if figures["version"]
        else ""
    )
    return [
        f"trained on {figures['split']}: validation MAE {figures['val_mae_deg']:.4f} deg after "
        f"{figures['n_trials']} Optuna trials in {figures['seconds']:.0f} s{reg}"
    ]


def run_train(
    *,
    prepared_dir: Path,
    split: str,
    out_dir: Path,
    metrics_path: Path,
    settings: Mapping[str, Any],
    storage: str,
    study_name: str,
    seed: int,
    val_fraction: float,
    model_name: str | None,
    progress: bool = False,
    data_split: str | None = None,
):
    """Train (search + final ensemble) on one split; export the model folder, write the summary.

    ``split`` names the run (Optuna study, MLflow run); ``data_split`` is the prepared table
    trained on (default: ``split``), so that e.g. a held-out surrogate trains on "large" too.

    ``out_dir`` receives the logged MLflow model file for file (:func:`femcal.tracking.
    export_model`), with ``mlflow.json`` recording the run and the registered version: the
    folder DVC versions is a complete model that loads and serves without the tracking store.
    """

    from femcal.train import train_surrogate, write_summary

    table, space = load_split(prepared_dir, data_split or split)
    result = train_surrogate(
        table,
        space,
        search_space=settings.get("search_space") or {},
        fixed=settings.get("fixed") or {},
        n_trials=int(settings.get("n_trials", 0)),
        final_members=int(settings.get("final_members", 1)),
        storage=storage,
        study_name=f"{study_name}-{split}",
        seed=seed,
        val_fraction=val_fraction,
        register_as=model_name if settings.get("register") else None,
        run_name=f"train-{split}",
        progress=progress,
    )
    export_folder(result, out_dir, model_name if settings.get("register") else None)
    write_summary(result, metrics_path)
    return result
