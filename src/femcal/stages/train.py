"""Stage ``train@<split>``: the surrogate's Optuna search and final ensemble, logged to MLflow.

The model folder (``models/surrogate-<split>``) is the logged MLflow model, file for file; the
summary goes to ``reports/train-<split>.json`` (``--metrics-file`` elsewhere), every figure
to its details file (:func:`femcal.dvc_metrics.details_path`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.datasets import load_split
from femcal.paths import setting_path
from femcal.stages.common import StageSettings, path_setting, typed
from femcal.stages.store import export_folder, registry_figures, study_search, tracking
from femcal.training.search import StudySearch


@dataclass(frozen=True)
class TrainSettings(StageSettings):
    """One ``train.<split>`` section of params.yaml, with the shared train settings."""

    prepared_dir: Path
    split: str
    out_dir: Path
    metrics_path: Path
    study: StudySearch
    final_members: int
    val_fraction: float
    register_as: str | None
    data_split: str | None = None
    target: str = "rom_deg"
    heldout_split: str | None = None

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> TrainSettings:
        split = args["split"]
        train = typed(params, "train", split, "study_name", "seed", "val_fraction")
        settings = train.splits[split]
        model_name = settings.model_name or typed(params, "mlflow", "model_name").model_name
        return cls(
            prepared_dir=path_setting(params, "data", "prepared_dir"),
            split=split,
            out_dir=setting_path(params, f"models/surrogate-{split}"),
            metrics_path=setting_path(
                params, args.get("metrics_file") or f"reports/train-{split}.json"
            ),
            study=study_search(
                params,
                args,
                settings,
                study_name=f"{train.study_name}-{split}",
                seed=train.seed if settings.seed is None else settings.seed,
            ),
            final_members=settings.final_members,
            val_fraction=train.val_fraction,
            register_as=model_name if settings.register_model else None,
            data_split=settings.split or split,
            target=settings.target,
            heldout_split=settings.stated_error_split,
            params=params,
        )


def run(settings: TrainSettings) -> dict[str, Any]:
    """Train and export; returns the validation MAE, trials, seconds and registry outcome."""
    tracking(settings.params)
    result = run_train(settings)
    return {
        "split": settings.split,
        "target": result.target,
        result.val_metric: result.val_mae_deg,
        **registry_figures(result),
    }


def describe(figures: Mapping[str, Any]) -> list[str]:
    reg = (
        f"; registered as version {figures['version']} ("
        f"{'now champion' if figures['promoted'] else 'champion unchanged'})"
        if figures["version"]
        else ""
    )
    return [
        f"trained on {figures['split']}: validation MAE {_validation_error(figures)} after "
        f"{figures['n_trials']} Optuna trials in {figures['seconds']:.0f} s{reg}"
    ]


def _validation_error(figures: Mapping[str, Any]) -> str:
    if "val_mae_mpa" in figures:
        return f"{figures['val_mae_mpa']:.4f} MPa (IDP)"
    return f"{figures['val_mae_deg']:.4f} deg"


def run_train(settings: TrainSettings):
    """Train (search + final ensemble) on one split; export the model folder, write the summary.

    ``settings.split`` names the run (Optuna study, MLflow run); ``data_split`` is the prepared
    table trained on (default: ``split``), so that e.g. a held-out surrogate trains on "large"
    too. ``study`` is the Optuna search; ``register_as`` the registered model name (None: not
    registered); ``target`` the output learnt (``rom_deg``, or ``idp_mpa`` for the FE
    campaign's IDP head); ``heldout_split`` a prepared table of configurations never trained
    on whose errors become the model's stated error (``train.<split>.stated_error_split``).

    ``out_dir`` receives the logged MLflow model file for file (:func:`femcal.tracking.
    export_model`), with ``mlflow.json`` naming the registered version: the folder DVC
    versions is a complete model that loads and serves without the tracking store.
    """

    from femcal.train import train_surrogate, write_summary

    s = settings
    table, space = load_split(s.prepared_dir, s.data_split or s.split)
    heldout = load_split(s.prepared_dir, s.heldout_split)[0] if s.heldout_split else None
    result = train_surrogate(
        table,
        space,
        final_members=s.final_members,
        val_fraction=s.val_fraction,
        register_as=s.register_as,
        run_name=f"train-{s.split}",
        target=s.target,
        heldout=heldout,
        **s.study.keywords(),
    )
    export_folder(result, s.out_dir, s.register_as)
    write_summary(result, s.metrics_path)
    return result
