"""The loop on the FE-made cohort: scoring the verdicts and errors against the answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from femcal.config import load_params
from femcal.errors import ConfigError
from femcal.fe.hidden import (
    FE_START_BANK,
    calibration_job,
    found_effects,
    portable_path,
    score,
    start_bank_of,
    visible_threshold,
)

ROOT = Path(__file__).resolve().parents[2]

ANSWERS = pd.DataFrame(
    {
        "specimen": ["0", "1", "2", "3", "4"],
        "class": ["none", "facets", "ligaments", "both", "both"],
    }
)


def diagnosis(effects: list[list[str]], baseline: list[float]) -> list[dict]:
    return [
        {"specimen": str(i), "effects": e, "baseline_mae_deg": b}
        for i, (e, b) in enumerate(zip(effects, baseline))
    ]


def test_every_term_of_an_effect_counts_as_the_effect():
    assert found_effects(["facet_contact:split", "ligament_tension"]) == (
        "facet_contact",
        "ligament_tension",
    )
    terms = ["ligament_tension@Flexion,Extension,LateralBending:split", "facet_contact:split"]
    assert found_effects(terms) == ("facet_contact", "ligament_tension")
    assert found_effects([]) == ()


def test_score_counts_right_verdicts_over_all_and_where_visible():
    diag = diagnosis(
        [[], ["facet_contact:split"], [], ["facet_contact", "ligament_tension"], ["neutral_zone"]],
        [0.05, 0.5, 0.15, 0.9, 0.6],
    )
    disc = {"0": 0.1, "1": 0.4, "2": 0.2, "3": 0.8, "4": 0.5}
    after = {"0": 0.1, "1": 0.12, "2": 0.2, "3": 0.15, "4": 0.3}
    out = score(diag, ANSWERS, 0.2, disc, after)
    # the disc alone misses (> 0.2 deg) specimens 1, 3, 4; 1 and 3 are right
    assert out["n_visible"] == 3 and out["visible_threshold_deg"] == 0.2
    assert out["right_fraction_visible"] == pytest.approx(2 / 3)
    assert out["right_fraction_all"] == pytest.approx(3 / 5)  # and the none specimen 0
    # specimen 2 (ligaments) got "none": 1 of the 4 with an element, none of the visible 3
    assert out["none_given_element_fraction_all"] == pytest.approx(0.25)
    assert out["none_given_element_fraction_visible"] == 0.0
    assert out["none_false_alarms"] == 0 and out["n_none"] == 1
    assert out["disc_only_floor_mae_deg"] == pytest.approx(0.1)
    assert out["classes"]["both"]["error_ratio"] == pytest.approx((0.15 + 0.3) / 2 / 0.1)
    assert out["error_ratio_max"] == pytest.approx(2.25)
    assert out["classes"]["facets"]["verdicts"] == {"facet_contact": 1}
    assert out["classes"]["both"]["n"] == 2 and out["classes"]["both"]["right"] == 1
    assert out["classes"]["both"]["n_visible"] == 2


def test_visible_means_beyond_twice_the_noise_plus_the_surrogate_error():
    # sigma by moment sqrt(noise^2 + sd^2) with sd 0.03 and 0.12: mean sd 0.075
    sigma = [float(np.hypot(0.05, 0.03)), float(np.hypot(0.05, 0.12))]
    summary = {"sigma_deg": sigma[0], "sigma_by_moment": sigma}
    assert visible_threshold(summary, 0.05) == pytest.approx(0.1 + 0.075)
    assert visible_threshold({"sigma_deg": 0.05, "sigma_by_moment": None}, 0.05) == 0.1


def test_the_jobs_start_from_the_given_bank(tmp_path):
    bank = tmp_path / "large.csv"
    bank.write_text("config_id\n")
    assert start_bank_of(bank) == {"start_bank": bank.resolve()}
    assert start_bank_of(None) == {}
    params = load_params(ROOT / "params.yaml")
    options = {"params": params, "model_uri": "m", "noise_deg": 0.05, "start_bank": bank}
    job = calibration_job(tmp_path / "meas.csv", tmp_path / "out", ["ligament_tension"], options)
    assert job.start_bank == bank.resolve() and job.effects == ("ligament_tension",)
    # None: params.yaml's calibrate.start_bank
    job = calibration_job(
        tmp_path / "meas.csv", tmp_path / "out", [], {**options, "start_bank": None}
    )
    assert job.start_bank.as_posix().endswith(params["calibrate"]["start_bank"])


def test_a_missing_start_bank_names_the_fix(tmp_path):
    with pytest.raises(ConfigError, match=r"is not a file.*prepare.*--start-bank ''"):
        start_bank_of(tmp_path / "absent.csv")
    assert FE_START_BANK.name == "large.csv"


def test_paths_inside_the_project_are_recorded_relative_to_it(tmp_path):
    root = tmp_path / "project"
    (root / "fe" / "data").mkdir(parents=True)
    assert portable_path(root / "fe" / "data" / "cohort", root) == "fe/data/cohort"
    assert portable_path("models:/ivd-fe@champion", root) == "models:/ivd-fe@champion"
    outside = tmp_path / "elsewhere" / "model"
    assert portable_path(outside, root) == str(outside)
