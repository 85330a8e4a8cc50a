"""The FE-made cohort: draws, per-configuration settings, noise, and a small real cohort."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from fe_helpers import requires_ccx

from femcal.errors import FemcalError, SolverError
from femcal.fe import cohort as cohort_module
from femcal.fe.calculix_settings import LIGAMENT_DEFAULTS, LIGAMENTS, posterior_settings
from femcal.fe.campaign import PerConfigSettings
from femcal.fe.cohort import (
    CLASSES,
    FIRST_CONFIG_ID,
    SLACK_RANGE,
    _with_noise,
    adapter_settings,
    build_cohort,
    complete_ids,
    draw_specimens,
    posterior_of,
)
from femcal.fe.runtime import FeRuntime
from femcal.fe.store import settings_hash
from femcal.measurements import read_measurements
from femcal.schema import LOAD_CASES
from femcal.settings.fe import CohortSettings

from synth import study_space

SPACE = study_space()


def settings(tmp_path, **overrides) -> CohortSettings:
    values = {
        "out_dir": str(tmp_path / "cohort"),
        "store": str(tmp_path / "store" / "runs.jsonl"),
        "per_class": 2,
        "seed": 7,
    }
    return CohortSettings(**{**values, **overrides})


def test_draws_are_balanced_seeded_and_inside_their_ranges(tmp_path):
    cohort = settings(tmp_path, disc_margin=0.1)
    counts = dict.fromkeys(CLASSES, 5)
    a = draw_specimens(SPACE, counts, cohort, np.random.default_rng(1))
    b = draw_specimens(SPACE, counts, cohort, np.random.default_rng(1))
    pd.testing.assert_frame_equal(a, b)
    assert a["class"].value_counts().to_dict() == counts
    disc = a[list(SPACE.names)].to_numpy()
    lo, hi = SPACE.lower, SPACE.upper
    assert np.all(disc >= lo + 0.1 * (hi - lo) - 1e-12)
    assert np.all(disc <= hi - 0.1 * (hi - lo) + 1e-12)
    facets = a["class"].isin(["facets", "both"])
    assert a.loc[facets, "facet_gap_mm"].between(*cohort.facet_gap_mm).all()
    assert a.loc[facets, "facet_stiffness_n_per_mm"].between(*cohort.facet_stiffness_n_per_mm).all()
    assert a.loc[~facets, "facet_gap_mm"].isna().all()
    ligaments = a["class"].isin(["ligaments", "both"])
    assert (
        a.loc[ligaments, "ligament_stiffness_scale"].between(*cohort.ligament_stiffness_scale).all()
    )
    assert a.loc[~ligaments, "ligament_slack_shift"].isna().all()


def test_posterior_of_each_class_is_valid_and_has_its_elements(tmp_path):
    drawn = draw_specimens(
        SPACE, dict.fromkeys(CLASSES, 1), settings(tmp_path), np.random.default_rng(0)
    )
    by_class = {row["class"]: posterior_of(row) for row in drawn.to_dict(orient="records")}
    assert by_class["none"] is None
    assert set(by_class["facets"]) == {"facets"}
    assert set(by_class["ligaments"]) == {"ligaments"}
    assert set(by_class["both"]) == {"facets", "ligaments"}
    both = posterior_settings(by_class["both"])  # the adapter's own check
    assert set(both.ligaments) == set(LIGAMENTS)


def test_slack_shift_is_clipped_to_the_ligaments_range():
    row = {"class": "ligaments", "ligament_stiffness_scale": 2.0, "ligament_slack_shift": 0.3}
    ligaments = posterior_of(row)["ligaments"]
    for name in LIGAMENTS:
        expected = min(LIGAMENT_DEFAULTS[name]["slack_strain"] + 0.3, SLACK_RANGE[1])
        assert ligaments[name]["slack_strain"] == pytest.approx(expected)
        stiffness = 2.0 * LIGAMENT_DEFAULTS[name]["stiffness_n_per_mm"]
        assert ligaments[name]["stiffness_n_per_mm"] == pytest.approx(stiffness)


def test_only_a_pre_strained_ligament_moves_the_zero_to_the_neutral_position():
    """A taut ligament (slack strain < 0) turns the unloaded disc: its jobs start with a step
    without load (``neutral_step``); slack elements keep the settings, and so their hashes."""
    lig = {"ligament_stiffness_scale": 1.0}
    taut = adapter_settings({"class": "ligaments", **lig, "ligament_slack_shift": -0.1})
    slack = adapter_settings({"class": "ligaments", **lig, "ligament_slack_shift": 0.0})
    facets = {"class": "facets", "facet_gap_mm": 0.5, "facet_stiffness_n_per_mm": 50.0}
    assert taut["neutral_step"] is True
    assert min(v["slack_strain"] for v in taut["posterior"]["ligaments"].values()) < 0
    assert slack == {
        "posterior": posterior_of({"class": "ligaments", **lig, "ligament_slack_shift": 0.0})
    }
    assert adapter_settings(facets) == {"posterior": posterior_of(facets)}
    assert adapter_settings({"class": "none"}) is None


def test_per_config_settings_change_only_their_configurations_hash():
    base = {"geometry": "coarse"}
    per = PerConfigSettings(base, {5: {"posterior": {"facets": {}}}})
    assert per.of(4) == base
    assert per.of(5) == {"geometry": "coarse", "posterior": {"facets": {}}}
    assert settings_hash("calculix", per.of(4)) == settings_hash("calculix", base)
    assert settings_hash("calculix", per.of(5)) != settings_hash("calculix", base)


def test_complete_ids_need_all_four_load_cases_ok():
    records = pd.DataFrame(
        {
            "config_id": [1] * 4 + [2] * 4,
            "load_case": list(LOAD_CASES) * 2,
            "status": ["ok"] * 4 + ["ok", "failed", "ok", "ok"],
        }
    )
    assert complete_ids(records, 20) == {1}
    assert complete_ids(records.iloc[:0], 20) == set()


def test_noise_is_seeded_and_keeps_missing_levels():
    records = pd.DataFrame(
        {
            "config_id": [1, 1],
            "load_case": ["Flexion", "Extension"],
            "rom_deg": [[1.0, 2.0, None], [1.5, 2.5, 3.5]],
        }
    )
    a, b = _with_noise(records, 0.05, 3), _with_noise(records, 0.05, 3)
    assert a == b and a != _with_noise(records, 0.05, 4)
    assert a[1]["rom_deg"][2] is None  # Flexion sorts after Extension: its missing level stays
    noise = np.array(a[0]["rom_deg"]) - np.array([1.5, 2.5, 3.5])
    assert np.all(np.abs(noise) < 0.3) and np.any(noise != 0)


def test_a_class_short_of_complete_specimens_is_an_error(tmp_path, monkeypatch):
    cohort = settings(tmp_path)
    drawn = draw_specimens(SPACE, dict.fromkeys(CLASSES, 2), cohort, np.random.default_rng(0))
    drawn.insert(0, "config_id", FIRST_CONFIG_ID + np.arange(len(drawn)))
    records = pd.DataFrame(
        {
            "config_id": np.repeat(drawn["config_id"], 4),
            "load_case": list(LOAD_CASES) * len(drawn),
            "status": "failed",
        }
    )
    monkeypatch.setattr(cohort_module, "_run_rounds", lambda *a, **k: (drawn, records, {}))
    fe = FeRuntime("calculix", {"geometry": "coarse"}, cohort.store)
    with pytest.raises(SolverError, match=r"lacks complete specimens.*per_class") as info:
        build_cohort(fe, SPACE, cohort, [5.0, 10.0])
    assert isinstance(info.value, FemcalError)


def test_a_partial_cohort_needs_every_class_in_the_store(tmp_path):
    cohort = settings(tmp_path)
    fe = FeRuntime("calculix", {"geometry": "coarse"}, cohort.store)
    with pytest.raises(SolverError, match=r"no complete specimen of the classes \['none'"):
        build_cohort(fe, SPACE, cohort, [5.0, 10.0], partial=True)
    assert not (tmp_path / "cohort").exists()


@pytest.mark.slow
@requires_ccx
def test_small_real_cohort_is_written_and_rebuilt_from_its_store(tmp_path):
    """One specimen per class on the coarse mesh at 5 and 10 Nm (16 CalculiX jobs)."""
    cohort = settings(tmp_path, per_class=1)
    fe = FeRuntime("calculix", {"geometry": "coarse"}, cohort.store, n_workers=2)
    info = build_cohort(fe, SPACE, cohort, [5.0, 10.0])
    assert info["n_specimens"] == 4 and info["classes"] == dict.fromkeys(CLASSES, 1)
    out = tmp_path / "cohort"
    answers = pd.read_csv(out / "answers.csv")
    assert sorted(answers["class"]) == sorted(CLASSES)
    # answers row i is row i of the study's files: the same disc
    (configurations,) = (out / "measured" / "Test").glob("MaterialConfigurations*.csv")
    np.testing.assert_allclose(
        pd.read_csv(configurations).to_numpy(), answers[list(SPACE.names)].to_numpy()
    )
    measured = read_measurements(out / "measured" / "Test")
    clean = read_measurements(out / "clean" / "Test")
    assert len(measured.specimens) == 4
    diff = measured.rom_deg - clean.rom_deg
    assert 0 < np.nanstd(diff) < 0.2
    # A rerun is read from the store: nothing runs again, the same cohort is written.
    rerun = settings(tmp_path / "again", per_class=1, store=cohort.store)
    again = build_cohort(fe, SPACE, rerun, [5.0, 10.0])
    assert again["jobs_run_now"] == 0 and again["complete"]
    preview = build_cohort(
        fe,
        SPACE,
        settings(tmp_path / "p", per_class=1, store=cohort.store),
        [5.0, 10.0],
        partial=True,
    )
    assert preview["n_specimens"] == 4
    assert json.loads((out / "cohort.json").read_text())["n_specimens"] == 4
