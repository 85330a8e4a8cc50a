"""Tests of femcal.moments: the one moment policy of every command."""

from __future__ import annotations

import json
import logging
import math
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import yaml

from femcal.errors import ConfigError, InputDataError
from femcal.measurements import Measurements, from_arrays
from femcal.moments import DROPPED_COLUMNS, DROPPED_FILE, MomentPolicy, log_distance
from femcal.schema import LOAD_CASES
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
    assert (policy.growth, policy.max_log_ratio) == ((GROWTH, GROWTH), (LMAX, LMAX))
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


def test_a_validation_profile_gives_the_error_by_moment() -> None:
    profile = {"moments": [1.0, 2.0, 5.0], "rms_deg": [0.01, 0.02, 0.08]}
    surrogate = SimpleNamespace(
        moment_range_=(1.0, 5.0), best_val_mae_deg_=VAL_MAE, val_error_profile_=profile
    )
    policy = MomentPolicy.for_surrogate(surrogate, growth=GROWTH, max_log_ratio=LMAX)
    assert policy.profile == ((1.0, 2.0, 5.0), (0.01, 0.02, 0.08))
    sd = policy.sigma_surrogate([1.0, math.sqrt(2.0), 5.0, 7.5])
    # in range: interpolated in log-moment; beyond: the end's value grown as without a profile
    np.testing.assert_allclose(sd[:3], [0.01, 0.015, 0.08], rtol=1e-12)
    assert sd[3] == pytest.approx(0.08 * 1.5**GROWTH)
    # calibrate's weights are the inverse variances of the same sd
    got = policy.point_weights(np.array([1.0, 5.0]), np.ones(2), 0.05)
    e = policy.error_deg
    np.testing.assert_allclose(got, (0.05**2 + e**2) / (0.05**2 + np.array([0.01, 0.08]) ** 2))
    # an explicit error_deg is the whole in-range error (no profile)
    flat = MomentPolicy.for_surrogate(surrogate, growth=1, max_log_ratio=0.2, error_deg=0.05)
    assert flat.profile is None and flat.sigma_surrogate([1.0, 5.0]).tolist() == [0.05, 0.05]


def test_a_relative_profile_gives_the_error_where_the_specimen_sits() -> None:
    policy = MomentPolicy((1.0, 5.0), 0.03, 1.0, 0.5, ((1.0, 5.0), (0.01, 0.08)), (0.02, 0.03))
    rom = np.array([[2.0, 10.0], [np.nan, 4.0]])  # (2 curves, 2 moments), one unmeasured
    sd = policy.sigma_surrogate([1.0, 5.0], rom)
    np.testing.assert_allclose(sd, [[0.04, 0.3], [0.01, 0.12]])  # unmeasured: the profile
    beyond = policy.sigma_surrogate([7.5], np.array([10.0]))  # grown beyond the range
    assert beyond[0] == pytest.approx(0.03 * 10.0 * 1.5)
    assert policy.sigma_surrogate([1.0, 5.0]).tolist() == [0.01, 0.08]  # without curves
    surrogate = SimpleNamespace(
        moment_range_=(1.0, 5.0),
        best_val_mae_deg_=VAL_MAE,
        val_error_profile_={
            "moments": [1, 5],
            "rms_deg": [0.01, 0.08],
            "relative_rms": [0.02, 0.03],
        },
    )
    assert MomentPolicy.for_surrogate(surrogate, growth=1, max_log_ratio=0.5).relative == (
        0.02,
        0.03,
    )
    # calibrate's weights: the inverse variances of the same sd at each measured point
    got = policy.point_weights([1.0, 5.0], np.ones(rom.shape), 0.05, rom)
    expected = (0.05**2 + 0.03**2) / (0.05**2 + np.array([[0.04, 0.3], [0.01, 0.12]]) ** 2)
    np.testing.assert_allclose(got, expected)
    assert policy.average_sd([1.0, 5.0], np.ones(rom.shape), 0.05, None, rom) == pytest.approx(
        policy.unit_sd(0.05) / np.sqrt(expected.mean())
    )
    with pytest.raises(ConfigError, match=r"profile must be \(moments, sd\) of equal length"):
        MomentPolicy((1.0, 5.0), 0.03, 1.0, 0.5, ((1.0, 5.0), (0.01, 0.08)), (0.02,))


