"""Stage ``baselines@<split>``: the study's model zoo, each fitted model saved and logged."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.datasets import load_split
from femcal.paths import setting_path
from femcal.stages.common import StageSettings, path_setting, typed
from femcal.stages.store import tracking

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BaselinesSettings(StageSettings):
    """The ``baselines`` section of params.yaml for one split."""

    prepared_dir: Path
    split: str
    out_dir: Path
    models: Sequence[str]
    seed: int
    n_jobs: int

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> BaselinesSettings:
        split = args["split"]
        cfg = typed(params, "baselines")
        return cls(
            prepared_dir=path_setting(params, "data", "prepared_dir"),
            split=split,
            out_dir=setting_path(params, f"models/baselines-{split}"),
            models=list(cfg.models),
            seed=cfg.seed,
            n_jobs=cfg.n_jobs,
            params=params,
        )


def run(settings: BaselinesSettings) -> dict[str, Any]:
    """Fit every model; returns ``{"split", "seconds": {model: fit seconds}}``."""
    tracking(settings.params)
    seconds = run_baselines(**settings.call_args())
    return {"split": settings.split, "seconds": seconds}


def describe(figures: Mapping[str, Any]) -> list[str]:
    return [
        f"{name:>18} fitted on {figures['split']} in {s:6.1f} s"
        for name, s in figures["seconds"].items()
    ]


def run_baselines(
    *,
    prepared_dir: Path,
    split: str,
    out_dir: Path,
    models: Sequence[str],
    seed: int,
    n_jobs: int,
) -> dict[str, float]:
    """Fit the baselines ``models`` (names of :data:`femcal.surrogates.baseline_registry`) on
    one split; save each fitted model into ``out_dir / name``; log each as a run."""
    import mlflow

    from femcal.datasets import ok_rows
    from femcal.surrogates import make_baseline

    table, space = load_split(prepared_dir, split)
    data = ok_rows(table)
    out_dir.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    with mlflow.start_run(run_name=f"baselines-{split}"):
        mlflow.set_tag("femcal.stage", "baselines")
        for name in models:
            with mlflow.start_run(run_name=f"{name}-{split}", nested=True):
                model = make_baseline(name, space=space, seed=seed, n_jobs=n_jobs)
                t0 = time.perf_counter()
                model.fit(data, data["rom_deg"].to_numpy())
                seconds[name] = time.perf_counter() - t0
                mlflow.log_params({"model": name, "train_split": split, "seed": seed})
                mlflow.log_metric("fit_seconds", seconds[name])
                model.save(out_dir / name)  # built-ins: skops + LightGBM text, data, not a pickle
                logger.info("%s on %s fitted in %.1f s", name, split, seconds[name])
    (out_dir / "fit_seconds.json").write_text(json.dumps(seconds, indent=2) + "\n")
    return seconds
