"""The hidden cohorts of experiments/hidden_cohorts.py (issue 11's measurement harness)."""

from __future__ import annotations

import numpy as np
import pytest

import experiments.hidden_cohorts as hc
from femcal.schema import LOAD_CASES


def _fe(n: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Power-law FE curves phi = a M^b at 1..5 Nm, shape (n, 4, 5)."""
    rng = np.random.default_rng(seed)
    moments = np.arange(1.0, 6.0)
    a = rng.uniform(0.3, 3.0, (n, 4, 1))
    b = rng.uniform(0.6, 0.9, (n, 4, 1))
    return moments, a * moments**b


def test_cohort_layout_protocols_and_truth():
    m, rom = _fe()
    c = hc.make_hidden_cohort(m, rom, seed=0)
    n = len(hc.CLASSES) * 8
    assert c.rom_deg.shape == (n, 4, len(hc.union_grid()))
    assert list(c.moments) == sorted(set().union(*map(set, hc.PROTOCOLS.values())))
    for i, proto in enumerate(c.truth["protocol"]):
        measured = np.isfinite(c.rom_deg[i]).all(axis=0)
        assert np.allclose(c.moments[measured], hc.PROTOCOLS[proto])
        assert not np.isfinite(c.rom_deg[i][:, ~measured]).any()
    counts = c.truth.groupby("class")["protocol"].value_counts().unstack()
    assert (counts.max(axis=1) - counts.min(axis=1) <= 1).all()
    assert c.truth["config_id"].is_unique
    assert np.nanmax(c.clean_deg) <= hc.ROM_MAX_DEG and np.nanmin(c.clean_deg) > 0
    row = c.truth[c.truth["class"] == "facet_contact+neutral_zone"].iloc[0]
    assert row["effects"] == "facet_contact+neutral_zone"
    assert hc.expected_effects(hc.UNEXPLAINED) == frozenset()
    assert len(c.to_long()) == int(np.isfinite(c.rom_deg).sum())


def test_same_seed_same_cohort_other_seed_other():
    m, rom = _fe()
    a, b = hc.make_hidden_cohort(m, rom, seed=1), hc.make_hidden_cohort(m, rom, seed=1)
    assert np.array_equal(a.rom_deg, b.rom_deg, equal_nan=True)
    other = hc.make_hidden_cohort(m, rom, seed=0)
    assert not np.array_equal(a.rom_deg, other.rom_deg, equal_nan=True)


def test_effects_act_on_their_load_cases_only():
    m, rom = _fe(1)
    q = np.array([1.0, 2.5, 5.0, 7.5])
    disc = hc.specimen_curves({}, m, rom[0], q)
    rng = np.random.default_rng(3)
    for comp, stiffer in (("facet", True), ("ligament", True), ("softening", False)):
        p = hc.draw_component(comp, m, rom[0], rng)
        out = hc.specimen_curves({comp: p}, m, rom[0], q)
        acts = np.isin(LOAD_CASES, hc.COMPONENT_LOAD_CASES[comp])
        assert np.allclose(out[~acts], disc[~acts])
        diff = out[acts] - disc[acts]
        assert np.all(diff <= 1e-9) if stiffer else np.all(diff >= -1e-9)
        assert np.abs(diff).max() > 0.05


@pytest.mark.parametrize("law", hc.LAWS["neutral_zone"])
def test_neutral_zone_laws_saturate(law):
    p = {"law": law, "range_deg": 1.0, "moment_nm": 1.0}
    phi = hc.series_rotation("neutral_zone", p, np.array([0.1, 1.0, 5.0, 50.0]))
    assert np.all(np.diff(phi) >= -1e-12) and phi[0] > 0 and phi[-1] <= 1.0 + 1e-9


def test_stratified_takes_every_class():
    labels = np.repeat(np.array(hc.CLASSES), 8)
    idx = hc.stratified(labels, 14)
    assert len(idx) == 14 and set(labels[idx]) == set(hc.CLASSES)


def test_component_curves_alone_match_single_classes_and_leave_the_cohort_unchanged():
    m, rom = _fe()
    c = hc.make_hidden_cohort(m, rom, seed=3)
    n_comp = len(hc.COMPONENT_NAMES)
    assert c.component_clean_deg.shape == (len(c.specimens), n_comp, 4, len(c.moments))
    for i, label in enumerate(c.labels):
        have = hc.COMPONENTS[label]
        for k, comp in enumerate(hc.COMPONENT_NAMES):
            alone = c.component_clean_deg[i, k]
            measured = np.isfinite(c.clean_deg[i])
            if comp not in have:
                assert not np.isfinite(alone).any()
                continue
            assert np.array_equal(np.isfinite(alone), measured)
            if len(have) == 1:
                assert np.allclose(alone[measured], c.clean_deg[i][measured])
            else:  # each component alone moves the curve less than both together
                both = np.abs(c.clean_deg[i] - c.component_clean_deg[i, k])
                assert np.nanmax(both) > 1e-6
    # computing them draws nothing (checked once against the cohorts before they existed)
    again = hc.make_hidden_cohort(m, rom, seed=3)
    assert np.array_equal(c.rom_deg, again.rom_deg, equal_nan=True)
    sub = c.subset([0, 40])
    assert sub.component_clean_deg.shape[:2] == (2, n_comp)
