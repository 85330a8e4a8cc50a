"""The parent run of a training: its parameters, the final history, registration and time."""

from __future__ import annotations

import math
import time

import mlflow
from mlflow import MlflowClient

from femcal.training.final import log_history, register_final, training_run

HISTORY = [
    {"epoch": 0, "member": 0, "train_loss": 1.0, "val_mae": 0.5},
    {"epoch": 1, "member": 0, "train_loss": 0.8, "val_mae": math.nan},
    {"epoch": 0, "member": 1, "train_loss": 2.0, "val_mae": None},
]


def _steps(client: MlflowClient, run_id: str, key: str) -> list[tuple[int, float]]:
    return [(m.step, m.value) for m in client.get_metric_history(run_id, key)]


def test_training_run_logs_params_and_stage(store) -> None:
    with training_run("train-x", "train", {"seed": 3, "optuna_study": "s-abc"}) as run:
        run_id = run.info.run_id
    data = MlflowClient().get_run(run_id).data
    assert data.params == {"seed": "3", "optuna_study": "s-abc"}
    assert data.tags["femcal.stage"] == "train"
    assert data.tags["mlflow.runName"] == "train-x"


def test_log_history_skips_missing_values(store) -> None:
    client = MlflowClient()
    with mlflow.start_run() as run:
        log_history(HISTORY, ("train_loss", "val_mae", "lr"))
    assert _steps(client, run.info.run_id, "final.train_loss") == [(0, 1.0), (1, 0.8), (0, 2.0)]
    assert _steps(client, run.info.run_id, "final.val_mae") == [(0, 0.5)]
    assert _steps(client, run.info.run_id, "final.lr") == []
    with mlflow.start_run() as run:
        log_history(HISTORY, ("train_loss",), by_member=True)
    assert _steps(client, run.info.run_id, "final.member0.train_loss") == [(0, 1.0), (1, 0.8)]
    assert _steps(client, run.info.run_id, "final.member1.train_loss") == [(0, 2.0)]


def test_register_final_without_a_name_logs_the_time_only(store) -> None:
    started = time.perf_counter()
    with mlflow.start_run() as run:
        version, promoted, seconds = register_final(
            "runs:/x/model",
            None,
            val_metric=0.1,
            study="s",
            run_id=run.info.run_id,
            started=started,
        )
    assert (version, promoted) == (None, False)
    assert 0.0 <= seconds <= time.perf_counter() - started
    assert MlflowClient().get_run(run.info.run_id).data.metrics["train_seconds"] == seconds