@pytest.mark.parametrize(
    "bad", [([1.0, 2.0], [0.1]), ([2.0, 1.0], [0.1, 0.1]), ([1.0], [-0.1]), "x", ([0.0], [0.1])]
)
def test_a_bad_profile_is_refused(bad: object) -> None:
    with pytest.raises(ConfigError, match=r"profile must be \(moments, sd\) of equal length"):
        MomentPolicy((1.0, 5.0), 0.03, 1.0, 0.2, bad)


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
    meas = measured(1.0, 1.25, 2.5, 3.75, 5.0)
    with warnings.catch_warnings(), caplog.at_level(logging.WARNING, logger="femcal.moments"):
        warnings.simplefilter("error")
        screened = policy.screen(meas)
    assert caplog.text == ""
    assert screened.measurements is meas
    assert screened.dropped.empty and list(screened.dropped.columns) == list(DROPPED_COLUMNS)


def test_the_in_vitro_protocol_is_accepted_with_a_warning(
    policy: MomentPolicy, caplog: pytest.LogCaptureFixture
) -> None:
    # 1.25 .. 7.5 Nm, the common in vitro protocol: 6.25 and 7.5 Nm are extrapolated.
    meas = measured(1.25, 2.5, 3.75, 5.0, 6.25, 7.5)
    with caplog.at_level(logging.WARNING, logger="femcal.moments"):
        with pytest.warns(UserWarning) as record:
            screened = policy.screen(meas)
    assert len(record) == 1
    assert record[0].filename == __file__  # the warning points at the caller
    text = str(record[0].message)
    assert text.startswith(
        "unit.csv: measured moments 6.25, 7.5 Nm lie outside the surrogate's trained moment "
        "range [1, 5] Nm (accepted up to [0.6, 8.33] Nm); the surrogate extrapolates there: "
        "surrogate error sd 0.0301 deg in range, 0.0614 deg at 6.25 Nm, 0.11 deg at 7.5 Nm, "
        "counted in sigma"
    )
    assert text in caplog.text
    assert screened.measurements is meas and screened.dropped.empty


