"""A small fitted neural surrogate of the synthetic study, shared by the calibration tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from femcal.calibration import CurveModel, SurrogateCurveModel
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = (1.0, 2.0, 3.0, 4.0, 5.0)


@pytest.fixture(scope="package")
def small_surrogate() -> NeuralSurrogate:
    table = tidy_table(48, seed=3)
    model = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    )
    model.fit(table, table["rom_deg"].to_numpy())
    # one stated error at every moment: the weighting tests' arithmetic (the error by moment
    # and relative to the RoM: tests/test_moments.py and test_stage.py's own surrogate)
    model.val_error_profile_ = None
    return model


@pytest.fixture
def curve_model(small_surrogate: NeuralSurrogate) -> CurveModel:
    return SurrogateCurveModel(small_surrogate, MOMENTS)


@pytest.fixture
def truth(curve_model: CurveModel) -> tuple[np.ndarray, np.ndarray]:
    """Six configurations inside the box and their surrogate curves (exactly reachable)."""
    x = curve_model.space.sample_uniform(6, np.random.default_rng(11))
    return x, curve_model.predict(x)


@pytest.fixture(scope="package")
def registry_store(tmp_path_factory, small_surrogate) -> Path:
    """An MLflow store (its folder) where ``small_surrogate`` is the champion of
    ``ivd-rom-surrogate`` and of ``ivd-rom-surrogate-holdout``, built once: :func:`registry`
    gives each test a copy of it."""
    import mlflow

    from femcal.tracking import (
        configure_tracking,
        ensure_experiment,
        log_surrogate,
        register_and_promote,
    )

    store = tmp_path_factory.mktemp("registry") / "mlruns"
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        configure_tracking(store_dir=store)
        ensure_experiment("test", store_dir=store)
        for name in ("ivd-rom-surrogate", "ivd-rom-surrogate-holdout"):
            with mlflow.start_run():
                info = log_surrogate(small_surrogate, small_surrogate.space)
            register_and_promote(info.model_uri, name=name, val_metric=0.1)
        mlflow.set_tracking_uri(None)
    return store


@pytest.fixture
def registry(tmp_path, monkeypatch, registry_store):
    """A temporary MLflow store in ``tmp_path`` where ``small_surrogate`` is the champion of
    ``ivd-rom-surrogate`` and of ``ivd-rom-surrogate-holdout``: a copy of
    :func:`registry_store`, its artifact locations resolved to the copy by
    :func:`femcal.tracking.configure_tracking`; yields ``tmp_path``."""
    import mlflow

    from femcal.tracking import configure_tracking, ensure_experiment

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    shutil.copytree(registry_store, tmp_path / "mlruns")
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("test", store_dir=tmp_path / "mlruns")
    yield tmp_path
    mlflow.set_tracking_uri(None)


@pytest.fixture
def diagnosis_keywords(registry) -> dict:
    """The :class:`femcal.jobs.diagnose.DiagnosisJob` keywords the diagnosis tests share: the
    champion of ``registry``, output ``registry / "diag"``, noise 0.05 deg, ``neutral_zone`` the
    one candidate, no start bank, a quick search (``min_delta`` 10, seed 0), plots off, and the
    moment policy of the tests' stages (error growth 3.2, log ratio 0.51)."""
    return dict(
        out_dir=registry / "diag",
        model_uri="models:/ivd-rom-surrogate@champion",
        noise_deg=0.05,
        candidates=["neutral_zone"],
        start_bank=None,
        options={"min_delta": 10.0, "seed": 0},
        plots=False,
        error_growth=3.2,
        max_log_ratio=0.51,
    )
