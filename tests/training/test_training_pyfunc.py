"""One MLflow model-from-code mechanism for every femcal model; older saved models still load."""

from __future__ import annotations

import json

import mlflow
import numpy as np
import pandas as pd
import pytest

from femcal.errors import UntrustedArtifactError
from femcal.inverse import InverseModel, load_inverse, log_inverse
from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import input_example, log_surrogate
from femcal.training.pyfunc import LOADER_FILE, model_requirements, trusted_loader

from synth import study_space, tidy_table

MOMENTS = [1.0, 2.0, 3.0, 4.0, 5.0]

#: The entry points femcal wrote before femcal.training.pyfunc (as in models/ on disk).
LEGACY_SURROGATE_ENTRY = """
import mlflow

from femcal.tracking import SurrogatePyfunc

mlflow.models.set_model(SurrogatePyfunc())
"""
LEGACY_INVERSE_ENTRY = """
import mlflow
import pandas as pd

from femcal.calibration.inverse import InverseModel


class InversePyfunc(mlflow.pyfunc.PythonModel):
    def load_context(self, context):
        self.model = InverseModel.load(context.artifacts["inverse"])

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        return self.model.predict_frame(model_input)


mlflow.models.set_model(InversePyfunc())
"""


@pytest.fixture(scope="module")
def surrogate() -> NeuralSurrogate:
    table = tidy_table(16, seed=0)
    model = NeuralSurrogate(study_space(), hidden=(8,), max_epochs=2, batch_size=16, seed=0)
    return model.fit(table, table["rom_deg"].to_numpy())


@pytest.fixture(scope="module")
def inverse() -> InverseModel:
    rng = np.random.default_rng(0)
    rom = np.exp(rng.normal(size=(200, 4, 5)))
    unit = rng.random((200, study_space().dim))
    model = InverseModel(study_space(), hidden=(8,), max_epochs=2, seed=0)
    return model.fit(rom, unit, moments=MOMENTS)


def _rom_frame(model: InverseModel, n: int = 3) -> pd.DataFrame:
    rom = np.exp(np.random.default_rng(1).normal(size=(n, 20)))
    return pd.DataFrame(rom, columns=model.rom_columns())


def test_both_kinds_log_through_one_entry_point(store, surrogate, inverse) -> None:
    with mlflow.start_run():
        s_info = log_surrogate(surrogate, study_space(), name="s")
        i_info = log_inverse(inverse, name="i")
    for info, kind, obj in ((s_info, "surrogate", surrogate), (i_info, "inverse", inverse)):
        local = mlflow.artifacts.download_artifacts(info.model_uri, dst_path=str(store / kind))
        record = json.loads((store / kind / "artifacts" / kind / LOADER_FILE).read_text())
        assert record == {"loader": f"{type(obj).__module__}:{type(obj).__qualname__}"}
        assert (store / kind / "pyfunc_model.py").is_file()
        reqs = (store / kind / "requirements.txt").read_text().split()
        assert reqs == model_requirements()
        assert local
    frame = input_example(study_space())
    np.testing.assert_allclose(
        mlflow.pyfunc.load_model(s_info.model_uri).predict(frame), surrogate.predict(frame)
    )
    rows = _rom_frame(inverse)
    out = mlflow.pyfunc.load_model(i_info.model_uri).predict(rows)
    pd.testing.assert_frame_equal(out, inverse.predict_frame(rows))
    np.testing.assert_array_equal(
        load_inverse(i_info.model_uri).predict(np.asarray(rows).reshape(3, 4, 5)),
        inverse.predict(np.asarray(rows).reshape(3, 4, 5)),
    )


def test_models_logged_before_the_move_still_load(store, surrogate, inverse) -> None:
    """Their entry points import femcal.tracking.SurrogatePyfunc and
    femcal.calibration.inverse.InverseModel; the inverse one has no femcal_loader.json."""
    (store / "legacy_surrogate.py").write_text(LEGACY_SURROGATE_ENTRY)
    (store / "inverse_pyfunc_model.py").write_text(LEGACY_INVERSE_ENTRY)
    surrogate.save(store / "surrogate")
    (store / "surrogate" / LOADER_FILE).write_text(
        json.dumps({"loader": "femcal.surrogates.nn:NeuralSurrogate"}) + "\n"
    )
    inverse.save(store / "inverse")
    with mlflow.start_run():
        s_info = mlflow.pyfunc.log_model(
            name="s",
            python_model=str(store / "legacy_surrogate.py"),
            artifacts={"surrogate": str(store / "surrogate")},
            pip_requirements=[],  # loading is tested here, not MLflow's inferred requirements
        )
        i_info = mlflow.pyfunc.log_model(
            name="i",
            python_model=str(store / "inverse_pyfunc_model.py"),
            artifacts={"inverse": str(store / "inverse")},
            pip_requirements=[],
        )
    frame = input_example(study_space())
    np.testing.assert_allclose(
        mlflow.pyfunc.load_model(s_info.model_uri).predict(frame), surrogate.predict(frame)
    )
    rows = _rom_frame(inverse)
    pd.testing.assert_frame_equal(
        mlflow.pyfunc.load_model(i_info.model_uri).predict(rows), inverse.predict_frame(rows)
    )
    np.testing.assert_array_equal(
        load_inverse(i_info.model_uri).predict(np.asarray(rows).reshape(3, 4, 5)),
        inverse.predict(np.asarray(rows).reshape(3, 4, 5)),
    )


def test_a_loader_record_names_a_class_of_its_kind(tmp_path) -> None:
    record = tmp_path / LOADER_FILE
    record.write_text(json.dumps({"loader": "femcal.inverse.model:InverseModel"}))
    assert trusted_loader(record, kind="inverse") is InverseModel
    with pytest.raises(UntrustedArtifactError, match="not a registered femcal surrogate"):
        trusted_loader(record, kind="surrogate")
    record.write_text(json.dumps({"loader": "femcal.surrogates.nn:NeuralSurrogate"}))
    assert trusted_loader(record, kind="surrogate") is NeuralSurrogate
    with pytest.raises(UntrustedArtifactError, match="not femcal's inverse model"):
        trusted_loader(record, kind="inverse")
    record.write_text(json.dumps({"loader": "os:system"}))
    with pytest.raises(UntrustedArtifactError, match="refuses to import it"):
        trusted_loader(record, kind="inverse")
