"""Relative paths: params.yaml's at the project root, the command line's at the current folder,
the stores' at the repository root, also from the temporary copy of ``dvc exp run --temp``."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from femcal.paths import (
    project_root,
    setting_path,
    setting_uri,
    store_path,
    store_root,
    store_url,
)

BIN = Path(sys.executable).parent


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A project folder with params.yaml, and another working directory beside it."""
    root = tmp_path / "proj"
    root.mkdir()
    (root / "params.yaml").write_text(yaml.safe_dump({"mlflow": {"store_dir": "mlruns"}}))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.delenv("DVC_ROOT", raising=False)
    return {"_path": str(root / "params.yaml")}, root, elsewhere


def test_settings_start_at_the_project_root_from_any_folder(project, monkeypatch):
    params, root, elsewhere = project
    assert project_root(params["_path"]) == root.resolve()
    monkeypatch.chdir(elsewhere)
    assert setting_path(params, "data/raw") == root.resolve() / "data/raw"
    assert setting_path(params, "/abs/data") == Path("/abs/data")
    assert setting_uri(params, "models/surrogate-large") == str(
        root.resolve() / "models/surrogate-large"
    )
    for uri in ("models:/ivd-rom-surrogate@champion", "runs:/abc/model", "s3://bucket/m"):
        assert setting_uri(params, uri) == uri
    # From the project root itself they stay as written (what runs record does not change).
    monkeypatch.chdir(root)
    assert setting_path(params, "data/raw") == Path("data/raw")
    assert setting_uri(params, "models/surrogate-large") == "models/surrogate-large"
    # A relative --params is relative to the current folder, like every command-line path.
    monkeypatch.chdir(elsewhere)
    rel = {"_path": "../proj/params.yaml"}
    assert setting_path(rel, "data") == root.resolve() / "data"


def test_stores_start_at_the_project_root_outside_dvc_experiments(project, monkeypatch):
    params, root, elsewhere = project
    monkeypatch.chdir(elsewhere)
    assert store_path(params, "mlruns") == root.resolve() / "mlruns"
    assert store_url(params, "sqlite:///mlruns/optuna.db") == (
        f"sqlite:///{root.resolve() / 'mlruns/optuna.db'}"
    )
    for url in ("sqlite:////abs/optuna.db", "postgresql://u:p@host/db", "sqlite:///:memory:"):
        assert store_url(params, url) == url
    # `dvc repro` sets DVC_ROOT to the repository the stage runs in: nothing moves.
    (root / ".dvc").mkdir()
    assert store_root(root, {"DVC_ROOT": str(root)}) == root.resolve()
    monkeypatch.chdir(root)
    assert store_url(params, "sqlite:///mlruns/optuna.db") == "sqlite:///mlruns/optuna.db"


def test_stores_of_a_temporary_experiment_copy_go_to_the_original_repository(tmp_path):
    repo = tmp_path / "repo"
    (repo / ".dvc").mkdir(parents=True)
    copy = repo / ".dvc" / "tmp" / "exps" / "standalone" / "tmpab12cd"
    (copy / ".dvc").mkdir(parents=True)
    (copy / "fe").mkdir()
    env = {"DVC_ROOT": str(repo)}
    assert store_root(copy, env) == repo.resolve()
    assert store_root(copy / "fe", env) == repo.resolve() / "fe"  # fe/params.yaml's folder
    params = {"_path": str(copy / "params.yaml")}
    assert store_path(params, "mlruns", env) == repo.resolve() / "mlruns"
    assert store_path(params, "/abs/store", env) == Path("/abs/store")
    assert store_url(params, "sqlite:///mlruns/optuna.db", env) == (
        f"sqlite:///{repo.resolve() / 'mlruns/optuna.db'}"
    )
    # Settings (data, models, outputs) stay in the copy: DVC collects the experiment there.
    assert setting_path(params, "data/raw") == copy.resolve() / "data/raw"
    # Without DVC_ROOT, or with another repository's, the copy is a project like any other.
    assert store_root(copy, {}) == copy.resolve()
    other = tmp_path / "other"
    (other / ".dvc").mkdir(parents=True)
    assert store_root(copy, {"DVC_ROOT": str(other)}) == copy.resolve()


def test_the_cli_reads_params_paths_from_the_project_root(project, monkeypatch, capsys):
    """`femcal --params ../proj/params.yaml prepare` from another folder: data in the project."""
    from femcal.cli import main

    params, root, elsewhere = project
    (root / "params.yaml").write_text("data: {raw_dir: data/raw, prepared_dir: data/prepared}\n")
    monkeypatch.chdir(elsewhere)
    assert main(["--params", "../proj/params.yaml", "prepare"]) == 2
    err = capsys.readouterr().err
    assert str(root.resolve() / "data" / "raw") in err  # looked for in the project, not here


