"""Headline figures (the DVC metrics files) and the evaluate stage's plot tables."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from femcal.dvc_metrics import VOCABULARY
from femcal.errors import FemcalError
from femcal.evaluate import Score, prediction_table, training_curves, write_reports
from femcal.headlines import (
    CALIBRATION_KEYS,
    MAX_KEYS,
    HeadlineError,
    calibration_headline,
    diagnosis_headline,
    surrogate_headline,
)


def _calibration_figures() -> dict:
    return {
        "method": "pgd",
        "n_specimens": 4,
        "mae_deg": 0.01,
        "mae_deg_median": 0.01,
        "mae_deg_max": 0.02,
        "r2_mean": 0.999,
        "exceedance_max": 0.0,
        "n_outside_bounds": 0,
        "seconds": 0.5,
        "n_success": 4,
        "n_r2_negative": 0,
        "nit": 12,
        **{f"mae_deg_{lc}": 0.01 for lc in ("Flexion", "Extension")},
        "holdout_mae_deg": float("nan"),
        "range_width_mean": 0.7,
        "determined": {f"p{i}": i / 10 for i in range(13)},
        "n_outside_envelope": 0,
        "n_plotted": 4,
    }


def test_calibration_headline_is_flat_and_on_the_vocabulary():
    head = calibration_headline(_calibration_figures())
    assert set(head) <= set(VOCABULARY)
    # NaN (no held-out surrogate) is left out: "-" in dvc metrics show, valid JSON
    assert head == {"mae_deg": 0.01, "r2": 0.999, "n": 4, "flagged": 0, "failed": 0, "seconds": 0.5}
    # With a noise, the specimens the model does not explain within it are flagged
    # (summary.json keeps their median residual in sd).
    noisy = {**_calibration_figures(), "n_beyond_noise": 2, "rms_z_median": 0.9}
    assert calibration_headline(noisy)["flagged"] == 2
    json.dumps(head, allow_nan=False)


def test_every_calibration_headline_key_at_once_fits():
    # A calibration with every figure a headline can take (a held-out surrogate, ranges,
    # reachability and a noise) still fits the limit before it is mapped onto the vocabulary.
    figures = {**_calibration_figures(), "holdout_mae_deg": 0.02, "holdout_r2_mean": 0.99}
    figures.update({k: 1 for k in CALIBRATION_KEYS if k not in figures})
    head = calibration_headline(figures)
    assert head["ref_mae_deg"] == 0.02 and set(head) <= set(VOCABULARY)
    assert len(CALIBRATION_KEYS) + 1 <= MAX_KEYS


def test_diagnosis_headline_counts():
    summary = {
        "sigma_deg": 0.06,
        "sigma_by_moment": [0.06] * 9,
        "noise_deg": 0.05,
        "alpha": 0.01,
        "cohort_verdict": "neutral_zone",
        "verdicts": {
            "none": 2,
            "neutral_zone": 3,
            "facet_contact+unexplained": 1,
            "unexplained": 1,
        },
        "effects": {"neutral_zone": 3, "facet_contact": 1, "unexplained": 2},
        "seconds": 1.0,
        "n_specimens": 7,
        "found_effects": ["neutral_zone", "facet_contact"],
    }
    assert diagnosis_headline(summary) == {"n": 7, "flagged": 2, "seconds": 1.0}


def test_a_headline_without_its_figures_says_what_is_missing():
    with pytest.raises(HeadlineError, match=r"lack \['verdicts', 'effects'\]") as err:
        diagnosis_headline({"n_specimens": 3})
    assert isinstance(err.value, FemcalError)
    with pytest.raises(HeadlineError, match="has no 'nn' row"):
        surrogate_headline({"trained_on_large": {"linear@large": {"model": "linear", "mae": 1}}})


class _Shifted:
    """A model predicting the FE value plus 0.1 deg."""

    def predict(self, rows: pd.DataFrame) -> np.ndarray:
        return rows["rom_deg"].to_numpy() + 0.1


def _test_table() -> pd.DataFrame:
    rows = [
        {"config_id": c, "load_case": lc, "moment_nm": m, "rom_deg": c + m, "status": s}
        for c, s in ((0, "ok"), (1, "ok"), (2, "failed"))
        for lc in ("Flexion", "Extension", "LateralBending", "AxialRotation")
        for m in (1.0, 2.0, 3.0)
    ]
    return pd.DataFrame(rows)


def test_evaluation_writes_a_headline_and_a_table(tmp_path: Path):
    test = _test_table()
    scores = {
        "Trained on Large": [
            Score("nn", "large", {"mae": 0.02, "r2_mean": 0.99, "r2_curve_mean": 0.98}, 24, {}),
            Score("linear", "large", {"mae": 0.9, "r2_mean": 0.6}, 24, {}),
        ],
    }
    paths = {k: tmp_path / f"{k}.x" for k in ("markdown", "json_path", "table_path")}
    head = write_reports(scores, **paths)
    assert json.loads(paths["json_path"].read_text()) == head
    assert head == {"mae_deg": 0.02, "ref_mae_deg": 0.9, "r2": 0.99, "n": 24}
    table = json.loads(paths["table_path"].read_text())
    assert set(table["trained_on_large"]) == {"nn@large", "linear@large"}
    pred = prediction_table(_Shifted(), test)
    assert len(pred) == 24 and np.allclose(pred["error_deg"], 0.1)
    assert list(pred.columns[:3]) == ["config_id", "load_case", "moment_nm"]


def test_training_curves_need_a_history():
    class Net:
        history_ = [
            {"member": 0, "epoch": 0, "train_loss": 1.0, "val_loss": 1.1},
            {"member": 0, "epoch": 1, "train_loss": 0.5, "val_loss": 0.6, "val_mae_deg": 0.2},
        ]

    curves = training_curves(Net())
    assert list(curves.columns) == ["member", "epoch", "train_loss", "val_loss", "val_mae_deg"]
    assert np.isnan(curves["val_mae_deg"][0])
    with pytest.raises(FemcalError, match="holds no training history"):
        training_curves(object())
