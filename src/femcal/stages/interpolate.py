"""Stage ``interpolate``: train on some moments of Large, test at the others on Test."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from femcal.datasets import load_split
from femcal.evaluate import Score, score_model
from femcal.paths import setting_path
from femcal.stages.common import StageSettings, path_setting, typed
from femcal.stages.store import tracking


@dataclass(frozen=True)
class InterpolateSettings(StageSettings):
    """The ``interpolation`` section, with the Large network's fixed recipe and seeds."""

    prepared_dir: Path
    out_path: Path
    train_moments: Sequence[float]
    test_moments: Sequence[float]
    fixed: Mapping[str, Any]
    final_members: int
    baselines: Sequence[str]
    seed: int
    val_fraction: float
    n_jobs: int

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> InterpolateSettings:
        cfg = typed(params, "interpolation")
        train = typed(params, "train", "large", "seed", "val_fraction")
        return cls(
            prepared_dir=path_setting(params, "data", "prepared_dir"),
            out_path=setting_path(params, "reports/interpolation.json"),
            train_moments=list(cfg.train_moments),
            test_moments=list(cfg.test_moments),
            fixed=dict(train.splits["large"].fixed),
            final_members=cfg.final_members,
            baselines=list(cfg.baselines),
            seed=train.seed,
            val_fraction=train.val_fraction,
            n_jobs=typed(params, "baselines", "n_jobs").n_jobs,
            params=params,
        )


def run(settings: InterpolateSettings) -> dict[str, Any]:
    """Train and score; returns ``{"mae_deg": {model: MAE at the unseen moments}}``."""
    tracking(settings.params)
    scores = run_interpolation(**settings.call_args())
    return {"mae_deg": {s.model: s.scores["mae"] for s in scores}}


def describe(figures: Mapping[str, Any]) -> list[str]:
    return [
        f"{model:>18}: MAE {mae:.3f} deg at unseen moments"
        for model, mae in figures["mae_deg"].items()
    ]


def run_interpolation(
    *,
    prepared_dir: Path,
    out_path: Path,
    train_moments: Sequence[float],
    test_moments: Sequence[float],
    fixed: Mapping[str, Any],
    final_members: int,
    baselines: Sequence[str],
    seed: int,
    val_fraction: float,
    n_jobs: int = 1,
) -> list[Score]:
    """Train on some moments of Large, test at others on Test (NN and chosen baselines)."""
    import mlflow

    from femcal.surrogates import make_baseline
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.train import ok_rows, surrogate_kwargs, validation_split

    large, space = load_split(prepared_dir, "large")
    test, _ = load_split(prepared_dir, "test")
    data = ok_rows(large)
    data = data[data["moment_nm"].isin(list(train_moments))].reset_index(drop=True)
    tr, va = validation_split(data, fraction=val_fraction, seed=seed)
    scores: list[Score] = []
    with mlflow.start_run(run_name="interpolation"):
        mlflow.set_tag("femcal.stage", "interpolation")
        mlflow.log_params(
            {"train_moments": list(train_moments), "test_moments": list(test_moments)}
        )
        nn = NeuralSurrogate(space, **surrogate_kwargs(fixed), n_members=final_members, seed=seed)
        nn.fit(tr, tr["rom_deg"].to_numpy(), X_val=va, y_val=va["rom_deg"].to_numpy())
        label = "large, " + ",".join(f"{m:g}" for m in train_moments) + " Nm"
        scores.append(score_model(nn, test, name="nn", train_split=label, moments=test_moments))
        for name in baselines:
            model = make_baseline(name, space=space, seed=seed, n_jobs=n_jobs)
            model.fit(data, data["rom_deg"].to_numpy())
            scores.append(
                score_model(model, test, name=name, train_split=label, moments=test_moments)
            )
        for s in scores:
            mlflow.log_metrics(
                {f"{s.model}.{k}": float(v) for k, v in s.scores.items() if np.isfinite(v)}
            )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(
        json.dumps(
            [
                {
                    "model": s.model,
                    "train_split": s.train_split,
                    "scores": s.scores,
                    "n_rows": s.n_rows,
                }
                for s in scores
            ],
            indent=2,
        )
        + "\n"
    )
    return scores
