"""The anatomy cohorts (experiments/anatomy_cohorts.py) and their runner's scoring
(experiments/bench_anatomy.py), on synthetic FE curves: no trained model, no study data."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from argparse import Namespace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import experiments.anatomy_cohorts as ac
import experiments.bench_anatomy as ba
from femcal.schema import LOAD_CASES

BENCH = Path(__file__).resolve().parents[1] / "experiments"


def _fe(n: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Saturating FE-like curves at 1..5 Nm, shape (n, 4, 5)."""
    rng = np.random.default_rng(seed)
    m = np.arange(1.0, 6.0)
    amp = rng.uniform(2.0, 9.0, (n, 4, 1))
    scale = rng.uniform(1.0, 3.0, (n, 4, 1))
    slope = rng.uniform(0.05, 0.3, (n, 4, 1))
    return m, amp * (1 - np.exp(-m / scale)) + slope * m


@pytest.fixture(scope="module")
def cohort() -> ac.AnatomyCohort:
    m, rom = _fe()
    return ac.make_cohort(m, rom, seed=7)


def test_imports_nothing_from_femcal_effects():
    tree = ast.parse((BENCH / "anatomy_cohorts.py").read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [n for n in names if n.startswith("femcal.effects")]
    code = (
        "import sys; import experiments.anatomy_cohorts; "
        "print(any(m.startswith('femcal.effects') for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert ac.LOAD_CASES == tuple(LOAD_CASES)


def test_classes_and_protocols_balanced(cohort):
    a = cohort.answers
    assert len(a) == 9 * len(ac.CLASSES) >= 54
    assert set(a["truth"].value_counts()) == {9}
    counts = pd.crosstab(a["truth"], a["protocol"])
    assert list(counts.columns.sort_values()) == sorted(ac.PROTOCOLS)
    assert (counts.max(axis=1) - counts.min(axis=1) <= 1).all()
    overall = a["protocol"].value_counts()
    assert overall.max() - overall.min() <= 1
    assert a["config_id"].is_unique


def test_deterministic_per_seed(cohort):
    m, rom = _fe()
    again = ac.make_cohort(m, rom, seed=7)
    pd.testing.assert_frame_equal(again.answers, cohort.answers)
    pd.testing.assert_frame_equal(again.measurements, cohort.measurements)
    other = ac.make_cohort(m, rom, seed=8, n_per_class=1)
    assert other.answers["config_id"].tolist() != cohort.answers["config_id"][:7].tolist()


def test_parameters_differ_per_load_case(cohort):
    a = cohort.answers
    facets = a[a["truth"].str.contains("facet_contact")]
    for key in ("engage_deg", "stiffness", "rom_ratio"):
        assert (facets[f"facets_Extension_{key}"] != facets[f"facets_AxialRotation_{key}"]).all()
    lig = a[a["truth"].str.contains("ligament_tension")]
    assert (lig["ligaments_Flexion_engage_deg"] != lig["ligaments_LateralBending_engage_deg"]).all()
    nz = a[a["truth"] == "neutral_zone"]
    amps = nz[[f"laxity_{lc}_amplitude_deg" for lc in LOAD_CASES]].to_numpy()
    assert (np.ptp(amps, axis=1) > 0).all()


@pytest.mark.parametrize("structure", ["facets", "ligaments"])
def test_parallel_element_lowers_rom_only_in_its_load_cases(structure):
    m, rom = _fe(4, seed=3)
    disc = ac.DiscCurve(m, rom[0])
    drawn = {structure: ac.draw_structure(structure, disc, np.random.default_rng(0))}
    moments = np.array([1.0, 2.5, 5.0, 7.5])
    with_el = ac.specimen_rom(drawn, disc, moments)
    alone = disc.rotation(moments)
    for j, lc in enumerate(LOAD_CASES):
        if lc in ac.ACTS_ON[structure]:
            assert (with_el[j] <= alone[j] + 1e-9).all() and with_el[j, -1] < alone[j, -1]
            # sized by the segment-to-disc RoM ratio at the reference moment
            ratio = drawn[structure][lc]["rom_ratio"]
            assert with_el[j, 2] == pytest.approx(ratio * alone[j, 2], rel=1e-6)
        else:
            np.testing.assert_allclose(with_el[j], alone[j])


def test_series_elements_add_rotation():
    m, rom = _fe(4, seed=4)
    disc = ac.DiscCurve(m, rom[1])
    moments = np.array([0.5, 1.0, 5.0])
    for structure in ("laxity", "annulus_yield"):
        drawn = {structure: ac.draw_structure(structure, disc, np.random.default_rng(1))}
        extra = ac.specimen_rom(drawn, disc, moments) - disc.rotation(moments)
        for j, lc in enumerate(LOAD_CASES):
            assert (extra[j] > 0).any() == (lc in ac.ACTS_ON[structure])


def test_disc_curve_monotone_and_inverse():
    m, rom = _fe(2, seed=5)
    disc = ac.DiscCurve(m, rom[0])
    grid = np.geomspace(0.3, 10.0, 50)
    phi = disc.rotation(grid)
    assert (np.diff(phi, axis=1) > 0).all()
    np.testing.assert_allclose(disc.rotation(m), rom[0], rtol=1e-10)
    np.testing.assert_allclose(disc.moment(phi), np.broadcast_to(grid, phi.shape), rtol=1e-8)


def test_written_files_match_answers(cohort, tmp_path):
    path = ac.write_cohort(cohort, tmp_path / "c")
    meas = pd.read_csv(path)
    answers = pd.read_csv(tmp_path / "c" / "answers.csv", keep_default_na=False)
    assert list(meas.columns) == ["specimen", "load_case", "moment_nm", "rom_deg"]
    for row in answers.itertuples():
        pts = meas[meas["specimen"] == row.specimen]
        assert len(pts) == row.n_points
        assert sorted(set(pts["moment_nm"])) == list(ac.PROTOCOLS[row.protocol])
        assert set(pts["load_case"]) == set(LOAD_CASES)
        assert row.expected_effects == "+".join(sorted(ac.expected_effects(row.truth)))
    assert json.loads((tmp_path / "c" / "cohort.json").read_text())["seed"] == 7


def test_reads_the_study_layout(synthetic_study):
    folder = synthetic_study("test", n_configs=5, seed=2)
    moments, rom = ac.read_heldout_curves(folder.parent)
    assert moments.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert rom.shape == (5, 4, 5) and (rom > 0).all()
    with pytest.raises(ac.ConfigError, match="held-out FE curves"):
        ac.read_heldout_curves(folder.parent / "elsewhere")


# ------------------------------------------------------------------------------- scoring
ANSWERS = pd.DataFrame(
    {
        "specimen": ["S0", "S1", "S2", "S3", "S4", "S5"],
        "truth": [
            "none",
            "facet_contact",
            "facet_contact",
            "facet_contact+ligament_tension",
            "unexplained",
            "neutral_zone",
        ],
        "expected_effects": ["", "facet_contact", "facet_contact", "facet_contact+ligament_tension"]
        + ["", "neutral_zone"],
        "out_of_library": [False, False, False, False, True, False],
        "protocol": ["1-5 Nm x 0.5"] * 3 + ["0.5-5 Nm x 0.5"] * 3,
        "effect_rms_deg": [0.0, 0.4, 0.3, 0.5, 0.2, 0.02],
    }
)


def _spec(name, verdict, effects, base, final, inclusion=None, outside=None) -> dict:
    s = {
        "specimen": name,
        "verdict": verdict,
        "effects": effects,
        "baseline_mae_deg": base,
        "final_mae_deg": final,
        "adequacy": {"disc_alone": {"p_chi2": 1e-6 if base > 0.1 else 0.5}},
    }
    if inclusion is not None:
        s["probabilities"] = {"models": {}, "inclusion": inclusion, "outside_library": outside}
    return s


def _diagnosis(with_probs: bool) -> list[dict]:
    inc = (lambda **kw: kw) if with_probs else (lambda **kw: None)
    return [
        _spec("S0", "none", [], 0.04, 0.04, inc(facet_contact=0.1), 0.05),
        _spec("S1", "facet_contact", ["facet_contact"], 0.3, 0.045, inc(facet_contact=0.9), 0.1),
        _spec(
            "S2",
            "facet_contact+unexplained",
            ["facet_contact"],
            0.2,
            0.07,
            inc(facet_contact=0.6),
            0.5,
        ),
        _spec("S3", "facet_contact", ["facet_contact"], 0.4, 0.09, inc(facet_contact=0.95), 0.3),
        _spec(
            "S4", "ligament_tension", ["ligament_tension"], 0.15, 0.05, inc(facet_contact=0.2), 0.4
        ),
        _spec("S5", "none", [], 0.06, 0.06, inc(facet_contact=0.1), 0.1),
    ]


def test_judge_criteria():
    j = ba.judge(
        "facet_contact+unexplained", ["facet_contact"], frozenset({"facet_contact"}), False
    )
    assert not j["strict"] and j["known_exact"] and j["no_wrong_one_right"]
    j = ba.judge("unexplained", [], frozenset(), True)
    assert j["strict"] and j["ool_right"] and not j["none_given_effect"]
    j = ba.judge("none", [], frozenset({"neutral_zone"}), False)
    assert j["none_given_effect"] and not j["no_wrong_one_right"]
    j = ba.judge("neutral_zone", ["neutral_zone"], frozenset(), False)
    assert j["false_alarm"] and not j["strict"] and j["none_given_effect"] is None


def test_score_and_summaries():
    table = ba.score_specimens(ANSWERS, _diagnosis(True), noise_deg=0.05, alpha=0.01)
    assert table["visible"].tolist() == [False, True, True, True, True, False]
    assert table["strict"].tolist() == [True, True, False, False, False, False]
    assert table["known_exact"].tolist()[1:4] == [True, True, False]
    assert table["no_wrong_one_right"].tolist()[1:4] == [True, True, True]
    h = ba.headline(table)
    assert (h["single_strict_visible"]["k"], h["single_strict_visible"]["n"]) == (1, 2)
    assert (h["ool_right"]["k"], h["ool_right"]["n"]) == (0, 1)
    assert (h["none_given_effect_all"]["k"], h["none_given_effect_all"]["n"]) == (1, 5)
    assert h["none_given_effect_visible"]["n"] == 4 and h["false_alarm"]["k"] == 0
    rel = ba.reliability(table)
    assert rel["effects"] == ["facet_contact", "ligament_tension", "neutral_zone"]
    assert sum(b["n"] for b in rel["inclusion"]) == 18  # absent effects count as p = 0
    top = rel["inclusion"][-1]
    assert top["n"] == 2 and top["observed"] == 1.0
    assert rel["true_effect_inclusion_ge_half"]["k"] == 2
    mae = ba.mae_ratios(table)
    assert mae["floor_deg"] == pytest.approx(0.04)
    assert mae["classes"]["facet_contact"]["ratio"] == pytest.approx(0.0575 / 0.04)
    by_class = {r["truth"]: r for r in ba.grouped_rates(table, "truth")}
    assert by_class["facet_contact"]["visible"] == 2 and by_class["none"]["strict"]["k"] == 1


def test_split_forms_count_as_their_effect():
    diag = _diagnosis(False)
    diag[1]["effects"] = ["facet_contact:split"]
    table = ba.score_specimens(ANSWERS, diag, noise_deg=0.05, alpha=0.01)
    assert table.loc[1, "effects"] == "facet_contact" and table.loc[1, "strict"]


def test_no_probabilities_is_skipped():
    table = ba.score_specimens(ANSWERS, _diagnosis(False), noise_deg=0.05, alpha=0.01)
    assert ba.reliability(table) is None
    with pytest.raises(ba.ConfigError, match="no verdict"):
        ba.score_specimens(ANSWERS, _diagnosis(False)[:3], noise_deg=0.05, alpha=0.01)


def test_runner_scores_an_existing_diagnosis(synthetic_study, tmp_path):
    folder = synthetic_study("test", n_configs=14, seed=1)
    curves = ac.read_heldout_curves(folder.parent)
    cohort = ac.make_cohort(*curves, seed=11, n_per_class=2)
    diag = [
        _spec(s, "none", [], 0.03, 0.03, {"facet_contact": 0.2, "neutral_zone": 0.1}, 0.1)
        for s in cohort.answers["specimen"]
    ]
    out = tmp_path / "bench"
    (out / "seed-11" / "diagnosis").mkdir(parents=True)
    (out / "seed-11" / "diagnosis" / "diagnosis.json").write_text(json.dumps(diag))
    argv = ["--seeds", "11", "--out", str(out), "--raw-dir", str(folder.parent)]
    ba.main([*argv, "--n-per-class", "2", "--reuse"])
    report = json.loads((out / "bench_anatomy.json").read_text())
    assert report["pooled"]["headline"]["false_alarm"] == {"k": 0, "n": 2, "rate": 0.0}
    assert "femcal diagnose" in (out / "bench_anatomy.md").read_text()
    assert len(pd.read_csv(out / "specimens.csv")) == 14
    with pytest.raises(ba.ConfigError, match="exists"):
        ba.one_seed(
            11,
            Namespace(
                out=out,
                n_per_class=2,
                protocols=list(ac.PROTOCOLS),
                raw_dir=folder.parent,
                noise_deg=0.05,
                model_uri=None,
                reuse=False,
            ),
            curves,
        )
