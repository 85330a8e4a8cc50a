"""The registered model's interface, through a real temporary MLflow store and registry."""

import json
import subprocess
import sys
from pathlib import Path

import mlflow
import numpy as np
import pytest

from femcal.errors import ConfigError, ModelRegistryError, UntrustedArtifactError
from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import (
    RECORD_FILE,
    RUN_FILE,
    champion_version,
    configure_tracking,
    ensure_experiment,
    export_model,
    folder_sha256,
    input_example,
    load_surrogate,
    log_surrogate,
    open_model,
    portable_mlmodel,
    register_and_promote,
)
from femcal.training.pyfunc import (
    MODEL_REQUIREMENTS,
    PIPELINE_ONLY_REQUIREMENTS,
    model_requirements,
)

from synth import study_space, tidy_table

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    uri = configure_tracking(store_dir=tmp_path / "mlruns")
    assert uri == f"sqlite:///{(tmp_path / 'mlruns' / 'mlflow.db').resolve()}"
    ensure_experiment("test", store_dir=tmp_path / "mlruns")
    yield tmp_path
    mlflow.set_tracking_uri(None)


@pytest.fixture(scope="module")
def fitted():
    table = tidy_table(16, seed=0)
    model = NeuralSurrogate(
        study_space(), hidden=(16, 16), max_epochs=3, patience=3, batch_size=128, seed=0
    )
    return model.fit(table, table["rom_deg"].to_numpy()), table


def test_pyfunc_from_registry_matches_the_surrogate(store, fitted):
    model, table = fitted
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    version, promoted = register_and_promote(info.model_uri, name="m", val_metric=0.5)
    assert (version, promoted) == ("1", True)

    pyfunc = mlflow.pyfunc.load_model("models:/m@champion")
    frame = table[["load_case", "moment_nm", *study_space().names]]
    np.testing.assert_allclose(pyfunc.predict(frame), model.predict(frame), rtol=1e-6)
    assert pyfunc.metadata.signature is not None
    # The same model as a femcal object with a differentiable torch module.
    loaded = load_surrogate("models:/m@champion")
    np.testing.assert_allclose(loaded.predict(frame), model.predict(frame), rtol=1e-6)
    assert loaded.torch_module() is not None


def test_alias_moves_only_when_better(store, fitted):
    model, _ = fitted
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    assert register_and_promote(info.model_uri, name="m", val_metric=0.5) == ("1", True)
    assert register_and_promote(info.model_uri, name="m", val_metric=0.7) == ("2", False)
    assert str(champion_version("m").version) == "1"
    assert register_and_promote(info.model_uri, name="m", val_metric=0.3) == ("3", True)
    assert str(champion_version("m").version) == "3"


def test_non_finite_metric_refused(store, fitted):
    with pytest.raises(ConfigError, match="non-finite validation metric: nan"):
        register_and_promote("runs:/x/model", name="m", val_metric=float("nan"))


def test_missing_model_is_a_clear_error(store):
    with pytest.raises(ModelRegistryError, match="Could not load the model 'models:/nope@"):
        load_surrogate("models:/nope@champion")
    assert champion_version("nope") is None


