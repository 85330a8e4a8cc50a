"""Stage ``evaluate``: every surrogate's Test-set table beside the study's, and the plot data."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from femcal.datasets import load_split
from femcal.evaluate import Score, score_model, write_reports
from femcal.paths import setting_path
from femcal.stages.common import StageSettings, path_setting, typed
from femcal.stages.store import tracking

#: The training sets whose networks and baselines are compared.
SPLITS = ("large", "small")


@dataclass(frozen=True)
class EvaluateSettings(StageSettings):
    """Where the models and reports are (the project's layout, at the project root)."""

    prepared_dir: Path
    surrogate_dirs: Mapping[str, Path]
    baseline_dirs: Mapping[str, Path]
    baseline_models: Sequence[str]
    interpolation_path: Path
    markdown: Path
    json_path: Path
    table_path: Path
    predictions_path: Path
    curves_path: Path

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> EvaluateSettings:
        def at(path: str) -> Path:
            return setting_path(params, path)

        return cls(
            prepared_dir=path_setting(params, "data", "prepared_dir"),
            surrogate_dirs={s: at(f"models/surrogate-{s}") for s in SPLITS},
            baseline_dirs={s: at(f"models/baselines-{s}") for s in SPLITS},
            baseline_models=list(typed(params, "baselines").models),
            interpolation_path=at("reports/interpolation.json"),
            markdown=at("reports/surrogates.md"),
            json_path=at("reports/surrogates.json"),
            table_path=at("reports/surrogates_table.json"),
            predictions_path=at("reports/plots/surrogate_test_predictions.csv"),
            curves_path=at("reports/plots/training_curves.csv"),
            params=params,
        )


def run(settings: EvaluateSettings) -> dict[str, Any]:
    """Score and write the reports; returns ``{"sections": {title: [Score, ...]}}``."""
    tracking(settings.params)
    sections = run_evaluate(settings)
    return {"sections": sections}


def describe(figures: Mapping[str, Any]) -> list[str]:
    lines = []
    for title, rows in figures["sections"].items():
        lines.append(title)
        for s in rows:
            lines.append(
                f"  {s.model:>18} {s.train_split:>6}: MAE {s.scores['mae']:.3f} deg, "
                f"mean R² {s.scores['r2_mean']:.4f}"
            )
    lines.append(
        "reports: reports/surrogates.md, reports/surrogates_table.json; plot data: "
        "reports/plots/ (dvc plots show)"
    )
    return lines


def load_nn(path: Path):
    """The surrogate in a model folder of the train stage (through its trusted loader)."""
    from femcal.tracking import load_surrogate

    return load_surrogate(str(path))


def run_evaluate(settings: EvaluateSettings, plot_split: str = "large") -> dict[str, list[Score]]:
    """Score every model on the Test split; write the reports and plot data; log to MLflow.

    ``settings`` (:class:`EvaluateSettings`) names the models and the reports: ``json_path``
    gets the headline figures (the stage's DVC metrics), ``table_path`` every
    model x training set x load case, ``markdown`` the tables for people. For the network
    trained on ``plot_split`` (the one calibrate uses), ``predictions_path`` gets its
    predicted vs FE RoM of every Test row and ``curves_path`` its training and validation
    loss per member and epoch (from the model folder): the data of ``dvc plots``.
    """
    import mlflow

    from femcal.evaluate import prediction_table, training_curves
    from femcal.surrogates import get_baseline

    s = settings
    surrogate_dirs, baseline_dirs = s.surrogate_dirs, s.baseline_dirs
    predictions_path, curves_path = s.predictions_path, s.curves_path
    markdown, json_path, table_path = s.markdown, s.json_path, s.table_path
    test, _ = load_split(s.prepared_dir, "test")
    sections: dict[str, list[Score]] = {}
    for split in surrogate_dirs:
        rows: list[Score] = []
        nn_dir = surrogate_dirs[split]
        info = (
            json.loads((nn_dir / "mlflow.json").read_text())
            if (nn_dir / "mlflow.json").exists()
            else {}
        )
        nn = load_nn(nn_dir)
        if split == plot_split and predictions_path is not None:
            predictions_path.parent.mkdir(parents=True, exist_ok=True)
            prediction_table(nn, test).to_csv(predictions_path, index=False)
        if split == plot_split and curves_path is not None:
            curves_path.parent.mkdir(parents=True, exist_ok=True)
            training_curves(nn).to_csv(curves_path, index=False)
        rows.append(
            score_model(
                nn,
                test,
                name="nn",
                train_split=split,
                extra={"registered_version": info.get("version")},
            )
        )
        for name in s.baseline_models:
            model = get_baseline(name).load(baseline_dirs[split] / name)
            rows.append(score_model(model, test, name=name, train_split=split))
        rows.sort(key=lambda s: s.scores["mae"])
        sections[f"Trained on {split.capitalize()}"] = rows
    if s.interpolation_path is not None and s.interpolation_path.exists():
        sections["Interpolation: trained on 1, 3, 5 Nm, tested at 2 and 4 Nm"] = [
            Score(r["model"], r["train_split"], r["scores"], r["n_rows"], {})
            for r in json.loads(s.interpolation_path.read_text())
        ]
    preamble = (
        "MAE in degrees over all rows; mean R² = R² per load case pooled over configurations "
        "and moments, averaged over load cases; curve R² = the study's per-specimen R² across "
        "the moments of a curve, averaged. Study figures: Atad et al., 4-fold CV means."
    )
    write_reports(
        sections,
        markdown=markdown,
        json_path=json_path,
        table_path=table_path,
        preamble=preamble,
    )
    with mlflow.start_run(run_name="evaluate"):
        mlflow.set_tag("femcal.stage", "evaluate")
        for title, rows in sections.items():
            for row in rows:
                with mlflow.start_run(run_name=f"eval-{row.model}-{row.train_split}", nested=True):
                    mlflow.log_params(
                        {"model": row.model, "train_split": row.train_split, "section": title[:200]}
                    )
                    scores = row.scores.items()
                    mlflow.log_metrics({k: float(v) for k, v in scores if np.isfinite(v)})
        mlflow.log_artifact(str(markdown))
        for path in (json_path, table_path, predictions_path, curves_path):
            if path is not None:
                mlflow.log_artifact(str(path))
    return sections
