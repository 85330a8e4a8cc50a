"""Tests of femcal.moments: the one moment policy of every command."""

from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from femcal.errors import ConfigError, InputDataError
from femcal.measurements import Measurements, from_arrays
from femcal.moments import MomentPolicy, log_distance
from femcal.stages.common import moment_settings as _moment_settings

GROWTH = 3.2
LMAX = 0.51
VAL_MAE = 0.024  # deg; sd = 0.024 * sqrt(pi / 2) = 0.0301
ROOT = Path(__file__).resolve().parents[1]


def measured(*moments: float, source: str = "unit.csv") -> Measurements:
    m = np.asarray(moments, dtype=float)
    rom = np.broadcast_to(m, (2, 4, m.size)).copy()
    return from_arrays(["A", "B"], m, rom, source=source)


@pytest.fixture
def surrogate() -> SimpleNamespace:
    """What the policy reads of a fitted surrogate."""
    return SimpleNamespace(moment_range_=(1.0, 5.0), best_val_mae_deg_=VAL_MAE)


@pytest.fixture
def policy(surrogate: SimpleNamespace) -> MomentPolicy:
    return MomentPolicy.for_surrogate(surrogate, growth=GROWTH, max_log_ratio=LMAX)


def test_for_surrogate_converts_the_validation_mae_to_an_sd(policy: MomentPolicy) -> None:
    assert policy.trained_range == (1.0, 5.0)
    assert policy.error_deg == pytest.approx(VAL_MAE * math.sqrt(math.pi / 2))
    assert (policy.growth, policy.max_log_ratio) == (GROWTH, LMAX)
    assert policy.accepted_range == pytest.approx((math.exp(-LMAX), 5 * math.exp(LMAX)))


def test_for_surrogate_explicit_error_and_old_models(caplog: pytest.LogCaptureFixture) -> None:
    explicit = MomentPolicy.for_surrogate(
        SimpleNamespace(moment_range_=(2, 4), best_val_mae_deg_=1.0),
        growth=1.0,
        max_log_ratio=0.2,
        error_deg=0.05,
    )
    assert explicit.error_deg == 0.05 and explicit.trained_range == (2.0, 4.0)
    # Saved without moment_range_ (trained on 1..5 Nm) and without a validation error.
    with caplog.at_level(logging.WARNING, logger="femcal.moments"):
        old = MomentPolicy.for_surrogate(
            SimpleNamespace(best_val_mae_deg_=float("nan")), growth=1.0, max_log_ratio=0.2
        )
    assert old.trained_range == (1.0, 5.0) and old.error_deg == 0.0
    assert "has no validation error" in caplog.text


def test_log_distance_and_sigma_surrogate(policy: MomentPolicy) -> None:
    moments = np.array([0.5, 1.0, 3.0, 5.0, 7.5, 10.0])
    L = np.array([math.log(2), 0, 0, 0, math.log(1.5), math.log(2)])
    np.testing.assert_allclose(log_distance(moments, (1, 5)), L, atol=1e-12)
    np.testing.assert_allclose(policy.log_distance(moments), L, atol=1e-12)
    sd = policy.sigma_surrogate(moments)
    assert sd.shape == (6,)
    e = VAL_MAE * math.sqrt(math.pi / 2)
    np.testing.assert_allclose(sd, e * np.exp(GROWTH * L))
    # Inside the range, the surrogate's own error; at 7.5 Nm (L = 0.405) 3.66 times it.
    np.testing.assert_allclose(sd[1:4], [e, e, e])
    assert sd[4] / e == pytest.approx(1.5**GROWTH)
    np.testing.assert_allclose(policy.weights(moments), (e / sd) ** 2)
    assert policy.sigma_surrogate(3.0).shape == (1,)