def test_env_var_overrides_store(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'team.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    assert configure_tracking(store_dir=tmp_path / "unused") == uri
    assert not (tmp_path / "unused").exists()
    mlflow.set_tracking_uri(None)


def test_input_example_is_valid():
    ex = input_example(study_space())
    assert list(ex.columns) == ["load_case", "moment_nm", *study_space().names]
    assert len(ex) == 4


# ------------------------------------------------------------- the model folder DVC versions
@pytest.fixture
def folder(store, fitted):
    """A logged, registered surrogate exported as the train stage does (models/surrogate-*)."""
    model, _ = fitted
    with mlflow.start_run() as run:
        info = log_surrogate(model, study_space())
    version, _ = register_and_promote(info.model_uri, name="m", val_metric=0.5)
    record = {"registered_model": "m", "version": version}
    provenance = {"run_id": run.info.run_id, "model_uri": info.model_uri}
    dest = store / "models" / "surrogate-large"
    return export_model(info.model_uri, dest, record=record, run=provenance)


def test_two_loggings_of_one_model_export_the_same_files(folder, fitted, tmp_path):
    """MLmodel keeps what loads the model, not the run, time or machine that logged it; the
    run goes to RUN_FILE, which .dvcignore leaves out of DVC's hashes."""
    model, _ = fitted
    with mlflow.start_run():
        again = export_model(log_surrogate(model, study_space()).model_uri, tmp_path / "again")
    text = (folder / "MLmodel").read_text()
    for key in ("run_id", "model_id", "model_uuid", "utc_time_created", "artifact_path", "uri"):
        assert f"{key}:" not in text.replace("artifact_path: input_example", "")
    assert "model_code_path: pyfunc_model.py" in text
    assert (folder / "MLmodel").read_bytes() == (again / "MLmodel").read_bytes()
    assert folder_sha256(folder) == folder_sha256(again)
    assert json.loads((folder / RUN_FILE).read_text())["run_id"]
    assert RUN_FILE in (ROOT / ".dvcignore").read_text().split()
    assert portable_mlmodel(text) == text


def test_two_loggings_of_one_model_hash_alike_for_dvc(folder, fitted, tmp_path, monkeypatch):
    """DVC, with the project's .dvcignore, hashes the exported folders of two runs alike: the
    model folder a fresh clone rebuilds matches the lock."""
    import shutil

    from dvc.repo import Repo

    model, _ = fitted
    record = json.loads((folder / RECORD_FILE).read_text())
    with mlflow.start_run() as run:
        info = log_surrogate(model, study_space())
    again = export_model(
        info.model_uri, tmp_path / "again", record=record, run={"run_id": run.info.run_id}
    )
    assert (again / RUN_FILE).read_text() != (folder / RUN_FILE).read_text()
    root = tmp_path / "repo"
    root.mkdir()
    (root / ".dvcignore").write_text((ROOT / ".dvcignore").read_text())
    Repo.init(str(root), no_scm=True)
    monkeypatch.chdir(root)
    digests = []
    for source in (folder, again):
        shutil.copytree(source, root / "model")
        with Repo(str(root)) as repo:
            repo.add("model", no_commit=True)
        digests.append((root / "model.dvc").read_text())
        shutil.rmtree(root / "model")
        (root / "model.dvc").unlink()
    assert digests[0] == digests[1]


def test_exported_folder_is_a_complete_mlflow_model(folder, fitted):
    model, table = fitted
    frame = table[["load_case", "moment_nm", *study_space().names]]
    # Plain MLflow loads the folder; femcal loads it as its own object, without a store.
    pyfunc = mlflow.pyfunc.load_model(str(folder))
    np.testing.assert_allclose(pyfunc.predict(frame), model.predict(frame), rtol=1e-6)
    loaded = load_surrogate(str(folder))
    np.testing.assert_allclose(loaded.predict(frame), model.predict(frame), rtol=1e-6)
    assert loaded.torch_module() is not None
    # It carries femcal's code (no bytecode) and femcal's dependencies, not femcal itself.
    assert (folder / "code" / "femcal" / "tracking.py").is_file()
    assert not list((folder / "code").rglob("__pycache__"))
    reqs = (folder / "requirements.txt").read_text().split()
    assert reqs == model_requirements()
    names = {r.split("==")[0].lower() for r in reqs}
    assert {r.lower() for r in MODEL_REQUIREMENTS} <= names
    assert not names & ({"femcal"} | PIPELINE_ONLY_REQUIREMENTS)
    assert all("+" not in r for r in reqs)  # torch==X, never X+cpu


def test_folder_and_registry_name_the_same_model(folder):
    local, registered = open_model(str(folder)), open_model("models:/m@champion")
    assert local.path == folder and local.version == registered.version == "m/1"
    assert local.sha256 == registered.sha256 == folder_sha256(folder)
    assert local.tags("model") == {
        "femcal.model.uri": str(folder),
        "femcal.model.sha256": local.sha256,
        "femcal.model.version": "m/1",
    }
    # femcal's training record is not part of the model; any model file is.
    (folder / RECORD_FILE).write_text(json.dumps({"registered_model": None, "version": None}))
    assert open_model(str(folder)).sha256 == local.sha256
    assert open_model(folder).sha256 == local.sha256  # a pathlib.Path works as well
    assert open_model(folder.as_uri()).version is None
    assert open_model(str(folder)).tags("m")["femcal.m.version"] == "unknown"
    (folder / "artifacts" / "surrogate" / "config.json").write_text("{}")
    assert folder_sha256(folder) != local.sha256


def test_loading_the_folder_in_a_fresh_process_needs_only_its_requirements(folder, fitted):
    """No pipeline tool is imported; femcal comes from the folder's code (as in a fresh env)."""
    _, table = fitted
    before = folder_sha256(folder)
    rows = table[["load_case", "moment_nm", *study_space().names]].head(3)
    code = (
        "import sys, json, importlib.metadata as md, mlflow, pandas as pd\n"
        f"m = mlflow.pyfunc.load_model({str(folder)!r})\n"
        f"rows = pd.DataFrame(json.loads({json.dumps(rows.to_dict(orient='list'))!r}))\n"
        "print(json.dumps(m.predict(rows).tolist()))\n"
        "import femcal; print(femcal.__file__)\n"
        "top = {n.split('.')[0] for n in sys.modules}; dists = md.packages_distributions()\n"
        "print(json.dumps(sorted({d for n in top for d in dists.get(n, [])})))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=folder.parent
    )
    predicted, where, imported = proc.stdout.strip().splitlines()[-3:]
    assert where.startswith(str(folder / "code" / "femcal"))
    np.testing.assert_allclose(json.loads(predicted), load_surrogate(str(folder)).predict(rows))
    imported = {d.lower() for d in json.loads(imported)}
    assert not imported & PIPELINE_ONLY_REQUIREMENTS, imported
    # Bytecode such a process may write into the folder is left out of the content hash.
    cache = folder / "code" / "femcal" / "__pycache__"
    cache.mkdir(exist_ok=True)
    (cache / "tracking.cpython-311.pyc").write_bytes(b"\0")
    assert folder_sha256(folder) == before


def test_local_folder_errors(store, fitted, tmp_path, monkeypatch):
    model, _ = fitted
    monkeypatch.chdir(tmp_path)
    with pytest.raises(
        ModelRegistryError,
        match=r"The model folder 'models/surrogate-large' does not exist \(looked in .*\)\. "
        r"Fetch it with `dvc pull models/surrogate-large`",
    ):
        load_surrogate("models/surrogate-large")
    (tmp_path / "weights.pt").write_bytes(b"")
    with pytest.raises(ModelRegistryError, match=r"The model 'weights\.pt' is a file; give"):
        load_surrogate("weights.pt")
    model.save(tmp_path / "old")  # a folder of the train stage before models were MLflow models
    with pytest.raises(
        ModelRegistryError,
        match=r"'old' is not a femcal surrogate \(no femcal_loader\.json in old\)\. .*dvc repro",
    ):
        load_surrogate("old")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(
        ModelRegistryError, match=r"Cannot export the model 'runs:/x/m' to .*full: it exists and"
    ):
        export_model("runs:/x/m", tmp_path / "full")


def test_local_folder_keeps_the_trust_rules(folder, tmp_path):
    """A folder's loader may only name a registered class; nothing else is imported from it."""
    loader = folder / "artifacts" / "surrogate" / "femcal_loader.json"
    loader.write_text(json.dumps({"loader": "os:system"}))
    with pytest.raises(
        UntrustedArtifactError,
        match=r"femcal_loader\.json of the model '.*surrogate-large' names the class 'os:system', "
        "which is not a registered femcal surrogate",
    ):
        load_surrogate(str(folder))
    loader.write_text("[]")
    with pytest.raises(ModelRegistryError, match=r"surrogate-large': not a femcal loader record"):
        load_surrogate(str(folder))


def test_store_elsewhere_keeps_its_artifacts_beside_it(tmp_path, monkeypatch):
    """MLFLOW_TRACKING_URI=sqlite:///elsewhere: no mlruns/ appears in the project."""
    project, team = tmp_path / "project", tmp_path / "team"
    project.mkdir()
    monkeypatch.chdir(project)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{team / 'mlflow.db'}")
    team.mkdir()
    configure_tracking(store_dir="mlruns")
    ensure_experiment("x", store_dir="mlruns")
    with mlflow.start_run() as run:
        mlflow.log_text("hello", "note.txt")
    assert run.info.artifact_uri.startswith((team / "artifacts").as_uri())
    assert not (project / "mlruns").exists()
    mlflow.set_tracking_uri(None)
