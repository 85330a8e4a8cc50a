"""The edge cohorts (experiments/edge_cohorts.py) and their scoring (experiments/bench_edges.py),
on synthetic held-out curves and the committed CalculiX store: no trained model, no study data."""

from __future__ import annotations

import ast
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

import experiments.bench_edges as be
import experiments.edge_cohorts as ec
from femcal.schema import LOAD_CASES

ROOT = Path(__file__).resolve().parents[1]
STDLIB = {"argparse", "csv", "gzip", "json", "os", "collections", "dataclasses", "pathlib"}


def _test_curves(n: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Saturating FE-like curves at 1..5 Nm, shape (n, 4, 5)."""
    rng = np.random.default_rng(seed)
    m = np.arange(1.0, 6.0)
    amp = rng.uniform(2.0, 9.0, (n, 4, 1))
    scale = rng.uniform(1.0, 3.0, (n, 4, 1))
    slope = rng.uniform(0.05, 0.3, (n, 4, 1))
    return m, amp * (1 - np.exp(-m / scale)) + slope * m


@pytest.fixture(scope="module")
def store() -> list[dict]:
    return ec.read_outside_store()


@pytest.fixture(scope="module")
def cohort(store) -> ec.EdgeCohort:
    return ec.make_cohort(_test_curves(), store, 11)


def test_imports_numpy_and_the_standard_library_only():
    for module in ("edge_cohorts.py", "edge_discs.py"):
        tree = ast.parse((ROOT / "experiments" / module).read_text())
        names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        own = {"experiments.edge_discs"}
        assert {n.split(".")[0] for n in set(names) - own} <= STDLIB | {"numpy", "__future__"}
    code = (
        "import sys, experiments.edge_cohorts; "
        "print(any(m.startswith('femcal') for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert ec.LOAD_CASES == tuple(LOAD_CASES)


def test_outside_discs_come_from_the_store_and_lie_above_the_box(store):
    bounds = yaml.safe_load((ROOT / "fe" / "params.yaml").read_text())["fe"]["bounds"]
    assert len(store) == 16
    for d in store:
        assert d["rom"].shape == (4, len(d["moments"])) and np.all(d["rom"] > 0)
        for name in ("C10Nucleus", "C01Nucleus", "C10Annulus", "K1Annulus", "K2Annulus"):
            assert d["parameters"][name] > bounds[name][1]


def test_a_seed_draws_the_same_cohort(store):
    small = ec.CohortOptions(n_per_class=1)
    one, again = (ec.make_cohort(_test_curves(), store, 11, small) for _ in range(2))
    assert again.rows == one.rows and again.truth == one.truth and again.meta == one.meta
    assert ec.make_cohort(_test_curves(), store, 12, small).rows != one.rows


def test_truth_is_consistent(store, cohort):
    truth = cohort.truth
    assert len(truth) == 6 * len(ec.CLASSES) >= 48
    params = [d["parameters"] for d in store]
    counts = {}
    for t in truth:
        counts[t["truth"]] = counts.get(t["truth"], 0) + 1
        assert set(t["structures"]) == set(ec.CLASSES[t["truth"]])
        assert set(t["contribution_rms_deg"]) == set(t["structures"])
        for s, per_lc in t["structures"].items():
            assert per_lc and all(ec.ACTS_PRIOR[s][lc] > 0 for lc in per_lc)
            assert all(p["law"] in ec.LAWS[s] for p in per_lc.values())
            assert set(t["contribution_rms_deg"][s]) == set(per_lc)
        if t["truth"] == "outside_box":
            assert t["disc"]["source"] == "outside_box" and t["disc"]["parameters"] in params
        else:
            assert t["disc"]["source"] == "test"
        assert t["noise"]["rms_deg"] > 0
    assert set(counts.values()) == {6}
    inside = [t["disc"]["config_id"] for t in truth if t["disc"]["source"] == "test"]
    assert len(set(inside)) == len(inside)  # without replacement
    # facets never in flexion; beyond the built-in assignment in some specimens
    acts = [lc for t in truth for lc in t["structures"].get("facets", {})]
    assert "Flexion" not in acts and "LateralBending" in acts
    assert {t["protocol"] for t in truth} == set(ec.PROTOCOLS)


def test_measurements_match_the_truth(cohort, tmp_path):
    path = ec.write_cohort(cohort, tmp_path / "c")
    rows = list(csv.DictReader(path.open()))
    assert set(rows[0]) == {"specimen", "load_case", "moment_nm", "rom_deg"}
    truth = json.loads((tmp_path / "c" / "truth.json").read_text())
    for t in truth:
        mine = [r for r in rows if r["specimen"] == t["specimen"]]
        assert len(mine) == t["n_points"]
        for lc, top in t["maxima_nm"].items():
            assert max(float(r["moment_nm"]) for r in mine if r["load_case"] == lc) == top
    # a disc alone: measured minus its curve is noise (within 6 sd of the true noise RMS)
    m, rom = _test_curves()
    t = next(t for t in truth if t["truth"] == "none" and t["noise"]["kind"] == "white")
    disc = ec.Disc(m, rom[t["disc"]["config_id"]])
    mine = [r for r in rows if r["specimen"] == t["specimen"]]
    at = np.array([float(r["moment_nm"]) for r in mine])
    j = np.array([LOAD_CASES.index(r["load_case"]) for r in mine])
    clean = disc.rotation(np.tile(at, (4, 1)))[j, np.arange(len(at))]
    resid = np.array([float(r["rom_deg"]) for r in mine]) - clean
    assert np.abs(resid).max() < 6 * t["noise"]["rms_deg"]


def test_disc_interpolates_its_curve_monotonically():
    m, rom = _test_curves(4)
    disc = ec.Disc(m, rom[0])
    np.testing.assert_allclose(disc.rotation(np.tile(m, (4, 1))), rom[0], rtol=1e-12)
    fine = disc.rotation(np.tile(np.linspace(0.5, 7.5, 200), (4, 1)))
    assert np.all(np.diff(fine, axis=1) > 0)


def test_parallel_structures_carry_their_share_at_the_reference_moment(cohort):
    t = next(t for t in cohort.truth if t["truth"] == "facets+ligaments")
    m, rom = _test_curves()
    disc = ec.Disc(m, rom[t["disc"]["config_id"]])
    ref = np.full((4, 1), ec.REFERENCE_NM)
    phi = ec.specimen_rom(t["structures"], disc, ref)
    for j, lc in enumerate(LOAD_CASES):
        acting = [t["structures"][s][lc] for s in ec.PARALLEL if lc in t["structures"][s]]
        carried = sum(p["stiffness"] * ec.parallel_unit(p, phi[j, 0]) for p in acting)
        assert carried == pytest.approx(sum(p["share"] for p in acting) * ec.REFERENCE_NM, rel=1e-6)


def test_scoring_flags_a_confident_wrong_effect_and_an_out_of_box_verdict(cohort):
    box = next(t for t in cohort.truth if t["truth"] == "outside_box")
    record = {
        "verdict": "facet_contact+outside_box",
        "effects": ["facet_contact:split"],
        "baseline_mae_deg": 0.5,
        "final_mae_deg": 0.04,
        "probabilities": {"inclusion": {"facet_contact": 0.5, "facet_contact:split": 0.45}},
        "outside_box": {"named": True, "probability": 0.7},
    }
    row = be.score_specimen(box, record)
    assert row["box_said"] and row["strict"] and row["visible"]
    assert row["confident_wrong"] == "facet_contact" == row["confident_builtin"]
    lig = next(t for t in cohort.truth if t["truth"] == "ligaments")
    record = {
        "verdict": "ligament_tension",
        "effects": ["ligament_tension"],
        "baseline_mae_deg": 0.3,
        "probabilities": {"inclusion": {"ligament_tension": 0.97, "neutral_zone": 0.2}},
    }
    row = be.score_specimen(lig, record)
    assert row["strict"] and not row["confident_wrong"] and not row["box_said"]


def test_time_report_is_parsed():
    text = (
        "\tUser time (seconds): 70.50\n\tSystem time (seconds): 2.25\n"
        "\tElapsed (wall clock) time (h:mm:ss or m:ss): 1:12.30\n"
        "\tMaximum resident set size (kbytes): 1048576\n"
    )
    t = be.parse_time(text)
    assert t["cpu_s"] == pytest.approx(72.75) and t["time_wall_s"] == pytest.approx(72.3)
    assert t["max_rss_mb"] == pytest.approx(1024.0)


def test_inclusion_scores_count_present_and_absent_effects():
    table = pd.DataFrame(
        {
            "expected": ["facet_contact", ""],
            "inclusion": ['{"facet_contact": 1.0, "ligament_tension": 0.95}', "{}"],
        }
    )
    got = be.inclusion_scores(table)
    assert got["pairs"] == 6  # two specimens x three built-in effects
    assert got["present_confident"]["k"] == 1 and got["present_confident"]["n"] == 1
    assert got["absent_confident"]["k"] == 1 and got["absent_confident"]["n"] == 5
    # the one miss: 0.95 on an absent effect; the rest exact (clipped to 0.999 / 0.001)
    assert got["brier"] == pytest.approx((0.95**2 + 1e-6 * 5) / 6, rel=1e-3)
