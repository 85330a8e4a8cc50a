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


def _fitted(name: str, chi2_per_dof: float) -> SpecimenDiagnosis:
    s = _specimen(name, None)
    s.adequacy = {"final": {"chi2": 20.0 * chi2_per_dof, "dof": 20.0}}
    return s


def test_residuals_beyond_the_stated_noise_say_it_looks_too_small():
    # eight specimens whose final fits leave 3 chi-square units per degree of freedom: the
    # residuals' sd is sqrt(3) = 1.7 times the noise counted
    lines = _printed([_fitted(f"S{k}", 3.0) for k in range(8)])
    (line,) = [x for x in lines if x.startswith("the stated noise looks too small")]
    assert "median chi-square per degree of freedom is 3.00 over 8 specimens" in line
    assert "about 1.7 times the 0.05 deg counted" in line and "--noise-deg" in line


def test_residuals_within_the_noise_or_too_few_specimens_say_nothing():
    assert not [
        x for x in _printed([_fitted(f"S{k}", 0.8) for k in range(8)]) if "noise looks" in x
    ]
    few = [_fitted(f"S{k}", 3.0) for k in range(7)]  # the median of seven is not enough
    assert not [x for x in _printed(few) if "noise looks" in x]
    diag = Diagnosis(few, 0.05, 0.05, 0.0, 0.0, np.array([1.0]), 1.0)
    assert diag.noise_check() is None and diag.to_dict()["noise_check"] is None
