"""The reachability messages name the model whose envelope they mean, and the likelier cause
first: calibrate's (the disc alone) and diagnose's (the disc with effects) cannot read as a
contradiction.

A synthetic world (tests/synth.py) whose model ties extension to 1.5 x flexion: there a
Flexion/Extension swap leaves the disc's envelope and is named. No study data needed.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from femcal.calibration import SurrogateCurveModel
from femcal.effects.composite import EffectModel
from femcal.measurements import from_arrays
from femcal.reachability import (
    UnreachableMeasurementsError,
    build_envelope,
    check_reachability,
)
from femcal.stages.calibrate import fit_warnings

from synth import study_space, tidy_table

MOMENTS = np.arange(1.0, 6.0)
NAMES = [f"S{i}" for i in range(6)]


@pytest.fixture(scope="module")
def disc():
    from femcal.surrogates.nn import NeuralSurrogate

    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    return SurrogateCurveModel(surrogate, MOMENTS)


@pytest.fixture(scope="module")
def curves(disc):
    return disc.predict(study_space().sample_uniform(6, np.random.default_rng(1)))


def test_a_swap_names_the_disc_alone_and_missing_physics_before_the_convention(disc, curves):
    env = build_envelope(disc, sigma_model=0.02)
    swapped = from_arrays(NAMES, MOMENTS, curves[:, [1, 0, 2, 3]], source="swapped.csv")
    report = check_reachability(swapped, env)
    assert report.outside == NAMES
    with pytest.raises(
        UnreachableMeasurementsError,
        match=r"swapped\.csv: the measurements lie outside every curve the disc alone can produce "
        r"over its whole parameter box .*Likely cause: physics the disc alone lacks \(run "
        r"`femcal diagnose`: it fits the disc with each effect and names the one missing; "
        r"--effects adds it\); else a different load case convention: the curves fit with "
        r"Flexion and Extension swapped",
    ):
        report.enforce()
    # per specimen too (metrics.csv's reachability column)
    for note, k in zip(report.notes(), report.n_outside):
        assert note.startswith(f"{k}/20 points outside the envelope of the disc alone, worst")


def test_a_few_swapped_specimens_warn_with_the_same_order(disc, curves, caplog):
    env = build_envelope(disc, sigma_model=0.02)
    rom = curves.copy()
    rom[:2] = rom[:2, [1, 0, 2, 3]]
    report = check_reachability(from_arrays(NAMES, MOMENTS, rom, source="two.csv"), env)
    assert report.outside == NAMES[:2] and not report.refused
    with caplog.at_level(logging.WARNING, logger="femcal.reachability"):
        report.enforce()
    (record,) = caplog.records
    text = record.getMessage()
    assert text.startswith(
        "two.csv: 2 of 6 specimens have measured points outside every curve the disc alone can "
        "produce over its whole parameter box"
    )
    physics = text.index("likely cause: physics the disc alone lacks (run `femcal diagnose`")
    assert physics < text.index("else a different load case convention")


def test_an_envelope_with_effects_is_named_with_them(disc, curves, caplog):
    effects = ["neutral_zone", "facet_contact"]
    env = build_envelope(EffectModel(disc, effects), sigma_model=0.02, n_samples=64)
    assert env.model == "the disc with neutral_zone+facet_contact"
    inside = from_arrays(NAMES, MOMENTS, curves, source="cohort.csv")
    with caplog.at_level(logging.INFO, logger="femcal.reachability"):
        check_reachability(inside, env).enforce()
    assert caplog.records[-1].levelno == logging.INFO
    assert (
        caplog.records[-1]
        .getMessage()
        .startswith(
            "cohort.csv: every measured point lies within the envelope of the disc with "
            "neutral_zone+facet_contact (every curve it can produce over its parameter box;"
        )
    )


def test_a_refused_file_names_the_model_it_is_out_of_reach_of(disc, curves):
    env = build_envelope(disc, sigma_model=0.02)
    radians = from_arrays(NAMES, MOMENTS, curves / 57.29578, source="radians.csv")
    with pytest.raises(
        UnreachableMeasurementsError,
        match=r"radians\.csv: the measurements lie outside every curve the disc alone can "
        r"produce over its whole parameter box \(\d+ surrogate curves\).*multiply by 57\.3",
    ):
        check_reachability(radians, env).enforce()


@pytest.mark.parametrize(
    ("model", "tail"),
    [
        ("the disc alone", "; `femcal diagnose` checks them against the disc with effects"),
        ("the disc with neutral_zone", ""),
    ],
)
def test_calibrates_summary_line_names_the_envelope(model, tail):
    figures = {"n_specimens": 48, "n_outside_envelope": 7, "envelope_model": model}
    line = fit_warnings(figures, "out")
    assert line == (
        f"\nWARNING: 7 of 48 specimens have points outside every curve {model} can produce: "
        f"see out/metrics.csv (column reachability){tail}"
    )


def test_more_rotation_than_any_disc_names_missing_physics_first(disc, curves):
    env = build_envelope(disc, sigma_model=0.02)
    rom = curves.copy()
    rom[0] *= 3  # softer than the softest disc of the box, in every load case
    report = check_reachability(from_arrays(NAMES, MOMENTS, rom, source="soft.csv"), env)
    assert report.outside == ["S0"] and report.cause_key[0] == "above"
    assert report.cause[0].startswith(
        "physics the disc alone lacks (run `femcal diagnose`: it fits the disc with each effect "
        "and names the one missing; --effects adds it); else more rotation than any disc in the "
        "parameter box"
    )
