"""A temporary MLflow store for the training toolkit's tests."""

from __future__ import annotations

import mlflow
import pytest

from femcal.tracking import configure_tracking, ensure_experiment


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A temporary MLflow store with the experiment ``training``; the URI is reset afterwards."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("training", store_dir=tmp_path / "mlruns")
    yield tmp_path
    mlflow.set_tracking_uri(None)
