"""The scoring of experiments/bench_edges_ceiling.py (issue 55's ceiling on the edge cohorts):
the forms fitted, the prior costs, the oracle's judgement and the bench rows it bounds."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest

from experiments.bench_edges_ceiling import (
    FRESH_SEEDS,
    all_forms,
    effect_set,
    judge,
    main,
    prior_cost,
    summarize,
)

FACET_WIDE = "facet_contact@Extension,LateralBending,AxialRotation"


def test_all_forms_holds_every_model_of_up_to_two_effects_in_every_form():
    forms = all_forms(["facet_contact", "ligament_tension", "neutral_zone"])
    # facets and ligaments: likely or every allowed load case, tied or split (4 each);
    # the neutral zone acts in every load case, tied or split (2)
    assert len(forms) == 1 + (4 + 4 + 2) + (4 * 4 + 4 * 2 + 4 * 2)
    assert len(set(forms)) == len(forms)
    assert forms[0] == ()
    assert (f"{FACET_WIDE}:split", "neutral_zone:split") in forms


def test_effect_set_names_the_effects_whatever_their_form():
    assert effect_set([f"{FACET_WIDE}:split", "neutral_zone"]) == "facet_contact+neutral_zone"
    assert effect_set([]) == ""


def test_prior_cost_is_the_diagnosis_first_further_split_and_load_case_costs():
    assert prior_cost("none") == 0.0
    assert prior_cost("facet_contact") == 10.0
    assert prior_cost("facet_contact:split+ligament_tension") == 10.0 + 2.0 * 2
    # lateral bending has prior 0.3 for facets: -2 ln(0.3 / 0.7) more
    assert prior_cost(FACET_WIDE) == pytest.approx(10.0 - 2.0 * math.log(0.3 / 0.7))


def test_judge_compares_effect_sets_by_their_best_form():
    scores = {
        "none": 90.0,
        "facet_contact": 60.0,
        f"{FACET_WIDE}:split": 40.0,  # the truth's best form
        "ligament_tension:split": 41.5,
        "facet_contact+neutral_zone": 39.0,
    }
    j = judge(scores, "facet_contact")
    assert j["oracle_pick"] == "facet_contact+neutral_zone"
    assert not j["oracle_right"]
    assert j["margin"] == pytest.approx(-1.0)
    assert j["truth_form"] == f"{FACET_WIDE}:split"
    del scores["facet_contact+neutral_zone"]
    j = judge(scores, "facet_contact")
    assert j["oracle_right"] and j["oracle_pick"] == "facet_contact"
    assert j["best_other"] == "ligament_tension" and j["margin"] == pytest.approx(1.5)


def _row(truth, expected, pick, strict, within, lb=False, facet_named=False):
    return {
        "truth": truth,
        "expected": expected,
        "oracle_pick": pick,
        "oracle_right": pick == expected,
        "oracle_right_engaged": pick == expected,
        "oracle_right_true_noise": pick == expected,
        "margin": 1.0 if pick == expected else -3.0,
        "strict": strict,
        "visible": True,
        "truth_within_noise": within,
        "facets_lb_visible": lb,
        "ligaments_ext_visible": False,
        "facet_named": facet_named,
        "ligament_named": False,
    }


def test_summarize_bounds_each_bench_row_and_splits_by_the_truth_fit():
    t = pd.DataFrame(
        [
            _row("facets", "facet_contact", "facet_contact", True, True, lb=True),
            _row("facets", "facet_contact", "ligament_tension", False, False, lb=True),
            _row(
                "facets+neutral_zone",
                "facet_contact+neutral_zone",
                "neutral_zone",
                False,
                False,
                facet_named=True,
            ),
            _row("facets+ligaments", "facet_contact+ligament_tension", "", False, True),
        ]
    )
    s = summarize(t)
    single = s["single effects strict"]
    assert single["diagnosis"] == {"k": 1, "n": 2} and single["oracle_fit"] == {"k": 1, "n": 2}
    assert single["oracle_fit_within_noise"] == {"k": 1, "n": 1}
    assert single["oracle_fit_misfit"] == {"k": 0, "n": 1}
    assert single["within_tie"] == {"k": 1, "n": 2}  # the miss lost by 3 > 2
    combos = s["combinations exactly right"]
    assert combos["oracle_fit"] == {"k": 0, "n": 2} and combos["within_noise"] == {"k": 1, "n": 2}
    beyond = s["beyond the old assignment: right effect named"]
    assert beyond["oracle_pick"] == {"k": 1, "n": 2} and beyond["diagnosis"] == {"k": 0, "n": 2}


def test_main_refuses_the_fresh_seeds(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--bench", str(tmp_path), "--seeds", f"101,{FRESH_SEEDS[0]}", "--out", str(tmp_path)])
    assert "fresh cohorts, run once" in capsys.readouterr().err


def _run(folder, margin, right, command):
    """A finished run's files in ``folder``: one facet specimen of seed 101."""
    row = _row("facets", "facet_contact", "facet_contact" if right else "neutral_zone", True, True)
    row.update(
        seed=101,
        specimen="E006",
        margin=margin,
        acts_in="{}",
        verdict="facet_contact",
        truth_form="facet_contact:split",
        truth_chi2_true_per_dof=0.5,
        truth_p_true=0.9,
    )
    folder.mkdir()
    pd.DataFrame([row]).to_csv(folder / "specimens.csv", index=False)
    cohort = {"seed": 101, "n": 1, "cpu_s": 60.0, "wall_s": 120.0, "specimens": None}
    meta = {"command": command, "seeds": [101], "summary": {}, "cohorts": [cohort]}
    (folder / "bench_edges_ceiling.json").write_text(json.dumps(meta))


def test_rewrite_joins_runs_counting_the_truth_where_any_run_lets_it_win(tmp_path):
    _run(tmp_path / "a", -1.5, False, "run a")
    _run(tmp_path / "b", 0.5, True, "run b")
    main(
        ["--bench", "x", "--seeds", "101", "--rewrite", "--out", str(tmp_path / "ab")]
        + ["--from", str(tmp_path / "a"), "--from", str(tmp_path / "b")]
    )
    t = pd.read_csv(tmp_path / "ab" / "specimens.csv")
    assert len(t) == 1 and bool(t["oracle_right"][0]) and t["margin"][0] == 0.5
    assert t["oracle_pick"][0] == "facet_contact"  # from the run where the truth wins
    report = (tmp_path / "ab" / "bench_edges_ceiling.md").read_text()
    assert "`run a` and `run b`" in report and "2 CPU-min, 4 min wall" in report