def test_unmeasured_moments_are_not_checked(policy: MomentPolicy) -> None:
    rom = np.ones((1, 4, 3))
    rom[:, :, 2] = np.nan  # the 12 Nm column is empty
    meas = from_arrays(["A"], [1.0, 2.0, 12.0], rom, source="unit.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert policy.screen(meas).measurements is meas


@pytest.mark.parametrize(
    ("moments", "dropped", "kept"),
    [
        ((1.0, 5.0, 7.5, 12.0), "12", (1.0, 5.0, 7.5)),
        ((0.5, 1.0, 5.0), "0.5", (1.0, 5.0)),
        ((2.0, 9.0, 10.0), "9, 10", (2.0,)),
    ],
)
def test_points_beyond_the_limits_are_dropped_with_a_warning_naming_them(
    policy: MomentPolicy, moments: tuple, dropped: str, kept: tuple
) -> None:
    meas = measured(*moments)
    with pytest.warns(UserWarning, match="dropped") as record:
        screened = policy.screen(meas)
    message = str(next(r.message for r in record if "dropped" in str(r.message)))
    n = 2 * 4 * (len(moments) - len(kept))
    assert message.startswith(
        f"unit.csv: dropped {n} measured point(s) at moments {dropped} Nm, outside the moments "
        "the surrogate is used at, [0.6, 8.33] Nm (moments.max_log_ratio below 0.51, above "
        f"0.51): specimen 'A' Flexion {dropped.split(',')[0]} Nm; "
    )
    assert message.endswith(
        f"The outputs list them (dropped_points.csv); the other {2 * 4 * len(kept)} points are "
        "used. To use them, train the surrogate on a wider moment range."
    )
    assert screened.measurements.moments.tolist() == list(kept)
    assert screened.measurements.specimens == ("A", "B")
    table = screened.dropped
    assert len(table) == n and set(table["source"]) == {"unit.csv"}
    assert set(table["specimen"]) == {"A", "B"} and set(table["load_case"]) == set(LOAD_CASES)
    assert {f"{m:g}" for m in table["moment_nm"]} == set(dropped.split(", "))
    assert table["reason"].str.contains(r"Nm (?:below|above) the accepted 0\.6\.\.8\.33 Nm").all()


def test_a_specimen_with_only_dropped_points_is_left_out_whole_and_named(
    policy: MomentPolicy,
) -> None:
    rom = np.full((3, 4, 3), 2.0)
    rom[2, :, :2] = np.nan  # C: only at 12 Nm
    weight = np.ones_like(rom)
    weight[1, :, :2] = 0.0  # B: its points at 1 and 2 Nm count for nothing
    meas = from_arrays(["A", "B", "C"], [1.0, 2.0, 12.0], rom, weight=weight, source="u.csv")
    with pytest.warns(UserWarning, match=r"Specimens left out whole \(no point left\): B, C\."):
        screened = policy.screen(meas)
    assert screened.measurements.specimens == ("A",)
    assert screened.measurements.moments.tolist() == [1.0, 2.0]
    table = screened.dropped
    assert sorted(set(table["specimen"])) == ["A", "B", "C"]
    b_rest = table[(table["specimen"] == "B") & (table["moment_nm"] < 12)]
    assert len(b_rest) == 8 and (b_rest["weight"] == 0).all()
    assert b_rest["reason"].eq("its specimen has no other point of positive weight").all()


def test_dropped_points_are_written_for_the_outputs(policy: MomentPolicy, tmp_path: Path) -> None:
    with pytest.warns(UserWarning, match="dropped 8 measured point"):
        screened = policy.screen(measured(1.0, 2.0, 12.0))
    path = screened.write(tmp_path)
    assert path == tmp_path / DROPPED_FILE
    table = pd.read_csv(path)
    assert list(table.columns) == list(DROPPED_COLUMNS) and len(table) == 8
    assert table["rom_deg"].tolist() == [12.0] * 8  # the values the user measured
    MomentPolicy((1, 5), 0.03, GROWTH, LMAX).screen(measured(2.0)).write(tmp_path)
    assert pd.read_csv(path).empty  # a header only: nothing was dropped


@pytest.mark.parametrize(
    ("moments", "where"),
    [((12.0, 20.0), "12, 20"), ((0.1, 0.2), "0.1, 0.2")],
)
def test_a_file_without_a_usable_point_is_refused(
    policy: MomentPolicy, moments: tuple, where: str
) -> None:
    with pytest.raises(
        InputDataError,
        match=rf"^unit\.csv: no measured point is usable: every measured moment \(field "
        rf"moment_nm: {where} Nm\) lies outside the moments the surrogate is used at, \[0\.6, "
        r"8\.33\] Nm \(its trained range \[1, 5\] Nm widened as far as its error was measured: "
        r"moments\.max_log_ratio below 0\.51, above 0\.51\)\. Give the moments in Nm within "
        r"that interval, or train the surrogate on a wider moment range\.$",
    ):
        policy.screen(measured(*moments))


def test_a_file_whose_usable_points_all_weigh_nothing_is_refused(policy: MomentPolicy) -> None:
    rom = np.ones((1, 4, 2))
    weight = np.array([0.0, 1.0])[None, None, :].repeat(4, axis=1)  # 0 at 2 Nm, 1 at 12 Nm
    meas = from_arrays(["A"], [2.0, 12.0], rom, weight=weight, source="w.csv")
    with pytest.raises(
        InputDataError,
        match=r"^w\.csv: no measured point is usable: the points at moments in \[0\.6, 8\.33\] "
        r"Nm all have weight 0 \(field weight\) and the others lie outside that interval \(field "
        r"moment_nm: 12 Nm; .*\)\. Give the points inside it a positive weight\.$",
    ):
        policy.screen(meas)


def test_newton_millimetres_are_recognised(policy: MomentPolicy) -> None:
    with pytest.raises(
        InputDataError,
        match=r"no measured point is usable: every measured moment \(field moment_nm: 1250, 2500, "
        r"5000, 7500 Nm\) .* The moments look like N·mm \(1250, 2500, 5000, 7500\): divide "
        r"them by 1000 \(femcal reads moments in Nm\)\. Give the moments",
    ):
        policy.screen(measured(1250.0, 2500.0, 5000.0, 7500.0))


def test_a_load_case_in_newton_millimetres_beside_others_in_nm_is_refused(
    policy: MomentPolicy,
) -> None:
    """One load case given in N·mm (1000-5000) is named, not dropped as beyond the moments."""
    m = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 1000.0, 2000.0, 3000.0, 4000.0, 5000.0])
    rom = np.full((2, 4, m.size), np.nan)
    rom[:, :3, :5] = np.arange(1.0, 6.0)  # Flexion, Extension, LateralBending in Nm
    rom[:, 3, 5:] = np.arange(1.0, 6.0)  # AxialRotation in N·mm
    meas = from_arrays(["A", "B"], m, rom, source="mixed.csv")
    with pytest.raises(
        InputDataError,
        match=r"^mixed\.csv: the moments of load case AxialRotation \(all 2 specimens\) look "
        r"like N·mm, not Nm: field moment_nm holds 1000, 2000, 3000, 4000, 5000 there, and 1, 2, "
        r"3, 4, 5 for the other curves\. .* Divide those moments by 1000",
    ):
        policy.screen(meas)
    rom[1, 3] = np.nan  # one specimen only: named
    rom[1, 3, :5] = np.arange(1.0, 6.0)
    with pytest.raises(InputDataError, match=r"load case AxialRotation \(specimens 'A'\)"):
        policy.screen(from_arrays(["A", "B"], m, rom, source="mixed.csv"))


