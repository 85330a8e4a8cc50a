"""experiments.outside_box_roc: each out-of-box score read as a rule, against the verdict."""

from __future__ import annotations

import numpy as np
import pandas as pd

from experiments.outside_box_roc import ceilings, load, markdown, rates


def _table():
    # four discs outside the box (two visible), four inside; the probability separates them
    # but for one disc outside (0.2) and one inside (0.7); the verdict names two outside, one in
    return pd.DataFrame(
        {
            "truth": ["outside_box"] * 4 + ["facets", "none", "ligaments", "none"],
            "visible": [True, True, False, False, True, False, True, False],
            "box_said": [True, True, False, False, False, False, True, False],
            "box_probability": [0.9, 0.8, 0.6, 0.2, 0.1, 0.0, 0.7, np.nan],
            "bounds_pressed": [6, 5, 4, 1, 2, 0, 3, 1],
        }
    )


def test_rates_count_hits_over_the_discs_outside_and_alarms_over_those_inside():
    r = rates(_table(), np.array([True, False, True, False, True, False, False, False]))
    assert r == {"hits": 0.5, "hits_visible": 0.5, "false_alarms": 0.25}


def test_each_score_is_read_at_the_verdicts_false_alarms_and_at_none():
    rows = ceilings(_table())
    verdict = rows[0]
    p_budget, p_none, p_bar, b_budget, b_none, b_bar = rows[1:]
    assert verdict["rule"] == "the verdict"
    assert (verdict["hits"], verdict["false_alarms"]) == (0.5, 0.25)
    # at one false alarm in four, 0.2 names all four; with none, 0.8 names two
    assert (p_budget["threshold"], p_budget["hits"]) == ("0.2", 1.0)
    assert (p_none["threshold"], p_none["hits"], p_none["false_alarms"]) == ("0.8", 0.5, 0.0)
    # three or four pressed parameters name three outside (four: none inside; the largest t)
    assert (b_budget["threshold"], b_budget["hits"]) == ("4", 0.75)
    assert (b_none["threshold"], b_none["hits"], b_none["false_alarms"]) == ("4", 0.75, 0.0)
    # 75 % named with the fewest false alarms: 0.6 (the 0.7 inside), and four pressed (none)
    assert (p_bar["threshold"], p_bar["false_alarms"]) == ("0.6", 0.25)
    assert (b_bar["threshold"], b_bar["false_alarms"]) == ("4", 0.0)
    assert [r["rule"].split(", ")[-1] for r in rows[1:4]] == [
        "false alarms at most the verdict's",
        "no false alarm",
        "at least 75% named",
    ]


def test_the_table_reads_the_folders_files_and_gives_counts(tmp_path):
    _table().to_csv(tmp_path / "specimens.csv", index=False)
    table = load([tmp_path])
    text = markdown(table, ceilings(table))
    assert "| the verdict |  | 2/4 (50 %) | 2/2 (100 %) | 1/4 (25 %) |" in text
