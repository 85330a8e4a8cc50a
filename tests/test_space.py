"""Tests of femcal.space.ParameterSpace."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from femcal.errors import InputDataError
from femcal.schema import PARAMETER_NAMES, PARAMETER_UNITS
from femcal.space import ParameterSpace


@pytest.fixture
def space() -> ParameterSpace:
    return ParameterSpace(["a", "b", "c"], [0.0, -1.0, 10.0], [1.0, 1.0, 20.0])


def test_basics(space: ParameterSpace) -> None:
    assert space.dim == 3
    np.testing.assert_array_equal(space.width, [1.0, 2.0, 10.0])
    assert space.units == ("1", "1", "1")
    assert not space.lower.flags.writeable
    with pytest.raises(ValueError):
        space.lower[0] = 5.0


def test_study_units_default() -> None:
    sp = ParameterSpace(PARAMETER_NAMES, np.zeros(13), np.ones(13))
    assert sp.units == tuple(PARAMETER_UNITS[n] for n in PARAMETER_NAMES)


def test_to_unit_from_unit(space: ParameterSpace) -> None:
    x = np.array([[0.5, 0.0, 15.0], [0.0, -1.0, 10.0], [1.0, 1.0, 20.0]])
    u = space.to_unit(x)
    np.testing.assert_allclose(u, [[0.5, 0.5, 0.5], [0, 0, 0], [1, 1, 1]])
    np.testing.assert_allclose(space.from_unit(u), x)
    # batch dimensions are kept
    x3 = np.random.default_rng(0).random((4, 5, 3))
    assert space.to_unit(x3).shape == (4, 5, 3)
    np.testing.assert_allclose(space.to_unit(space.from_unit(x3)), x3)


def test_wrong_number_of_columns(space: ParameterSpace) -> None:
    with pytest.raises(InputDataError, match=r"must have 3 columns \(a, b, c\).*\(2, 2\)"):
        space.to_unit(np.zeros((2, 2)))
    with pytest.raises(InputDataError, match="Unit-box parameters must have 3 columns"):
        space.from_unit(np.zeros((1, 4)))


def test_contains_clip_exceedance(space: ParameterSpace) -> None:
    x = np.array([[0.5, 0.0, 15.0], [1.5, 0.0, 15.0], [0.5, -2.0, 25.0]])
    np.testing.assert_array_equal(space.contains(x), [True, False, False])
    np.testing.assert_array_equal(space.contains(x, atol=10.0), [True, True, True])
    assert space.contains(space.clip(x)).all()
    np.testing.assert_allclose(space.exceedance(x), [0.0, 0.5, 0.5 + 0.5])


@pytest.mark.parametrize(
    ("lower", "upper", "match"),
    [
        ([0.0, 2.0], [1.0, 1.0], r"Inverted or empty bounds for b: lower=2, upper=1"),
        ([0.0, 1.0], [1.0, 1.0], r"Inverted or empty bounds for b"),
        ([0.0, np.nan], [1.0, 1.0], "must be finite"),
        ([0.0, 0.0], [np.inf, 1.0], "must be finite"),
        ([0.0], [1.0, 1.0], r"got 2 names, 1 lower and 2 upper"),
    ],
)
def test_bad_bounds(lower: list[float], upper: list[float], match: str) -> None:
    with pytest.raises(InputDataError, match=match):
        ParameterSpace(["a", "b"], lower, upper)


def test_repeated_names_and_units() -> None:
    with pytest.raises(InputDataError, match=r"unique; repeated: \['a'\]"):
        ParameterSpace(["a", "a"], [0, 0], [1, 1])
    with pytest.raises(InputDataError, match="Got 1 units for 2 parameters"):
        ParameterSpace(["a", "b"], [0, 0], [1, 1], units=["MPa"])


def test_lhs_one_point_per_stratum(space: ParameterSpace) -> None:
    n = 17
    x = space.sample_lhs(n, np.random.default_rng(3))
    assert x.shape == (n, 3)
    assert space.contains(x).all()
    strata = np.floor(space.to_unit(x) * n).astype(int)
    for j in range(space.dim):
        np.testing.assert_array_equal(np.sort(strata[:, j]), np.arange(n))


def test_same_seed_same_sample(space: ParameterSpace) -> None:
    a = space.sample_lhs(8, np.random.default_rng(42))
    b = space.sample_lhs(8, np.random.default_rng(42))
    c = space.sample_lhs(8, np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    u1 = space.sample_uniform(5, np.random.default_rng(1))
    np.testing.assert_array_equal(u1, space.sample_uniform(5, np.random.default_rng(1)))
    assert space.contains(u1).all()


def test_dict_and_json_round_trip(space: ParameterSpace, tmp_path: Path) -> None:
    assert ParameterSpace.from_dict(space.to_dict()) == space
    path = tmp_path / "space.json"
    space.to_json(path)
    back = ParameterSpace.from_json(path)
    assert back == space
    assert hash(back) == hash(space)
    assert space != ParameterSpace(["a", "b", "c"], [0.0, -1.0, 10.0], [1.0, 1.0, 21.0])


def test_from_dict_and_json_errors(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="lacks the field 'upper'"):
        ParameterSpace.from_dict({"names": ["a"], "lower": [0.0]})
    with pytest.raises(InputDataError, match="does not exist; run the 'prepare' stage"):
        ParameterSpace.from_json(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"names": ["a"], "lower": [1.0], "upper": [0.0]}')
    with pytest.raises(InputDataError, match=r"bad\.json: Inverted"):
        ParameterSpace.from_json(bad)


def test_from_bounds_csv_crlf_and_lf(tmp_path: Path) -> None:
    text = "a, b\n0,7.5\n1,52.5\n"
    (tmp_path / "lf.csv").write_bytes(text.encode())
    (tmp_path / "crlf.csv").write_bytes(text.replace("\n", "\r\n").encode())
    lf = ParameterSpace.from_bounds_csv(tmp_path / "lf.csv")
    assert lf == ParameterSpace.from_bounds_csv(tmp_path / "crlf.csv")
    assert lf.names == ("a", "b")
    np.testing.assert_array_equal(lf.lower, [0.0, 7.5])
    np.testing.assert_array_equal(lf.upper, [1.0, 52.5])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("a,b\n0,0\n", r"expected 2 rows \(minimum, then maximum\).*got 1"),
        ("a,b\n0,0\n1,1\n2,2\n", r"expected 2 rows.*got 3"),
        ("a,b\n0,x\n1,1\n", r"column 'b' must hold two numbers"),
        ("a,b\n0,\n1,1\n", r"column 'b' must hold two numbers"),
        ("a,b\n0,1\n1,0\n", r"bounds\.csv: Inverted or empty bounds for b: lower=1, upper=0"),
    ],
)
def test_from_bounds_csv_errors(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bounds.csv"
    path.write_text(text)
    with pytest.raises(InputDataError, match=match):
        ParameterSpace.from_bounds_csv(path)


def test_from_bounds_csv_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="does not exist; run the 'fetch' stage"):
        ParameterSpace.from_bounds_csv(tmp_path / "ParameterBounds.csv")
