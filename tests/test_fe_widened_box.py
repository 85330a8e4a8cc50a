"""The widened box's pure logic (experiments/fe_widened_box.py): the bounds, the added design
outside the old box, and the store records as a tidy table. No CalculiX, no training."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

import experiments.fe_widened_box as wb
from experiments.common import REPO

#: The FE campaign's box (fe/params.yaml ``fe.bounds``), the box the script widens.
BOUNDS = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())["fe"]["bounds"]


def test_widened_bounds_double_only_the_stiffnesses_upper_bounds():
    wide = wb.widened_bounds(BOUNDS, 2.0)
    for name, (lo, hi) in BOUNDS.items():
        expected_hi = 2.0 * hi if name in wb.STIFFNESSES else hi
        assert wide[name] == [lo, expected_hi]


def test_added_design_is_seeded_and_outside_the_old_box_inside_the_wide_one():
    a = wb.added_design(BOUNDS, 2.0, 64, seed=7)
    b = wb.added_design(BOUNDS, 2.0, 64, seed=7)
    assert a.equals(b)
    names = list(BOUNDS)
    x = a[names].to_numpy()
    assert wb.outside(x, names, BOUNDS).all()
    assert not wb.outside(x, names, wb.widened_bounds(BOUNDS, 2.0)).any()
    # inside the old box on all five stiffnesses with probability ~0.46^3 0.49^2 ~ 0.02 each
    assert len(a) >= 56
    assert (a["config_id"] >= wb.ID_OFFSET).all() and a["config_id"].is_unique


def test_outside_flags_a_point_below_or_above_any_bound():
    names = ["C10Nucleus", "Kappa"]
    bounds = {"C10Nucleus": [0.03, 0.21], "Kappa": [0.0, 0.33]}
    x = np.array([[0.1, 0.1], [0.3, 0.1], [0.1, -0.01], [0.21, 0.33]])
    assert wb.outside(x, names, bounds).tolist() == [False, True, True, False]


def test_added_table_ends_a_curve_at_its_first_level_not_reached():
    rec = {
        "config_id": 100003,
        "load_case": "Flexion",
        "levels": [0.5, 1.0, 1.5],
        "rom_deg": [0.4, None, 1.2],
        "idp_mpa": [0.01, None, 0.03],
        "parameters": dict.fromkeys(BOUNDS, 0.1),
    }
    table = wb.added_table([rec], list(BOUNDS))
    assert table["status"].tolist() == ["ok", "failed", "failed"]
    assert table["rom_deg"].iloc[0] == pytest.approx(0.4)
    assert table["rom_deg"].iloc[1:].isna().all()
    assert table["moment_nm"].tolist() == [0.5, 1.0, 1.5]


def test_complete_configs_keeps_configurations_with_every_load_case():
    recs = [
        {
            "config_id": cid,
            "load_case": lc,
            "levels": [0.5],
            "rom_deg": [0.4],
            "idp_mpa": [0.01],
            "parameters": dict.fromkeys(BOUNDS, 0.1),
        }
        for cid, cases in ((1, ("Flexion", "Extension")), (2, ("Flexion",)))
        for lc in cases
    ]
    table = wb.complete_configs(wb.added_table(recs, list(BOUNDS)), 2)
    assert sorted(table["config_id"].unique()) == [1]
