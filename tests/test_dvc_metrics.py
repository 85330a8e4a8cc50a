"""``dvc metrics show`` stays narrow: every metrics file holds keys of one shared vocabulary.

DVC prints one table for the whole repository (a row per metrics file of every dvc.yaml, a
column per key of any of them); the committed metrics files are read through DVC's own API
and rendered as ``dvc metrics show`` renders them, without running any stage.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

from femcal.dvc_metrics import (
    MAX_WIDTH,
    SOURCES,
    VOCABULARY,
    MetricsFileError,
    details_path,
    headline,
    run_path,
    split_run,
    write,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def metrics():
    """``dvc metrics show``'s data of this checkout (the workspace), as DVC's API returns it."""
    from dvc.repo import Repo

    with Repo(str(ROOT)) as repo:
        return repo.metrics.show()


@pytest.fixture(scope="module")
def shown(metrics):
    """Path of each metrics file -> its content (None where DVC could not read it)."""
    (data,) = (rev["data"] for rev in metrics.values())  # the workspace only
    return {path: entry.get("data") for path, entry in data.items()}


def test_dvc_metrics_show_fits_200_characters(metrics, shown):
    from dvc.compare import metrics_table

    assert shown, "no metrics file declared"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):  # rendered as `dvc metrics show` renders it
        metrics_table(metrics, precision=5, round_digits=True).render()
    lines = printed.getvalue().splitlines()
    width = max(len(line) for line in lines)
    assert width <= MAX_WIDTH, f"dvc metrics show is {width} characters wide:\n" + "\n".join(
        line[:MAX_WIDTH] for line in lines[:3]
    )


def test_every_metrics_file_holds_flat_vocabulary_keys(shown):
    shown = {p: d for p, d in shown.items() if d is not None}  # a stage not run yet: no file
    wrong = {
        path: sorted(set(data) - set(VOCABULARY))
        for path, data in shown.items()
        if set(data) - set(VOCABULARY)
    }
    assert not wrong, f"keys outside femcal.dvc_metrics.VOCABULARY: {wrong}"
    nested = [p for p, d in shown.items() for v in d.values() if isinstance(v, (dict, list))]
    assert not nested, f"nested values in {nested}"


def test_headline_maps_each_kind_onto_the_vocabulary(tmp_path):
    figures = {
        "mae_deg": 0.0066,
        "holdout_mae_deg": float("nan"),
        "r2_mean": 0.9999,
        "n_specimens": 64,
        "n_r2_negative": 1,
        "n_beyond_noise": 2,
        "n_outside_bounds": 0,
        "seconds": 0.238,
        "determined": {"E": 0.5},
        "mae_deg_Flexion": 0.01,
    }
    assert headline("calibrate", figures) == {
        "mae_deg": 0.0066,
        "r2": 0.9999,
        "n": 64,
        "flagged": 3,
        "failed": 0,
    }
    assert all(set(keys) <= set(VOCABULARY) for keys in SOURCES.values())
    nested = {"idp_head": {"mae_mpa": 0.004}, "fe_mae_deg": 0.07, "fe_predictive": {"a": 1}}
    assert headline("validate", nested) == {"mae_deg": 0.07, "mae_mpa": 0.004}
    path = tmp_path / "reports" / "validate.json"
    write(path, "validate", nested, details=True)
    assert json.loads(path.read_text()) == {"mae_deg": 0.07, "mae_mpa": 0.004}
    assert json.loads(details_path(path).read_text()) == nested
    assert details_path(path).name == "validate.details.json"
    with pytest.raises(MetricsFileError, match="No DVC metrics mapping for stage kind 'nope'"):
        headline("nope", figures)


def test_the_run_figures_go_to_the_run_record_not_to_the_hashed_files(tmp_path):
    """Wall time and run id describe the run: a rebuild from the same inputs writes the same
    metrics file and report, and the run record (not versioned) holds them."""
    figures = {"val_mae_deg": 0.08, "n_trials": 5, "seconds": 1875.7, "mlflow_run_id": "abc"}
    path = tmp_path / "reports" / "metrics" / "train-large.json"
    head = write(path, "train", figures, details=True)
    assert head == {"mae_deg": 0.08, "n": 5} == json.loads(path.read_text())
    assert json.loads(details_path(path).read_text()) == {"val_mae_deg": 0.08, "n_trials": 5}
    assert run_path(path) == tmp_path / "reports" / "train-large.run.json"
    assert json.loads(run_path(path).read_text()) == {"seconds": 1875.7, "mlflow_run_id": "abc"}
    again = dict(figures, seconds=12.0, mlflow_run_id="def")
    before = path.read_bytes(), details_path(path).read_bytes()
    write(path, "train", again, details=True)
    assert (path.read_bytes(), details_path(path).read_bytes()) == before
    assert run_path("reports/calibrate-test.json") == Path("reports/calibrate-test.run.json")
    assert split_run({"a": 1, "seconds": 2}) == ({"a": 1}, {"seconds": 2})


def test_a_metrics_folder_puts_the_details_at_the_report_name():
    """The FE pipeline keeps its metrics in reports/metrics/ and each report by its name."""
    assert details_path("reports/metrics/train-large.json") == Path("reports/train-large.json")
    assert details_path("reports/sigma.json") == Path("reports/sigma.details.json")
