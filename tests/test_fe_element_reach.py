"""experiments.fe_element_reach: where the FE cohort's elements act, read from runs without them
(the CalculiX runs themselves are the experiment's; here their records are given)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from experiments.fe_element_reach import FIRST_ID, reach, score, shape, summary, variants

MOMENTS = [0.5 * k for k in range(1, 21)]
NAMES = ["C10Nucleus", "C01Nucleus"]


def _answers() -> pd.DataFrame:
    return pd.DataFrame(
        {
            "specimen": ["0", "1", "2"],
            "class": ["none", "facets", "both"],
            "facet_gap_mm": [np.nan, 0.5, 0.4],
            "facet_stiffness_n_per_mm": [np.nan, 60.0, 80.0],
            "ligament_stiffness_scale": [np.nan, np.nan, 1.0],
            "ligament_slack_shift": [np.nan, np.nan, -0.1],
            "C10Nucleus": [0.1, 0.12, 0.14],
            "C01Nucleus": [0.02, 0.03, 0.04],
            "config_id": [100000, 100001, 100002],
        }
    )


def test_one_run_per_element_without_it():
    table = variants(_answers())
    assert list(zip(table["specimen"], table["removed"])) == [
        ("1", "facets"),
        ("2", "facets"),
        ("2", "ligaments"),
    ]
    assert list(table["config_id"]) == [FIRST_ID + 1, FIRST_ID + 2, FIRST_ID + 1002]
    one, two_no_facets, two_no_ligaments = table["settings"]
    assert one is None  # the disc alone
    # taut ligaments stay: their neutral step too
    assert set(two_no_facets["posterior"]) == {"ligaments"} and two_no_facets["neutral_step"]
    # facets alone exert no force at rest: no neutral step
    assert set(two_no_ligaments["posterior"]) == {"facets"}
    assert "neutral_step" not in two_no_ligaments


def test_shapes():
    m = np.array(MOMENTS)
    assert shape(0.04 * np.ones(20)) == "none"  # within the noise
    assert shape(0.5 * (1 - np.exp(-m))) == "saturating"  # a taut element gone slack
    assert shape(0.02 * np.maximum(m - 3, 0) ** 2) == "engaging"  # a gap closed
    assert shape(np.r_[0.5 * (1 - np.exp(-m[:15])), np.full(5, np.nan)]) == "saturating"


def _cohort(tmp_path, answers):
    folder = tmp_path / "cohort"
    (folder / "clean" / "Test").mkdir(parents=True)
    answers.to_csv(folder / "answers.csv", index=False)
    for k, lc in enumerate(["Flexion", "Extension", "LateralBending", "AxialRotation"]):
        # specimen i is row i; its stiffness factor r + 1 + k
        rows = np.array([[0.0, *(np.array(MOMENTS) * (r + 1 + k))] for r in (2, 0, 1)])
        pd.DataFrame(rows, columns=["0.0", *map(str, MOMENTS)]).to_csv(
            folder / "clean" / "Test" / f"ROM_Results_{lc}_TestData_64_wMoment.csv",
            index=False,
        )
    return folder


def test_reach_against_the_cohorts_own_curves(tmp_path):
    answers = _answers()
    folder = _cohort(tmp_path, answers)
    m = np.array(MOMENTS)
    # specimen 2: extension 3 * m
    without = 3 * m + 0.4 * (1 - np.exp(-m))
    records = pd.DataFrame(
        {
            "config_id": [FIRST_ID + 1002],
            "load_case": ["Extension"],
            "rom_deg": [list(without[:18]) + [None, None]],
            "specimen": ["2"],
            "removed": ["ligaments"],
        }
    )
    table = reach(records, folder, MOMENTS)
    row = table.iloc[0]
    assert row["effect"] == "ligament_tension" and row["levels"] == 18
    assert row["max_deg"] == pytest.approx(0.4 * (1 - np.exp(-9.0)), rel=1e-9)
    assert row["onset_nm"] == 0.5 and row["shape"] == "saturating"
    diagnosis = [
        {
            "specimen": "2",
            "sigma_parts": {"surrogate_by_load_case_deg": {"Extension": 0.1}},
            "probabilities": {
                "inclusion": {"ligament_tension": 0.8},
                "acts_in": {"ligament_tension": {"Flexion": 1.0, "Extension": 0.5}},
            },
        }
    ]
    scored = score(table, diagnosis)
    assert scored["threshold_deg"].iloc[0] == pytest.approx(0.2)
    assert scored["p_acts"].iloc[0] == pytest.approx(0.4)
    assert bool(scored["visible"].iloc[0])
    got = summary(scored).iloc[0]
    assert (
        got["visible"],
        got["saturating (visible)"],
        got["named there, p >= 0.5 (visible)"],
    ) == (
        1,
        1,
        0,
    )


def test_a_missing_cohort_says_how_to_get_it(tmp_path):
    from experiments.fe_element_reach import main

    with pytest.raises(SystemExit, match="not found; the FE-made cohort is a DVC output"):
        main(["--out", str(tmp_path / "out"), "--cohort", str(tmp_path / "nowhere")])
