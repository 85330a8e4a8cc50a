"""The diagnosis' sigma from a surrogate error given per point (femcal.diagnose.search)."""

from __future__ import annotations

import numpy as np
import pytest

from femcal.diagnose.search import _per_moment, diagnose
from femcal.errors import ConfigError


def test_a_per_point_error_is_averaged_per_moment_over_the_measured_points() -> None:
    value = np.arange(2 * 4 * 3, dtype=float).reshape(2, 4, 3)
    mask = np.ones(value.shape, dtype=bool)
    mask[:, :, 2] = False  # the third moment measured nowhere: the mean of every point
    mask[0, :, 0] = False  # the first moment measured in the second specimen only
    got = _per_moment(value, mask)
    np.testing.assert_allclose(
        got, [value[1, :, 0].mean(), value[:, :, 1].mean(), value[:, :, 2].mean()]
    )
    per_moment = np.array([0.1, 0.2, 0.3])
    assert _per_moment(per_moment, mask) is per_moment  # one per moment: as given


def test_a_negative_or_missing_error_is_refused_before_any_fit() -> None:
    rom = np.ones((2, 4, 3))
    bad = np.full((2, 4, 3), 0.01)
    bad[1, 2, 0] = np.nan
    with pytest.raises(
        ConfigError, match=r"surrogate_error_deg must be finite and >= 0 \(one value"
    ):
        diagnose(
            None, rom, specimens=["a", "b"], noise_deg=0.05, surrogate_error_deg=bad, candidates=[]
        )


def test_the_parts_of_a_specimens_sigma() -> None:
    from femcal.diagnose.result import SpecimenDiagnosis

    sigma = np.full((4, 3), np.hypot(0.05, 0.12))
    sur = np.full((4, 3), 0.12)
    sigma[2], sur[2] = np.hypot(0.05, 0.02), 0.02  # a load case with a smaller surrogate error
    sigma[3], sur[3] = np.nan, np.nan  # not measured
    spec = SpecimenDiagnosis(
        specimen="S",
        verdict="none",
        baseline_mae_deg=0.1,
        ranking=[],
        residuals=np.zeros((4, 3)),
        sigma=sigma,
        surrogate_sd=sur,
    )
    parts = spec.to_dict()["sigma_parts"]
    assert parts["noise_deg"] == pytest.approx(0.05)
    assert parts["surrogate_deg"] == pytest.approx((0.12 * 2 + 0.02) / 3)
    assert parts["surrogate_by_load_case_deg"] == pytest.approx(
        {"Flexion": 0.12, "Extension": 0.12, "LateralBending": 0.02}
    )
    assert "AxialRotation" not in parts["sigma_by_load_case_deg"]
