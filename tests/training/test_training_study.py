"""The shared Optuna study runner: resume, trial 0, nested MLflow runs, pruning tags."""

from __future__ import annotations

import mlflow
import optuna
import pytest
from mlflow import MlflowClient

from femcal.errors import ConfigError
from femcal.training.study import (
    TrialRun,
    fixed_as_trial,
    n_complete,
    run_study,
    search_settings,
    study_name_for,
)

SPACE = {"x": {"type": "float", "low": -2.0, "high": 2.0}}


def _quadratic(seen: list[TrialRun]):
    def train_trial(trial: TrialRun) -> float:
        seen.append(trial)
        return (trial.params["x"] - 0.5) ** 2

    return train_trial


def _run(store, n_trials: int, seen: list[TrialRun]):
    return run_study(
        _quadratic(seen),
        storage=f"sqlite:///{store / 'optuna.db'}",
        study_name="q-study",
        search_space=SPACE,
        fixed={"x": 1.0, "width": 8},
        n_trials=n_trials,
        seed=0,
        monitor="val_mae",
        heartbeat_seconds=5,
    )


def test_a_study_resumes_from_its_storage(store) -> None:
    seen: list[TrialRun] = []
    with mlflow.start_run(run_name="first") as first:
        outcome = _run(store, 2, seen)
    assert outcome.n_complete == 2 and len(seen) == 2
    # Trial 0 is the fixed recipe; every trial gets the fixed settings and a logger.
    assert seen[0].number == 0 and seen[0].params == {"x": 1.0, "width": 8}
    assert all(t.params["width"] == 8 and len(t.callbacks) == 1 for t in seen)

    with mlflow.start_run(run_name="second"):
        again = _run(store, 3, seen)
    # Only the missing trial ran: 3 in all, the first two kept.
    assert again.n_complete == 3 and len(seen) == 3 and seen[-1].number == 2
    study = optuna.load_study(study_name="q-study", storage=f"sqlite:///{store / 'optuna.db'}")
    assert n_complete(study) == 3
    assert again.best_value == min(t.value for t in study.trials)
    assert again.best_params == study.best_trial.params

    # Each trial was a nested MLflow run of the run that started it, tagged COMPLETE.
    client = MlflowClient()
    children = client.search_runs(
        [mlflow.get_experiment_by_name("training").experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{first.info.run_id}'",
    )
    assert sorted(c.data.params["trial"] for c in children) == ["0", "1"]
    assert {c.data.tags["optuna.state"] for c in children} == {"COMPLETE"}
    assert {c.data.params["optuna_study"] for c in children} == {"q-study"}

    # A study already complete runs nothing.
    with mlflow.start_run(run_name="third"):
        assert _run(store, 3, seen).n_complete == 3
    assert len(seen) == 3


def test_runner_settings_and_helpers(store) -> None:
    with pytest.raises(ConfigError, match="n_trials >= 1"):
        _run(store, 0, [])
    # Without trials the fixed settings are the answer and no study is opened.
    assert search_settings(_quadratic([]), fixed={"x": 1.0}, n_trials=0, metric="m") == (
        {"x": 1.0},
        0,
    )
    assert not (store / "optuna.db").exists()
    with mlflow.start_run() as run:
        best, n = search_settings(
            _quadratic([]),
            fixed={"x": 1.0, "width": 8},
            n_trials=2,
            metric="loss",
            storage=f"sqlite:///{store / 'optuna.db'}",
            study_name="q2",
            search_space=SPACE,
            seed=0,
            monitor="val_mae",
        )
    assert n == 2 and best["width"] == 8 and set(best) == {"x", "width"}
    logged = MlflowClient().get_run(run.info.run_id).data.metrics["best_trial_loss"]
    assert logged == min((1.0 - 0.5) ** 2, (best["x"] - 0.5) ** 2)
    assert fixed_as_trial({"x": 5.0, "width": 8}, SPACE) == {}
    assert fixed_as_trial({"x": 1.0}, SPACE) == {"x": 1.0}
    choices = {"act": {"type": "categorical", "choices": ["relu", "gelu"]}}
    assert fixed_as_trial({"act": "gelu"}, choices) == {"act": "gelu"}
    assert fixed_as_trial({"act": "tanh"}, choices) == {}
    a = study_name_for("s", search_space=SPACE, fixed={"x": 1.0}, data_id="d")
    assert a == study_name_for("s", search_space=SPACE, fixed={"x": 1.0}, data_id="d")
    assert a != study_name_for("s", search_space=SPACE, fixed={"x": 1.0}, data_id="e")
    assert a.startswith("s-") and len(a) == 12