# -------------------------------------------------------------- both ends of the trained range
BELOW, ABOVE = (0.8, 1.1), (3.2, 0.51)  # (growth, max_log_ratio) of each side


@pytest.fixture
def two_sided(surrogate: SimpleNamespace) -> MomentPolicy:
    return MomentPolicy.for_surrogate(
        surrogate,
        growth={"below": BELOW[0], "above": ABOVE[0]},
        max_log_ratio={"below": BELOW[1], "above": ABOVE[1]},
    )


def test_each_side_has_its_own_growth_and_limit(two_sided: MomentPolicy) -> None:
    assert two_sided.growth == (0.8, 3.2) and two_sided.max_log_ratio == (1.1, 0.51)
    assert two_sided.accepted_range == pytest.approx((math.exp(-1.1), 5 * math.exp(0.51)))
    e = two_sided.error_deg
    sd = two_sided.sigma_surrogate([0.5, 0.75, 1.0, 5.0, 10.0])
    expected = [
        e * 2.0**0.8,  # 0.5 Nm: L = log 2 below
        e * (4 / 3) ** 0.8,
        e,
        e,
        e * 2.0**3.2,  # 10 Nm: L = log 2 above
    ]
    np.testing.assert_allclose(sd, expected, rtol=1e-12)
    assert two_sided.accepts([0.3, 0.34, 8.3, 8.4]).tolist() == [False, True, True, False]
    assert two_sided.as_params() == {
        "moments.error_growth.below": 0.8,
        "moments.error_growth.above": 3.2,
        "moments.max_log_ratio.below": 1.1,
        "moments.max_log_ratio.above": 0.51,
    }


def test_a_pair_a_mapping_and_one_number_are_the_same_policy() -> None:
    pair = MomentPolicy((1, 5), 0.03, (0.8, 3.2), [1.1, 0.51])
    mapping = MomentPolicy(
        (1, 5), 0.03, {"above": 3.2, "below": 0.8}, {"below": 1.1, "above": 0.51}
    )
    assert pair == mapping
    assert MomentPolicy((1, 5), 0.03, 2, 0.5).growth == (2.0, 2.0)


