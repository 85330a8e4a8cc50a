"""What `femcal diagnose` prints (femcal.stages.diagnose.describe)."""

from __future__ import annotations

import numpy as np

from femcal.diagnose.result import Diagnosis, SpecimenDiagnosis
from femcal.stages.diagnose import SHOWN, describe


def _specimen(name: str, apart_sigma: float | None):
    n = None
    if apart_sigma is not None:
        n = {
            "between": ["facet_contact", "facet_contact+neutral_zone"],
            "criterion_gap": 2.0,
            "load_case": "Extension",
            "moment_nm": 0.6,
            "difference_deg": 0.2,
            "difference_sigma": apart_sigma,
            "repeats_to_settle": int(np.ceil(12.0 / apart_sigma**2)),
        }
    return SpecimenDiagnosis(
        specimen=name,
        verdict="facet_contact",
        baseline_mae_deg=0.2,
        ranking=[],
        residuals=np.zeros((4, 3)),
        effects=["facet_contact"],
        next_measurement=n,
    )


def _printed(specimens) -> list[str]:
    diag = Diagnosis(
        specimens=specimens,
        sigma_deg=0.05,
        noise_deg=0.05,
        noise_sd_deg=0.0,
        surrogate_error_deg=0.0,
        moments=np.array([1.0, 2.5, 5.0]),
        seconds=1.0,
    )
    figures = {
        "diagnosis": diag,
        "n_specimens": len(specimens),
        "user_effects": [],
        "user_effect_paths": [],
    }
    return describe(figures)


def test_close_calls_a_few_measurements_settle_are_named():
    lines = _printed([_specimen("A", 2.0), _specimen("B", 0.3), _specimen("C", None)])
    (line,) = [x for x in lines if x.startswith("close calls")]
    assert "A: Extension at 0.6 Nm, 3x" in line
    assert "B:" not in line and "more" not in line  # B would need 134 measurements


def test_beyond_a_few_close_calls_the_rest_are_counted():
    lines = _printed([_specimen(f"S{i}", 2.0) for i in range(SHOWN + 2)])
    (line,) = [x for x in lines if x.startswith("close calls")]
    assert f"S{SHOWN - 1}:" in line and f"S{SHOWN}:" not in line
    assert "and 2 more" in line


def test_without_a_practical_measurement_nothing_is_printed_about_it():
    assert not [x for x in _printed([_specimen("B", 0.3)]) if x.startswith("close calls")]