def test_point_weights_are_inverse_variances(policy: MomentPolicy) -> None:
    moments = np.array([3.0, 7.5])
    e = VAL_MAE * math.sqrt(math.pi / 2)
    sd = policy.sigma_surrogate(moments)
    w = np.array([[1.0, 1.0], [4.0, 4.0], [0.0, 2.0]])  # (3, m): single, mean of 4, left out
    # Without a noise: the weight scales the whole inverse variance (as before).
    np.testing.assert_allclose(policy.point_weights(moments, w), w * (e / sd) ** 2)
    got = policy.point_weights(moments, w, 0.05)
    var = 0.05**2 / np.where(w > 0, w, 1) + sd**2
    np.testing.assert_allclose(got[w > 0], ((0.05**2 + e**2) / var)[w > 0], rtol=1e-12)
    assert got[0, 0] == pytest.approx(1.0)  # one measurement in range
    assert got[2, 0] == 0.0
    # Four repeats gain less than 4x: the surrogate's error is not averaged.
    assert 1.0 < got[1, 0] < 4.0
    assert got[1, 0] == pytest.approx((0.05**2 + e**2) / (0.05**2 / 4 + e**2))


def test_average_sd_is_the_scale_of_a_point_of_average_weight(policy: MomentPolicy) -> None:
    e = VAL_MAE * math.sqrt(math.pi / 2)
    moments = np.array([1.0, 3.0, 5.0])
    one = policy.average_sd(moments, np.ones((2, 3)), 0.05)
    assert one == pytest.approx(math.hypot(0.05, e))
    # The mean of 4 repeats everywhere: the noise over 2, the surrogate's error whole.
    assert policy.average_sd(moments, np.full((2, 3), 4.0), 0.05) == pytest.approx(
        math.sqrt(0.05**2 / 4 + e**2)
    )
    # Mixed: 1 / sd^2 is the mean inverse variance of the counted points.
    w = np.array([[1.0, 4.0, 0.0]])
    var = np.array([0.05**2 + e**2, 0.05**2 / 4 + e**2])
    expected = 1 / math.sqrt(np.mean(1 / var))
    assert policy.average_sd(moments, w, 0.05) == pytest.approx(expected)
    assert policy.average_sd(moments, w, 0.05, mask=[[True, False, True]]) == pytest.approx(one)
    with pytest.raises(ConfigError, match="no point has a positive weight"):
        policy.average_sd(moments, np.zeros((1, 3)), 0.05)


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), "a", True])
def test_point_weights_refuse_a_bad_noise(policy: MomentPolicy, bad: object) -> None:
    with pytest.raises(ConfigError, match=r"measurement noise sd must be a finite number > 0"):
        policy.point_weights([3.0], [1.0], bad)


def test_moments_inside_are_silent(policy: MomentPolicy, caplog: pytest.LogCaptureFixture) -> None:
    with warnings.catch_warnings(), caplog.at_level(logging.WARNING, logger="femcal.moments"):
        warnings.simplefilter("error")
        policy.check(measured(1.0, 1.25, 2.5, 3.75, 5.0))
    assert caplog.text == ""


def test_the_in_vitro_protocol_is_accepted_with_a_warning(
    policy: MomentPolicy, caplog: pytest.LogCaptureFixture
) -> None:
    # 1.25 .. 7.5 Nm, the common in vitro protocol: 6.25 and 7.5 Nm are extrapolated.
    meas = measured(1.25, 2.5, 3.75, 5.0, 6.25, 7.5)
    with caplog.at_level(logging.WARNING, logger="femcal.moments"):
        with pytest.warns(UserWarning) as record:
            policy.check(meas)
    assert len(record) == 1
    text = str(record[0].message)
    assert text.startswith(
        "unit.csv: measured moments 6.25, 7.5 Nm lie outside the surrogate's trained moment "
        "range [1, 5] Nm (accepted up to [0.6, 8.33] Nm); the surrogate extrapolates there: "
        "surrogate error sd 0.0301 deg in range, 0.0614 deg at 6.25 Nm, 0.11 deg at 7.5 Nm, "
        "counted in sigma"
    )
    assert text in caplog.text


