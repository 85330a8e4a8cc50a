"""Training under a real Optuna RDB study with a real (temporary) MLflow store."""

import mlflow
import numpy as np
import optuna
import pytest
from mlflow import MlflowClient

from femcal.errors import ConfigError
from femcal.train import surrogate_kwargs, train_surrogate, validation_split
from femcal.training.study import suggest

from synth import study_space, tidy_table

TINY = {
    "width": 16,
    "depth": 2,
    "max_epochs": 4,
    "patience": 4,
    "batch_size": 256,
    "learning_rate": 3e-3,
}
SPACE = {"learning_rate": {"type": "float", "low": 1e-3, "high": 1e-2, "log": True}}


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    from femcal.tracking import configure_tracking, ensure_experiment

    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("test", store_dir=tmp_path / "mlruns")
    yield tmp_path
    mlflow.set_tracking_uri(None)


def _train(table, store, **kw):
    args = dict(
        search_space=SPACE,
        fixed=TINY,
        n_trials=2,
        final_members=1,
        storage=f"sqlite:///{store / 'optuna.db'}",
        study_name="t",
        seed=0,
        register_as="ivd-rom-surrogate",
    )
    args.update(kw)
    return train_surrogate(table, study_space(), **args)


def test_search_logs_trials_registers_and_resumes(store):
    table = tidy_table(24, seed=1)
    res = _train(table, store)
    assert res.n_trials == 2
    assert res.version == "1" and res.promoted
    client = MlflowClient()
    children = client.search_runs(
        [mlflow.get_experiment_by_name("test").experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{res.run_id}'",
    )
    assert len(children) == 2
    for child in children:
        history = client.get_metric_history(child.info.run_id, "val_mae_deg")
        assert len(history) >= 2, "per-epoch validation MAE must be logged"
        assert "learning_rate" in child.data.params
    champion = client.get_model_version_by_alias("ivd-rom-surrogate", "champion")
    assert str(champion.version) == "1"

    # Resume: the study already holds 2 complete trials, asking for 3 runs only one more.
    res2 = _train(table, store, n_trials=3)
    assert res2.n_trials == 3
    children2 = client.search_runs(
        [mlflow.get_experiment_by_name("test").experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{res2.run_id}'",
    )
    assert len(children2) == 1


def test_champion_moves_only_on_better_validation(store):
    table = tidy_table(24, seed=1)
    good = _train(table, store, n_trials=0, fixed={**TINY, "max_epochs": 30, "patience": 30})
    bad = _train(table, store, n_trials=0, fixed={**TINY, "max_epochs": 1, "learning_rate": 1e-5})
    assert bad.val_mae_deg > good.val_mae_deg
    assert good.promoted and not bad.promoted
    champion = MlflowClient().get_model_version_by_alias("ivd-rom-surrogate", "champion")
    assert str(champion.version) == good.version


def test_same_seed_same_metrics(store):
    table = tidy_table(20, seed=2)
    a = _train(table, store, n_trials=0, register_as=None)
    b = _train(table, store, n_trials=0, register_as=None)
    assert a.val_mae_deg == b.val_mae_deg
    c = _train(table, store, n_trials=0, register_as=None, seed=1)
    assert c.val_mae_deg != a.val_mae_deg


def test_validation_split_is_by_configuration():
    table = tidy_table(20, seed=0)
    tr, va = validation_split(table, fraction=0.25, seed=0)
    assert set(tr["config_id"]).isdisjoint(va["config_id"])
    assert va["config_id"].nunique() == 5
    assert len(tr) + len(va) == len(table)


def test_validation_fraction_error():
    with pytest.raises(ConfigError, match=r"Validation fraction must lie in \(0, 1\); got 1.5"):
        validation_split(tidy_table(4, seed=0), fraction=1.5, seed=0)


def test_suggest_errors():
    trial = optuna.create_study().ask()
    with pytest.raises(ConfigError, match="search_space.lr.type is 'floaty'"):
        suggest(trial, {"lr": {"type": "floaty"}})
    with pytest.raises(ConfigError, match="search_space.lr \\(float\\) lacks 'high'"):
        suggest(trial, {"lr": {"type": "float", "low": 0.1}})


def test_surrogate_kwargs_width_depth():
    assert surrogate_kwargs({"width": 8, "depth": 3, "loss": "l1"}) == {
        "hidden": (8, 8, 8),
        "loss": "l1",
    }


def test_negative_trials_error(store):
    with pytest.raises(ConfigError, match="n_trials must be >= 0"):
        _train(tidy_table(4, seed=0), store, n_trials=-1)


def test_failed_rows_are_not_trained_on(store):
    table = tidy_table(20, seed=3)
    table.loc[:9, "status"] = "failed"
    table.loc[:9, "rom_deg"] = np.nan
    res = _train(table, store, n_trials=0, register_as=None)
    assert np.isfinite(res.val_mae_deg)


KILL_SCRIPT = """
import sys, time, mlflow
sys.path.insert(0, {tests!r})
from synth import study_space, tidy_table
from femcal.tracking import configure_tracking, ensure_experiment
from femcal.train import train_surrogate
configure_tracking(store_dir={store!r})
ensure_experiment("test", store_dir={store!r})
train_surrogate(
    tidy_table(24, seed=1), study_space(), search_space={space!r},
    fixed={fixed!r}, n_trials=50, final_members=1, storage={storage!r}, study_name="t",
    seed=0, heartbeat_seconds=1,
)
"""


def test_killed_search_resumes(store):
    """SIGKILL a worker mid-search; the next run keeps its finished trials and retries the
    one it was running."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    storage = f"sqlite:///{store / 'optuna.db'}"
    fixed = {**TINY, "max_epochs": 40, "patience": 40}
    script = KILL_SCRIPT.format(
        tests=str(Path(__file__).parent),
        store=str(store / "mlruns"),
        space=SPACE,
        fixed=fixed,
        storage=storage,
    )
    proc = subprocess.Popen([sys.executable, "-c", script])
    name = None
    import sqlite3

    def progress() -> tuple[str | None, list[str], bool]:
        # Read the store with plain SQL, read-only: Optuna's own storage object would try to
        # create the schema that the worker may be creating at that moment (a race that failed
        # with "UNIQUE constraint failed: alembic_version").
        try:
            with sqlite3.connect(f"file:{store / 'optuna.db'}?mode=ro", uri=True) as db:
                study = db.execute("SELECT study_name FROM studies").fetchone()
                trials = db.execute("SELECT trial_id, state FROM trials ORDER BY trial_id")
                trials = trials.fetchall()
                beats = {r[0] for r in db.execute("SELECT trial_id FROM trial_heartbeats")}
        except sqlite3.Error:  # not there yet, or the schema is being written
            return None, [], False
        # Optuna only fails a running trial as stale once it has beaten at least once: a
        # worker killed before its trial's first heartbeat leaves a trial that stays RUNNING
        # (seen under load), so the kill waits for that beat too.
        beating = bool(trials) and trials[-1][0] in beats
        return (study[0] if study else None), [row[1] for row in trials], beating

    try:
        # No wall-clock deadline: wait for the worker as long as it runs (a loaded machine only
        # makes it slower); the hour is a guard against a hang, not a race.
        give_up = time.monotonic() + 3600
        while proc.poll() is None and time.monotonic() < give_up:
            time.sleep(0.5)
            name, states, beating = progress()
            if states.count("COMPLETE") >= 2 and states[-1] == "RUNNING" and beating:
                break
        else:
            pytest.fail(f"the worker ended (code {proc.returncode}) before two complete trials")
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    before = optuna.load_study(study_name=name, storage=storage).trials
    n_done = sum(t.state == optuna.trial.TrialState.COMPLETE for t in before)
    assert before[-1].state == optuna.trial.TrialState.RUNNING  # orphaned by the kill
    # Make its heartbeat stale through the storage itself (no wall-clock race): the killed
    # worker's last beat is moved back an hour, as if it had died long ago.
    with sqlite3.connect(store / "optuna.db") as db:
        changed = db.execute(
            "UPDATE trial_heartbeats SET heartbeat = datetime(heartbeat, '-1 hour')"
        ).rowcount
    assert changed >= 1
    res = _train(
        tidy_table(24, seed=1),
        store,
        fixed=fixed,
        n_trials=n_done + 1,
        heartbeat_seconds=1,
        register_as=None,
    )
    after = optuna.load_study(study_name=name, storage=storage).trials
    assert after[len(before) - 1].state == optuna.trial.TrialState.FAIL
    assert res.n_trials == n_done + 1
    # Finished trials were kept, not recomputed: their values are unchanged.
    for t_before, t_after in zip(before[:-1], after):
        assert t_before.state != optuna.trial.TrialState.COMPLETE or t_before.value == t_after.value


def test_idp_target_trains_a_pressure_head_with_its_own_unit(store):
    # The FE campaign's second output: a pressure that can be <= 0 under a pure moment,
    # learnt linearly; its error is named in MPa in the result, MLflow and the summary.
    table = tidy_table(16, seed=2)
    table["idp_mpa"] = 0.05 * table["moment_nm"] - 0.1  # negative at 1 Nm
    table.loc[3, "idp_mpa"] = np.nan  # a level without a pressure is left out, not an error
    fixed = {**TINY, "log_target": False}
    res = _train(table, store, fixed=fixed, n_trials=0, target="idp_mpa", register_as=None)
    assert res.target == "idp_mpa" and res.val_metric == "val_mae_mpa"
    run = MlflowClient().get_run(res.run_id)
    assert "val_mae_mpa" in run.data.metrics and "val_mae_deg" not in run.data.metrics
    assert run.data.params["target"] == "idp_mpa"
    pred = res.surrogate.predict(table[["load_case", "moment_nm", *study_space().names]])
    assert np.isfinite(pred).all()
    assert pred.min() < 0, "a pressure head must be able to predict negative values"


def test_idp_target_errors(store):
    table = tidy_table(8, seed=2)
    with pytest.raises(ConfigError, match="needs fixed log_target: false"):
        _train(table, store, n_trials=0, target="idp_mpa")
    with pytest.raises(ConfigError, match="not an output a surrogate can learn"):
        _train(table, store, n_trials=0, target="force_n")
    with pytest.raises(ConfigError, match="has no column 'idp_mpa'"):
        _train(
            table.drop(columns="idp_mpa"),
            store,
            n_trials=0,
            target="idp_mpa",
            fixed={**TINY, "log_target": False},
        )


def test_a_heldout_table_sets_the_stated_error(store):
    """The stated error (what calibrate and diagnose count) comes from the held-out rows when
    given; the validation error still decides the promotion."""
    table, heldout = tidy_table(20, seed=2), tidy_table(6, seed=7)
    plain = _train(table, store, n_trials=0, register_as=None)
    res = _train(table, store, n_trials=0, register_as=None, heldout=heldout)
    assert res.val_mae_deg == plain.val_mae_deg
    model = res.surrogate
    pred = model.predict(heldout)
    mae = float(np.mean(np.abs(pred - heldout["rom_deg"].to_numpy())))
    assert model.best_val_mae_deg_ == pytest.approx(mae, rel=1e-12)
    assert model.val_error_profile_ != plain.surrogate.val_error_profile_
    assert MlflowClient().get_run(res.run_id).data.metrics["heldout_val_mae_deg"] == mae
    empty = heldout.assign(rom_deg=np.nan)
    with pytest.raises(ConfigError, match="held-out table for the stated error has no finite"):
        _train(table, store, n_trials=0, register_as=None, heldout=empty)