def test_half_a_newton_metre_is_used_where_the_low_end_was_measured(
    two_sided: MomentPolicy,
) -> None:
    """The study's grid starts at 0.5 Nm: accepted with a warning; 0.25 Nm is dropped."""
    with pytest.warns(UserWarning) as record:
        screened = two_sided.screen(measured(0.25, 0.5, 1.0, 2.0, 5.0))
    messages = [str(r.message) for r in record]
    assert any("dropped 8 measured point(s) at moments 0.25 Nm" in m for m in messages)
    outside = next(m for m in messages if "lie outside" in m)
    assert "measured moments 0.5 Nm lie outside" in outside
    assert f"{two_sided.sigma_surrogate(0.5)[0]:.3g} deg at 0.5 Nm" in outside
    assert screened.measurements.moments.tolist() == [0.5, 1.0, 2.0, 5.0]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"growth": -1.0}, r"growth \(moments\.error_growth, .*\) must be a number >= 0 or "),
        ({"growth": "fast"}, r"growth \(moments\.error_growth, .*; got 'fast'"),
        ({"growth": (1.0, 2.0, 3.0)}, r"one per side .*; got \(1\.0, 2\.0, 3\.0\)"),
        ({"growth": {"low": 1.0, "above": 2.0}}, r"\{below: \.\.\., above: \.\.\.\}; got \{'low'"),
        ({"growth": {"above": 2.0}}, r"got \{'above': 2\.0\}\. Set each side"),
        ({"max_log_ratio": float("nan")}, r"max_log_ratio \(moments\.max_log_ratio, .*got nan"),
        ({"max_log_ratio": (0.5, -0.1)}, r"max_log_ratio .* got \(0\.5, -0\.1\)\. Set each side"),
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
        policy.screen(measured(1.25, 2.5, 5.0, 7.5))
    with pytest.warns(UserWarning, match=r"dropped 8 measured point\(s\) at moments 12 Nm"):
        assert policy.screen(measured(1.25, 12.0)).measurements.moments.tolist() == [1.25]


def test_the_shipped_settings_use_the_studys_half_newton_metre() -> None:
    """params.yaml's low end is measured: 0.5 Nm (the study's first point) is used."""
    settings = _moment_settings(yaml.safe_load((ROOT / "params.yaml").read_text()))
    growth, limit = settings["error_growth"], settings["max_log_ratio"]
    assert growth[0] < growth[1]  # measured: the error grows more slowly below the range
    policy = MomentPolicy((1, 5), 0.03, growth=growth, max_log_ratio=limit)
    with pytest.warns(UserWarning, match=r"measured moments 0\.5 Nm lie outside"):
        screened = policy.screen(measured(0.5, 1.0, 2.5, 5.0))
    assert screened.dropped.empty and screened.measurements.moments[0] == 0.5


def test_cli_settings_errors() -> None:
    with pytest.raises(ConfigError, match=r"p\.yaml: missing setting 'moments'\. Add it"):
        _moment_settings({"_path": "p.yaml"})
    for bad in ("far", {"below": 1.0}, {"below": 1.0, "above": True}, float("nan")):
        with pytest.raises(
            ConfigError,
            match=r"p\.yaml: moments\.max_log_ratio must be a number >= 0 per side of the "
            r"trained moment range, \{below: \.\.\., above: \.\.\.\} \(or one number for both\); "
            rf"got {re.escape(repr(bad))}\. Use the values measured by",
        ):
            _moment_settings(
                {"_path": "p.yaml", "moments": {"error_growth": 3, "max_log_ratio": bad}}
            )
    two = {"error_growth": {"below": 0.8, "above": 3}, "max_log_ratio": 0.5}
    assert _moment_settings({"moments": two}) == {
        "error_growth": (0.8, 3.0),
        "max_log_ratio": (0.5, 0.5),
    }


def test_the_shipped_settings_are_the_measured_ones() -> None:
    """params.yaml's moments are what bench_extrapolation measured at each end (the experiments
    pipeline's metrics, experiments/metrics/bench_extrapolation.json)."""
    chosen = json.loads((ROOT / "experiments" / "metrics" / "bench_extrapolation.json").read_text())
    settings = _moment_settings(yaml.safe_load((ROOT / "params.yaml").read_text()))
    for key in ("error_growth", "max_log_ratio"):
        measured_pair = tuple(chosen["chosen"][key][side] for side in ("below", "above"))
        assert settings[key] == pytest.approx(measured_pair), key