def test_unmeasured_moments_are_not_checked(policy: MomentPolicy) -> None:
    rom = np.ones((1, 4, 3))
    rom[:, :, 2] = np.nan  # the 12 Nm column is empty
    meas = from_arrays(["A"], [1.0, 2.0, 12.0], rom, source="unit.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy.check(meas)


@pytest.mark.parametrize(
    ("moments", "refused"),
    [((1.0, 5.0, 7.5, 12.0), "12"), ((0.5, 1.0, 5.0), "0.5"), ((2.0, 9.0, 10.0), "9, 10")],
)
def test_moments_far_outside_are_refused(
    policy: MomentPolicy, moments: tuple, refused: str
) -> None:
    with pytest.raises(InputDataError) as info:
        policy.check(measured(*moments))
    message = str(info.value)
    assert message.startswith(
        f"unit.csv: measured moments {refused} Nm are too far outside the surrogate's trained "
        "moment range [1, 5] Nm: moments in [0.6, 8.33] Nm are accepted (the trained range "
        "widened by the factor e^0.51 = 1.67 on each side, moments.max_log_ratio"
    )
    assert message.endswith(
        "Delete the points at those moments from the measurements, or train the surrogate on a "
        "wider moment range."
    )
    assert "N·mm" not in message


def test_newton_millimetres_are_recognised(policy: MomentPolicy) -> None:
    with pytest.raises(
        InputDataError,
        match=r"measured moments 1250, 2500, 5000, 7500 Nm are too far outside .* The moments "
        r"look like N·mm \(1250, 2500, 5000, 7500\): divide them by 1000 \(femcal reads moments "
        r"in Nm\)\. Delete the points",
    ):
        policy.check(measured(1250.0, 2500.0, 5000.0, 7500.0))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"growth": -1.0}, r"growth \(moments\.error_growth\) must be a finite number >= 0; "),
        ({"growth": "fast"}, r"growth \(moments\.error_growth\) .*; got 'fast'"),
        ({"max_log_ratio": float("nan")}, r"max_log_ratio \(moments\.max_log_ratio\) .*got nan"),
        ({"max_log_ratio": -0.1}, r"max_log_ratio .* got -0\.1\. Set it to a non-negative"),
        ({"error_deg": float("inf")}, r"error_deg \(the surrogate's error sd in degrees\)"),
        ({"error_deg": True}, r"error_deg .*; got True"),
        ({"trained_range": (5, 1)}, r"two finite moments in Nm with 0 < lo < hi; got \(5, 1\)"),
        ({"trained_range": (0, 5)}, r"0 < lo < hi; got \(0, 5\)"),
        ({"trained_range": (1,)}, r"trained_range must be a pair \(lo, hi\) .*; got \(1,\)"),
    ],
)
def test_bad_settings(kwargs: dict, match: str) -> None:
    args = {"trained_range": (1, 5), "error_deg": 0.03, "growth": GROWTH, "max_log_ratio": LMAX}
    args.update(kwargs)
    with pytest.raises(ConfigError, match=match):
        MomentPolicy(**args)


def test_bad_moments_for_log_distance() -> None:
    with pytest.raises(InputDataError, match=r"moments must be finite and > 0 Nm; got \[0\.0"):
        log_distance([0.0, 1.0], (1, 5))


@pytest.mark.parametrize("params_file", ["params.yaml", "fe/params.yaml"])
def test_the_shipped_settings_accept_the_in_vitro_protocol(params_file: str) -> None:
    params = yaml.safe_load((ROOT / params_file).read_text())
    settings = _moment_settings(params)
    assert "max_extrapolation" not in params["calibrate"]
    policy = MomentPolicy(
        (1, 5), 0.03, growth=settings["error_growth"], max_log_ratio=settings["max_log_ratio"]
    )
    with pytest.warns(UserWarning, match=r"measured moments 7\.5 Nm lie outside"):
        policy.check(measured(1.25, 2.5, 5.0, 7.5))
    with pytest.raises(InputDataError, match=r"measured moments 12 Nm are too far outside"):
        policy.check(measured(1.25, 12.0))


def test_cli_settings_errors() -> None:
    with pytest.raises(ConfigError, match=r"p\.yaml: missing setting 'moments'\. Add it"):
        _moment_settings({"_path": "p.yaml"})
    with pytest.raises(
        ConfigError, match=r"p\.yaml: moments\.max_log_ratio must be a number >= 0; got 'far'"
    ):
        _moment_settings(
            {"_path": "p.yaml", "moments": {"error_growth": 3, "max_log_ratio": "far"}}
        )