def test_the_cli_puts_the_mlflow_store_at_the_project_root(project, monkeypatch):
    import mlflow

    from femcal.config import load_params
    from femcal.stages.store import tracking as _tracking

    _, root, elsewhere = project
    (root / "params.yaml").write_text(
        yaml.safe_dump({"mlflow": {"store_dir": "mlruns", "experiment": "paths-test"}})
    )
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(elsewhere)
    try:
        _tracking(load_params("../proj/params.yaml", validate=False))
        assert mlflow.get_tracking_uri() == f"sqlite:///{root.resolve() / 'mlruns/mlflow.db'}"
    finally:
        mlflow.set_tracking_uri(None)
    assert (root / "mlruns" / "mlflow.db").is_file() and (root / "mlruns" / "artifacts").is_dir()
    assert not (elsewhere / "mlruns").exists()


# ----------------------------------------------------------- dvc exp run --temp, for real
STAGE = """\
import os
import sqlite3

from femcal.config import load_params
from femcal.paths import store_path, store_url

params = load_params("params.yaml", validate=False)
store = store_path(params, params["mlflow"]["store_dir"])
store.mkdir(parents=True, exist_ok=True)
url = store_url(params, params["train"]["storage"])
db = sqlite3.connect(url[len("sqlite:///"):])
db.execute("CREATE TABLE IF NOT EXISTS runs (name TEXT, seed INTEGER, workspace TEXT)")
db.execute(
    "INSERT INTO runs VALUES (?, ?, ?)",
    (os.environ.get("DVC_EXP_NAME", ""), params["seed"], os.getcwd()),
)
db.commit()
with open("result.txt", "w") as f:
    f.write(f"{store}\\n{url}\\n")
"""


def _run(args, cwd, env):
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{args} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


def test_dvc_exp_run_temp_keeps_the_stores_in_the_repository(tmp_path):
    """The experiment runs in <repo>/.dvc/tmp/exps/...; its store rows land in <repo>/mlruns."""
    repo = tmp_path / "repo"
    repo.mkdir()
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("DVC_", "MLFLOW_", "FEMCAL_", "GIT_"))
    }
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["DVC_NO_ANALYTICS"] = "1"
    (repo / "params.yaml").write_text(
        yaml.safe_dump(
            {
                "seed": 1,
                "mlflow": {"store_dir": "mlruns"},
                "train": {"storage": "sqlite:///mlruns/optuna.db"},
            }
        )
    )
    (repo / "store_stage.py").write_text(STAGE)
    (repo / "dvc.yaml").write_text(
        yaml.safe_dump(
            {
                "stages": {
                    "store": {
                        "cmd": f"{sys.executable} store_stage.py",
                        "deps": ["store_stage.py"],
                        "params": ["seed"],
                        "outs": [{"result.txt": {"cache": False}}],
                    }
                }
            }
        )
    )
    (repo / ".gitignore").write_text("/mlruns/\n")
    for args in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "test@example.com"],
        ["git", "config", "user.name", "test"],
        [BIN / "dvc", "init", "-q"],
        ["git", "add", "-A"],
        ["git", "commit", "-q", "-m", "init"],
    ):
        _run(args, repo, env)
    start = time.perf_counter()
    _run([BIN / "dvc", "exp", "run", "--temp", "-S", "seed=2", "-n", "temp-exp"], repo, env)
    seconds = time.perf_counter() - start
    db_file = repo / "mlruns" / "optuna.db"
    assert db_file.is_file(), sorted(str(p.relative_to(repo)) for p in repo.rglob("*.db"))
    rows = sqlite3.connect(db_file).execute("SELECT name, seed, workspace FROM runs").fetchall()
    assert len(rows) == 1
    name, seed, workspace = rows[0]
    assert (name, seed) == ("temp-exp", 2)
    # It did run in DVC's temporary copy, which kept no store of its own.
    assert Path(workspace).resolve().is_relative_to((repo / ".dvc" / "tmp" / "exps").resolve())
    assert not [p for p in (repo / ".dvc").rglob("optuna.db")]
    assert not (repo / "result.txt").exists()  # the workspace itself was not touched
    # The experiment's result names the repository's store.
    shown = _run(["git", "show", "refs/exps/" + _exp_ref(repo, env) + ":result.txt"], repo, env)
    assert shown.stdout.splitlines()[0] == str((repo / "mlruns").resolve())
    assert seconds < 120


def _exp_ref(repo: Path, env) -> str:
    refs = _run(["git", "for-each-ref", "--format=%(refname)", "refs/exps/"], repo, env)
    (ref,) = [r for r in refs.stdout.split() if r.endswith("/temp-exp")]
    return ref.removeprefix("refs/exps/")
