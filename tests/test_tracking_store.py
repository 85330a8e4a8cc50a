"""The default MLflow store follows its folder; saved models name only trusted classes.

Real MLflow, SQLite store and registry in temporary folders; a tiny real surrogate.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import sys
from pathlib import Path

import mlflow
import numpy as np
import pytest

import femcal.surrogates.base as surrogate_base
from femcal.errors import ConfigError, ModelRegistryError, UntrustedArtifactError
from femcal.surrogates.base import trusted_surrogate_class, trusted_surrogate_classes
from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import (
    configure_tracking,
    ensure_experiment,
    load_surrogate,
    log_surrogate,
    register_and_promote,
)
from femcal.tracking_store import relocate_store

from synth import study_space, tidy_table


@pytest.fixture(scope="module")
def fitted():
    table = tidy_table(12, seed=0)
    model = NeuralSurrogate(
        study_space(), hidden=(8, 8), max_epochs=2, patience=2, batch_size=128, seed=0
    )
    frame = table[["load_case", "moment_nm", *study_space().names]]
    return model.fit(table, table["rom_deg"].to_numpy()), frame


@pytest.fixture
def no_env(monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    yield
    mlflow.set_tracking_uri(None)


def _locations(db: Path) -> list[str]:
    """Every artifact location MLflow recorded in the store."""
    with sqlite3.connect(db) as con:
        rows = con.execute(
            "SELECT artifact_location FROM experiments UNION ALL "
            "SELECT artifact_uri FROM runs UNION ALL "
            "SELECT artifact_location FROM logged_models UNION ALL "
            "SELECT storage_location FROM model_versions UNION ALL "
            "SELECT source FROM model_versions"
        ).fetchall()
    return [r[0] for r in rows if r[0]]


def test_moved_project_logs_and_loads_in_its_own_store(tmp_path, monkeypatch, no_env, fitted):
    model, frame = fitted
    old, new = tmp_path / "checkout", tmp_path / "moved" / "checkout"
    old.mkdir()
    monkeypatch.chdir(old)  # the project root; the store is the relative "mlruns"
    configure_tracking(store_dir="mlruns")
    ensure_experiment("femcal-ivd", store_dir="mlruns")
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    assert register_and_promote(info.model_uri, name="m", val_metric=0.5) == ("1", True)
    assert any(str(old) in loc for loc in _locations(old / "mlruns" / "mlflow.db"))
    mlflow.set_tracking_uri(None)

    new.parent.mkdir()
    monkeypatch.chdir(tmp_path)
    shutil.move(old, new)  # the original path is gone: nothing can be read from or written to it
    monkeypatch.chdir(new)
    configure_tracking(store_dir="mlruns")
    exp_id = ensure_experiment("femcal-ivd", store_dir="mlruns")
    store = new / "mlruns"
    assert mlflow.get_experiment(exp_id).artifact_location == (store / "artifacts").as_uri()
    locations = _locations(store / "mlflow.db")
    assert locations and not any(str(old) + "/" in loc or str(old) == loc for loc in locations)
    assert all(str(store) in loc for loc in locations if loc.startswith(("/", "file:")))
    # Load the registered model (femcal object and pyfunc) from the new place ...
    np.testing.assert_allclose(
        load_surrogate("models:/m@champion").predict(frame), model.predict(frame), rtol=1e-6
    )
    pyfunc = mlflow.pyfunc.load_model("models:/m@champion")
    np.testing.assert_allclose(pyfunc.predict(frame), model.predict(frame), rtol=1e-6)
    # ... and log into it.
    with mlflow.start_run() as run:
        mlflow.log_dict({"moved": True}, "moved.json")
    assert run.info.artifact_uri.startswith((store / "artifacts").as_uri() + "/")
    assert (store / "artifacts" / run.info.run_id / "artifacts" / "moved.json").is_file()
    assert not old.exists()
    # The next start finds nothing to resolve.
    mlflow.set_tracking_uri(None)
    assert relocate_store(store) == {}


def test_copied_project_leaves_the_original_untouched(tmp_path, monkeypatch, no_env, fitted):
    model, frame = fitted
    orig, copy = tmp_path / "orig", tmp_path / "copy"
    orig.mkdir()
    monkeypatch.chdir(orig)
    configure_tracking(store_dir="mlruns")
    ensure_experiment("femcal-ivd", store_dir="mlruns")
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    register_and_promote(info.model_uri, name="m", val_metric=0.5)
    mlflow.set_tracking_uri(None)
    shutil.copytree(orig, copy)
    before = {p: p.read_bytes() for p in sorted(orig.rglob("*")) if p.is_file()}

    monkeypatch.chdir(copy)
    configure_tracking(store_dir="mlruns")
    ensure_experiment("femcal-ivd", store_dir="mlruns")
    with mlflow.start_run() as run:
        mlflow.log_dict({"copy": True}, "copy.json")
    load_surrogate("models:/m@champion").predict(frame)
    assert run.info.artifact_uri.startswith((copy / "mlruns").as_uri())
    after = {p: p.read_bytes() for p in sorted(orig.rglob("*")) if p.is_file()}
    assert after == before  # not one byte of the original changed, no file added


def test_store_elsewhere_is_not_rewritten(tmp_path, monkeypatch, no_env):
    """Only the default store is resolved; an experiment with its own artifact root stays."""
    monkeypatch.chdir(tmp_path)
    configure_tracking(store_dir="mlruns")
    elsewhere = (tmp_path / "bucket" / "artifacts").as_uri()
    mlflow.create_experiment("custom", artifact_location=elsewhere)
    mlflow.set_tracking_uri(None)
    assert relocate_store("mlruns") == {}
    assert relocate_store(tmp_path / "no-store") == {}
    configure_tracking(store_dir="mlruns")
    assert mlflow.get_experiment_by_name("custom").artifact_location == elsewhere


# ------------------------------------------------------------------ trusted loader classes
def _log_with_loader(model, loader: object) -> str:
    """Log ``model`` as a run artifact whose femcal_loader.json names ``loader``."""
    with mlflow.start_run() as run:
        info = log_surrogate(model, study_space())
    local = Path(mlflow.artifacts.download_artifacts(artifact_uri=info.model_uri))
    (file,) = local.rglob("femcal_loader.json")
    file.write_text(json.dumps({"loader": loader}) if loader is not None else "{oops")
    with mlflow.start_run(run_id=run.info.run_id):
        mlflow.log_artifacts(str(file.parent), "tampered")
    return f"runs:/{run.info.run_id}/tampered"


@pytest.fixture
def store(tmp_path, no_env):
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("test", store_dir=tmp_path / "mlruns")
    return tmp_path


def test_loader_naming_os_system_is_refused_without_import(store, fitted, monkeypatch):
    model, frame = fitted
    uri = _log_with_loader(model, "os:system")
    with pytest.raises(
        UntrustedArtifactError,
        match=r"femcal_loader\.json of the model 'runs:/\w+/tampered' names the class "
        r"'os:system', which is not a registered femcal surrogate",
    ):
        load_surrogate(uri)
    # A module with an import-time side effect is never imported on the file's say-so.
    (store / "evil_mod.py").write_text(
        f"open({str(store / 'imported')!r}, 'w').close()\nclass Evil:\n    load = print\n"
    )
    monkeypatch.syspath_prepend(str(store))
    uri = _log_with_loader(model, "evil_mod:Evil")
    with pytest.raises(UntrustedArtifactError, match=r"'evil_mod:Evil'.*register it with"):
        load_surrogate(uri)
    assert not (store / "imported").exists() and "evil_mod" not in sys.modules
    # A real class that is not a registered surrogate is refused too.
    uri = _log_with_loader(model, "sklearn.linear_model:LinearRegression")
    with pytest.raises(UntrustedArtifactError, match="LinearRegression'"):
        load_surrogate(uri)
    uri = _log_with_loader(model, None)
    with pytest.raises(ModelRegistryError, match=r"json of the model 'runs:/\w+/tampered': not a"):
        load_surrogate(uri)
    # The untampered model loads.
    uri = _log_with_loader(model, "femcal.surrogates.nn:NeuralSurrogate")
    np.testing.assert_allclose(load_surrogate(uri).predict(frame), model.predict(frame))


def test_baselines_log_and_load_through_the_trusted_loader(store, fitted):
    from femcal.surrogates import make_surrogate

    _, frame = fitted
    table = tidy_table(12, seed=0)
    model = make_surrogate("lightgbm", space=study_space()).fit(table, table["rom_deg"])
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    loaded = load_surrogate(info.model_uri)
    np.testing.assert_array_equal(loaded.predict(frame), model.predict(frame))


def _install_plugin(root: Path, entry: str) -> None:
    """A distribution on sys.path with an entry point in the group femcal.surrogates."""
    (root / "femcal_plugin_demo.py").write_text(
        "from femcal.surrogates.nn import NeuralSurrogate\n\n"
        "class DemoSurrogate(NeuralSurrogate):\n    pass\n"
    )
    info = root / "femcal_plugin_demo-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: femcal-plugin-demo\nVersion: 0.1\n"
    )
    (info / "entry_points.txt").write_text(f"[femcal.surrogates]\n{entry}\n")


@pytest.fixture
def clean_registry():
    registry = surrogate_base.surrogate_registry
    registry.load()
    state = registry.snapshot()
    registry.rescan_plugins()
    yield
    registry.restore(state)
    sys.modules.pop("femcal_plugin_demo", None)


def test_entry_point_plugins_are_trusted(tmp_path, monkeypatch, clean_registry):
    spec = "femcal_plugin_demo:DemoSurrogate"
    with pytest.raises(UntrustedArtifactError, match="'femcal_plugin_demo:DemoSurrogate'"):
        trusted_surrogate_class(spec, source="model/femcal_loader.json")
    _install_plugin(tmp_path, f"demo = {spec}")
    monkeypatch.syspath_prepend(str(tmp_path))
    surrogate_base.surrogate_registry.rescan_plugins()  # as in a fresh process
    cls = trusted_surrogate_class(spec, source="model/femcal_loader.json")
    assert cls.__name__ == "DemoSurrogate" and spec in trusted_surrogate_classes()
    assert "femcal.surrogates.nn:NeuralSurrogate" in trusted_surrogate_classes()


def test_broken_entry_point_plugin_is_named(tmp_path, monkeypatch, clean_registry):
    _install_plugin(tmp_path, "demo = femcal_plugin_demo:Missing")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match=r"plugin 'demo = femcal_plugin_demo:Missing'.*failed"):
        trusted_surrogate_classes()


def test_a_model_folder_loads_without_mlflow_or_the_model_zoo(store, fitted, tmp_path):
    """``femcal calibrate`` on models/surrogate-large: the network's loader alone."""
    import subprocess

    from femcal.tracking import export_model

    model, frame = fitted
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    folder = export_model(info.model_uri, tmp_path / "surrogate-large", record={})
    heavy = ("mlflow", "lightgbm", "sklearn.compose", "femcal.surrogates.baselines")
    code = (
        "import sys\n"
        "from femcal.tracking import load_surrogate, open_model\n"
        f"source = open_model({str(folder)!r})\n"
        "model = load_surrogate(source)\n"
        "print(type(model).__name__, source.sha256[:8])\n"
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == "[]", proc.stdout
    assert proc.stdout.startswith("NeuralSurrogate")
    # A class femcal's network module does not register is refused, as before.
    with pytest.raises(
        UntrustedArtifactError,
        match=r"names the class 'femcal\.surrogates\.nn:RomNet', which is not a registered",
    ):
        trusted_surrogate_class("femcal.surrogates.nn:RomNet", source="model/femcal_loader.json")
    # The model zoo's classes still resolve (their module imported alone).
    spec = "femcal.surrogates.baselines:LinearSurrogate"
    assert trusted_surrogate_class(spec, source="x").__name__ == "LinearSurrogate"
