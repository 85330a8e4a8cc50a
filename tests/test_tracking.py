"""The registered model's interface, through a real temporary MLflow store and registry."""

import mlflow
import numpy as np
import pytest

from femcal.errors import ConfigError, ModelRegistryError
from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import (
    champion_version,
    configure_tracking,
    ensure_experiment,
    input_example,
    load_surrogate,
    log_surrogate,
    register_and_promote,
)

from synth import study_space, tidy_table


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
