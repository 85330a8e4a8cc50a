"""`dvc repro` for real, in a temporary copy of the repository, on a few dozen configurations.

Slow (minutes): excluded from the default ``make test``; ``make test-slow`` (CI's second step)
runs it. Needs the study's data through FEMCAL_DATA_MIRROR (CI sets it); skipped otherwise.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from checkout import copy_working_tree

BIN = Path(sys.executable).parent

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not os.environ.get("FEMCAL_DATA_MIRROR"),
        reason="set FEMCAL_DATA_MIRROR to the study's data to run the pipeline",
    ),
]


def _run(args, cwd, env, check=True):
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)
    if check and proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
        )
    return proc


def tiny_params(path: Path) -> None:
    params = yaml.safe_load(path.read_text())
    params["data"]["limit_configs"] = 24
    tiny = {"width": 16, "depth": 2, "max_epochs": 3, "patience": 3, "batch_size": 256}
    for split in ("large", "small", "holdout"):
        params["train"][split]["fixed"].update(tiny)
        params["train"][split]["final_members"] = 1
    params["train"]["large"]["n_trials"] = 1
    params["train"]["large"]["search_space"] = {
        "learning_rate": {"type": "float", "low": 0.001, "high": 0.01, "log": True}
    }
    params["train"]["holdout"]["final_members"] = 1
    params["inverse"].update({"n_samples": 500, "n_trials": 1})
    params["inverse"]["fixed"] = {"width": 16, "depth": 2, "max_epochs": 2, "patience": 2}
    params["calibrate"]["max_plots"] = 3
    params["plant"]["n_per_class"] = 2
    params["diagnose"]["max_plots"] = 2
    params["calibrate"]["options"]["pgd"] = {"n_starts": 2, "max_iter": 3}
    params["baselines"]["models"] = ["linear", "lightgbm"]
    params["interpolation"]["final_members"] = 1
    params["interpolation"]["baselines"] = ["linear"]
    path.write_text(yaml.safe_dump(params, sort_keys=False))


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("femcal") / "repo"
    # The FE pipeline (fe/dvc.yaml) is tested in tests/fe, and the experiments pipeline
    # (experiments/dvc.yaml, experiments/archive.dvc) runs by hand; this copy is the root
    # pipeline's, where a teammate's `dvc pull` would miss their never-run or unpushed outputs.
    copy_working_tree(root, skip=lambda rel: rel.startswith(("fe/", "experiments/")))
    tiny_params(root / "params.yaml")
    # No MLflow settings from the test process: mlflow.set_registry_uri (called by other
    # tests in this process) exports MLFLOW_REGISTRY_URI, which would leak into the copy.
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["FEMCAL_OPTUNA_STORAGE"] = ""
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    _run(["git", "init", "-q"], root, env)
    _run([*git, "add", "-A"], root, env)
    _run([*git, "commit", "-qm", "copy"], root, env)
    first = _run([BIN / "dvc", "repro"], root, env)
    return root, env, git, first


def test_repro_produces_the_reports_and_the_registered_model(project):
    root, env, _, first = project
    for stage in (
        "fetch",
        "prepare",
        "train@large",
        "train@small",
        "baselines@large",
        "interpolate",
        "evaluate",
        "train@holdout",
        "train-inverse",
        "calibrate@test",
        "calibrate@planted",
        "plant",
        "diagnose",
    ):
        assert f"Running stage '{stage}'" in first.stdout
    report = json.loads((root / "reports/surrogates_table.json").read_text())
    rows = report["trained_on_large"]
    headline = json.loads((root / "reports/surrogates.json").read_text())
    assert headline["n"] == 24 * 20 and len(headline) <= 15
    assert {"nn@large", "linear@large", "lightgbm@large"} <= set(rows)
    assert all(r["n_rows"] == 24 * 20 for r in rows.values())
    # nn trained on Large, on Small, and in the interpolation check
    assert (root / "reports/surrogates.md").read_text().count("| nn |") == 3
    # The registered champion answers through MLflow's pyfunc interface.
    code = (
        "import mlflow, pandas as pd; from femcal.tracking import input_example;"
        "from femcal.space import ParameterSpace;"
        f"mlflow.set_tracking_uri('sqlite:///{root}/mlruns/mlflow.db');"
        "m = mlflow.pyfunc.load_model('models:/ivd-rom-surrogate@champion');"
        f"s = ParameterSpace.from_json('{root}/data/prepared/parameter_space.json');"
        "p = m.predict(input_example(s)); assert len(p) == 4 and (p > 0).all(), p; print('ok')"
    )
    assert _run([sys.executable, "-c", code], root, env).stdout.strip().endswith("ok")
    # calibrate: the 64 Test specimens through the registered champion, inside the bounds.
    cal = json.loads((root / "reports/calibrate-test.json").read_text())
    assert cal["n"] == 64 and cal["failed"] == 0
    assert np.isfinite(cal["ref_mae_deg"])
    metrics = pd.read_csv(root / "reports/calibration/test/metrics.csv")
    assert len(metrics) == 64 and (metrics["exceedance"] == 0).all()
    assert len(list((root / "reports/calibration/test/plots").glob("*.png"))) == 3
    # diagnose: a verdict per planted specimen, named as the issue requires.
    diagnosis = json.loads((root / "reports/diagnosis/diagnosis.json").read_text())
    assert len(diagnosis) == 8
    names = {"none", "facet_contact", "ligament_tension", "neutral_zone", "unexplained"}
    names.add("outside_box")  # a disc the 5-epoch surrogate's box cannot reach
    # A verdict names every effect found, joined by "+", possibly ending in "+unexplained".
    assert all(set(d["verdict"].split("+")) <= names and d["ranking"] for d in diagnosis)
    # Output folders are all or nothing: each holds its run's marker, nothing staged is left.
    for folder in ("reports/calibration/test", "reports/diagnosis", "data/planted"):
        marker = json.loads((root / folder / ".femcal-run.json").read_text())
        assert marker["status"] == "complete" and marker["files"], folder
    staged = [
        p
        for top in ("reports", "data")
        for p in (root / top).rglob("*")
        if ".partial-" in p.name or ".previous-" in p.name or p.name.endswith(".femcal-lock")
    ]
    assert not staged, staged


def test_second_repro_runs_nothing_and_a_change_reruns_only_downstream(project):
    root, env, _, _ = project
    again = _run([BIN / "dvc", "repro"], root, env)
    assert "Running stage" not in again.stdout, again.stdout
    # The markers inside the output folders are in .dvcignore: DVC sees nothing to do.
    status = _run([BIN / "dvc", "status"], root, env)
    assert "Data and pipelines are up to date" in status.stdout, status.stdout
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["train"]["small"]["fixed"]["max_epochs"] = 4
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    changed = _run([BIN / "dvc", "repro"], root, env)
    ran = {
        line.split("'")[1]
        for line in changed.stdout.splitlines()
        if line.startswith("Running stage")
    }
    assert ran == {"train@small", "evaluate"}, changed.stdout


def test_teammate_pulls_data_and_models_and_has_nothing_to_run(project, tmp_path):
    """The owner shares through a folder remote; a teammate clones, pulls, and calibrates and
    diagnoses with the pulled models: no MLflow store of the owner's, no tracking server."""
    root, env, git, _ = project
    remote = tmp_path / "remote"
    _run(["make", "remote", f"DIR={remote}"], root, env)  # the README's command
    assert f"url = {remote}" in (root / ".dvc/config").read_text()
    _run([BIN / "dvc", "push"], root, env)
    _run([*git, "add", "-A"], root, env)
    _run([*git, "commit", "-qm", "results"], root, env)
    clone = tmp_path / "clone"
    _run(["git", "clone", "-q", str(root), str(clone)], tmp_path, env)
    clone_env = {**env, "FEMCAL_DATA_MIRROR": ""}
    _run([BIN / "dvc", "pull"], clone, clone_env)
    assert (clone / "models/surrogate-large").is_dir()
    assert (clone / "data/prepared/test.csv").is_file()
    status = _run([BIN / "dvc", "repro"], clone, clone_env)
    assert "Running stage" not in status.stdout, status.stdout

    # The teammate's MLflow store is new and empty; the clone has no mlruns/.
    assert not (clone / "mlruns").exists()
    store = tmp_path / "teammate-store"
    store.mkdir()
    uri = f"sqlite:///{store / 'mlflow.db'}"
    team_env = {**clone_env, "MLFLOW_TRACKING_URI": uri}
    cal = _run(
        [BIN / "femcal", "calibrate", "--measurements", "data/raw/Test", "--out", "mine/cal"],
        clone,
        team_env,
    )
    assert "calibrated 64 specimens with pgd against models/surrogate-large" in cal.stdout
    assert len(pd.read_csv(clone / "mine/cal/metrics.csv")) == 64
    diag = _run([BIN / "femcal", "diagnose", "--out", "mine/diag"], clone, team_env)
    assert "diagnosed 8 specimens" in diag.stdout, diag.stdout
    assert not (clone / "mlruns").exists()
    # Plain MLflow loads the pulled folder too (and serves it: tests/test_tracking_serve.py).
    # The bytecode that writes into the folder's code/ is no change for DVC (.dvcignore).
    code = (
        "import mlflow; m = mlflow.pyfunc.load_model('models/surrogate-large');"
        "import femcal; from femcal.tracking import input_example;"  # the folder's femcal
        "from femcal.space import ParameterSpace;"
        "s = ParameterSpace.from_json('data/prepared/parameter_space.json');"
        "p = m.predict(input_example(s)); assert len(p) == 4 and (p > 0).all(), p;"
        "print(femcal.__file__)"
    )
    bytecode_env = {k: v for k, v in team_env.items() if k != "PYTHONDONTWRITEBYTECODE"}
    where = _run([sys.executable, "-c", code], clone, bytecode_env).stdout.strip()
    assert where.endswith("models/surrogate-large/code/femcal/__init__.py"), where
    assert list((clone / "models/surrogate-large/code").rglob("__pycache__"))
    status = _run([BIN / "dvc", "status"], clone, clone_env)
    assert "Data and pipelines are up to date" in status.stdout, status.stdout

    # Every run names the model that ran: the pulled folder's hash, the owner's version.
    from mlflow import MlflowClient

    from femcal.tracking import folder_sha256

    folder = clone / "models/surrogate-large"
    record = json.loads((folder / "mlflow.json").read_text())
    version = f"{record['registered_model']}/{record['version']}"
    runs = {
        r.data.tags["femcal.stage"]: r.data.tags
        for r in MlflowClient(tracking_uri=uri).search_runs(
            [MlflowClient(tracking_uri=uri).get_experiment_by_name("femcal-ivd").experiment_id]
        )
    }
    assert set(runs) == {"calibrate", "diagnose"}
    for tags in runs.values():
        assert tags["femcal.model.uri"] == "models/surrogate-large"
        assert tags["femcal.model.sha256"] == folder_sha256(folder)
        assert tags["femcal.model.version"] == version == "ivd-rom-surrogate/1"
    holdout = clone / "models/surrogate-holdout"
    assert runs["calibrate"]["femcal.holdout.sha256"] == folder_sha256(holdout)
    # The owner's calibrate stage ran the same model (its own store, same hash).
    owner = MlflowClient(tracking_uri=f"sqlite:///{root / 'mlruns' / 'mlflow.db'}")
    owner_runs = owner.search_runs(
        [owner.get_experiment_by_name("femcal-ivd").experiment_id],
        filter_string="tags.`femcal.stage` = 'calibrate'",
    )
    assert {r.data.tags["femcal.model.sha256"] for r in owner_runs} == {folder_sha256(folder)}
