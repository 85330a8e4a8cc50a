"""A flat effect inside the box shares its probability with something outside the library
(femcal.diagnose.balance).

The disc is the synthetic study's surrogate (``synth``) at the middle of its box; the facet
is femcal's own law in its tied form, read at two parameter vectors: no gap and a linear
law (it acts from 0 Nm: a stand-in for a disc stiffer in extension and axial rotation), and a
2 deg gap (it engages).
"""

from __future__ import annotations

import numpy as np
import pytest

from femcal.calibration import SurrogateCurveModel
from femcal.diagnose import UNEXPLAINED
from femcal.diagnose.balance import SHARE, flat_note, shared_out
from femcal.diagnose.outside import ShapeReader
from femcal.effects.base import get_effect
from femcal.effects.terms import Model, Term
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = np.arange(1.0, 5.01, 0.5)
FACET = Model.of(Term("facet_contact"))


@pytest.fixture(scope="module")
def reader():
    table = tidy_table(24, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(16, 16), max_epochs=20, patience=20, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    base = SurrogateCurveModel(surrogate, MOMENTS)
    return ShapeReader(base, np.ones((1, 4, len(MOMENTS)), dtype=bool))


def _facet(gap_deg: float) -> np.ndarray:
    """Unit coordinates (dim,) of the disc at the middle of its box with a linear facet
    (0.5 Nm/deg) after ``gap_deg``."""
    facet = get_effect("facet_contact")
    names = [p.name for p in facet.parameters]
    physical = {"facet_gap_deg": gap_deg, "facet_stiffness": 0.5, "facet_exponent": 1.0}
    physical["facet_onset_deg"] = 0.05
    unit = facet.to_unit(np.array([[physical[n] for n in names]]))[0]
    return np.concatenate([np.full(study_space().dim, 0.5), unit])


def _probabilities() -> dict:
    return {
        "models": {"facet_contact": 0.96, "none": 0.04},
        "inclusion": {"facet_contact": 0.96},
        "outside_library": 0.0,
    }


def test_a_facet_acting_from_zero_shares_its_probability(reader):
    got = shared_out(_probabilities(), {"facet_contact": (FACET, _facet(0.0))}, FACET, reader, 0)
    assert got is not None
    (reading,) = got["stand_ins"].values()
    assert reading["stand_in"] == pytest.approx(SHARE)  # flat in both load cases it acts in
    assert got["inclusion"]["facet_contact"] == pytest.approx(0.96 * (1 - SHARE), abs=1e-4)
    assert got["models"][UNEXPLAINED] == pytest.approx(0.96 * SHARE, abs=1e-4)
    assert got["outside_library"] == pytest.approx(0.96 * SHARE, abs=1e-4)
    assert sum(got["models"].values()) == pytest.approx(1.0, abs=1e-3)


def test_a_facet_that_engages_after_a_gap_keeps_its_probability(reader):
    assert (
        shared_out(_probabilities(), {"facet_contact": (FACET, _facet(2.0))}, FACET, reader, 0)
        is None
    )


def test_the_note_names_the_flat_effect_and_its_load_cases(reader):
    got = shared_out(_probabilities(), {"facet_contact": (FACET, _facet(0.0))}, FACET, reader, 0)
    note = flat_note(got)
    assert note.startswith("Possibly a stand-in: facet_contact acts from about 0 Nm in ")
    assert "Extension (flatness" in note and "AxialRotation (flatness" in note
    assert f"`{UNEXPLAINED}` (outside the library 0.48)" in note
    assert flat_note(_probabilities()) is None
