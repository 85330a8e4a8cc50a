"""A small real CalculiX campaign (coarse mesh, two Dask workers), shared by the FE tests.

Every FE test runs the real solver (``ccx`` on PATH; ``make install`` installs it); none
fakes it. The shared campaign holds three configurations (one per split: Large, Small, Test)
x four load cases = 12 jobs. It is built once per test run: under pytest-xdist the first
worker that needs it runs it in the run's shared temporary folder, under a file lock, and the
others load its result (the tests only read the campaign's folder).
"""

from __future__ import annotations

import os
import pickle
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from fe_helpers import COARSE, MOMENTS, SPLITS

from femcal.fe.campaign import CampaignResult, run_campaign
from femcal.fe.design import split_design

from synth import study_space


@pytest.fixture(scope="package")
def coarse_campaign(tmp_path_factory) -> tuple[Path, object, CampaignResult]:
    """(folder, design, result) of the shared campaign; the store is ``folder/runs.jsonl``."""
    if shutil.which("ccx") is None:
        pytest.skip("CalculiX (ccx) is not installed; `make install`")
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return _run_coarse(tmp_path_factory.mktemp("campaign"))
    from filelock import FileLock

    folder = tmp_path_factory.getbasetemp().parent / "coarse-campaign"  # shared by the workers
    done = folder / "campaign.pickle"
    with FileLock(f"{folder}.lock"):
        if not done.exists():
            folder.mkdir(exist_ok=True)
            done.write_bytes(pickle.dumps(_run_coarse(folder)))
    return pickle.loads(done.read_bytes())


def _run_coarse(folder: Path) -> tuple[Path, object, CampaignResult]:
    design_df = split_design(study_space(), SPLITS, seed=1)  # all 12 jobs converge
    result = run_campaign(
        "calculix",
        COARSE,
        design_df,
        store=folder / "runs.jsonl",
        moments=MOMENTS,
        n_workers=2,
        scratch_dir=folder / "scratch",
        progress=False,
    )
    return folder, design_df, result


@pytest.fixture
def mlflow_store(tmp_path, monkeypatch) -> Iterator[Path]:
    """A temporary MLflow store ``tmp_path/mlruns`` with the experiment ``fe-test``.

    The test runs in ``tmp_path`` with no MLFLOW_TRACKING_URI from the environment; the
    tracking URI is reset afterwards. Returns the store's folder.
    """
    import mlflow

    from femcal.tracking import configure_tracking, ensure_experiment

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    store = tmp_path / "mlruns"
    configure_tracking(store_dir=store)
    ensure_experiment("fe-test", store_dir=store)
    yield store
    mlflow.set_tracking_uri(None)
