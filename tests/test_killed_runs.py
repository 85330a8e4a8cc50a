"""MLflow runs of a ``kill -9``-ed process are closed as KILLED at the next start.

A child process starts a run and a nested run (tagged with its pid and host) in each of two
experiments, says so through a file, and is killed; the next start closes them. Real MLflow,
one temporary store for the module (one child: MLflow's store set-up takes seconds).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest

from femcal.tracking import configure_tracking, ensure_experiment
from femcal.tracking_runs import (
    HOST_TAG,
    KILLED_TAG,
    PID_TAG,
    close_killed_runs,
    process_tags,
    tag_runs_with_process,
)

CHILD = """
import json, sys, time
from pathlib import Path
import mlflow
from femcal.tracking import configure_tracking, ensure_experiment
from femcal.tracking_runs import tag_runs_with_process

store, ready = Path(sys.argv[1]), Path(sys.argv[2])
configure_tracking(store_dir=store)
tag_runs_with_process()
ids = {}
for name in ("a", "b"):  # a run and a trial run in each experiment, never ended
    experiment = ensure_experiment(name, store_dir=store)
    run = mlflow.start_run(experiment_id=experiment, run_name="train", nested=bool(ids))
    trial = mlflow.start_run(experiment_id=experiment, run_name="trial-0", nested=True)
    ids[name] = [run.info.run_id, trial.info.run_id]
ready.with_suffix(".tmp").write_text(json.dumps(ids))
ready.with_suffix(".tmp").rename(ready)
while True:
    time.sleep(0.05)
"""


@pytest.fixture(scope="module")
def killed(tmp_path_factory) -> tuple[Path, dict[str, list[str]]]:
    """A store, and per experiment ("a", "b") the run ids a killed child left RUNNING."""
    tmp = tmp_path_factory.mktemp("killed")
    store, ready = tmp / "mlruns", tmp / "ready.json"
    (tmp / "child.py").write_text(CHILD)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    proc = subprocess.Popen(
        [sys.executable, str(tmp / "child.py"), str(store), str(ready)],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 300
        while not ready.exists():  # a handshake, not a timing race
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "the child never started its runs"
            time.sleep(0.02)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate()
    return store, json.loads(ready.read_text())


@pytest.fixture
def store(killed, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setenv("MLFLOW_RUN_CONTEXT", "{}")
    yield killed[0]
    mlflow.set_tracking_uri(None)


def test_runs_of_a_killed_process_are_closed_as_killed(killed, store):
    killed = killed[1]["a"]
    configure_tracking(store_dir=store)
    experiment = ensure_experiment("a", store_dir=store)
    client = mlflow.MlflowClient()
    assert {client.get_run(r).info.status for r in killed} == {"RUNNING"}
    tags = client.get_run(killed[0]).data.tags
    assert tags[HOST_TAG] == process_tags()[HOST_TAG] and tags[PID_TAG] != str(os.getpid())
    # A run of a live process (this one), and a run without femcal's tags: left alone.
    tag_runs_with_process()
    untagged = client.create_run(experiment).info.run_id
    with mlflow.start_run() as live:
        assert sorted(close_killed_runs([experiment])) == sorted(killed)
        assert client.get_run(live.info.run_id).info.status == "RUNNING"
    assert client.get_run(untagged).info.status == "RUNNING"
    for run_id in killed:
        run = client.get_run(run_id)
        assert run.info.status == "KILLED" and run.info.end_time is not None
        assert f"process {tags[PID_TAG]} on" in run.data.tags[KILLED_TAG]
    assert close_killed_runs([experiment]) == []  # once


def test_every_command_closes_them_at_its_start(killed, store, caplog):
    from femcal.stages.store import tracking as _tracking

    killed = killed[1]["b"]
    with caplog.at_level(logging.WARNING, logger="femcal.tracking_runs"):
        _tracking({"mlflow": {"store_dir": str(store), "experiment": "b"}})
    said = [r.getMessage() for r in caplog.records if r.name == "femcal.tracking_runs"]
    assert len(said) == 2 and all("which is gone: closed as KILLED" in m for m in said)
    client = mlflow.MlflowClient()
    assert {client.get_run(r).info.status for r in killed} == {"KILLED"}
    # This command's own runs carry its pid and host.
    with mlflow.start_run() as run:
        assert client.get_run(run.info.run_id).data.tags[PID_TAG] == str(os.getpid())
