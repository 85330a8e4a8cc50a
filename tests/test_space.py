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


# --------------------------------------------------------------- scales (linear and log)
@pytest.fixture
def mixed() -> ParameterSpace:
    # a linear parameter that crosses zero, two log parameters spanning decades
    return ParameterSpace(
        ["a", "k", "e"], [-1.0, 0.5, 1e-3], [1.0, 50.0, 10.0], scales=["linear", "log", "log"]
    )


def test_log_scale_maps_decades_evenly(mixed: ParameterSpace) -> None:
    assert mixed.scales == ("linear", "log", "log")
    np.testing.assert_array_equal(mixed.is_log, [False, True, True])
    x = np.array([[0.0, 5.0, 0.1], [-1.0, 0.5, 1e-3], [1.0, 50.0, 10.0]])
    u = mixed.to_unit(x)
    np.testing.assert_allclose(u, [[0.5, 0.5, 0.5], [0, 0, 0], [1, 1, 1]], atol=1e-15)
    np.testing.assert_allclose(mixed.from_unit(u), x, rtol=1e-14)
    # a linear space maps exactly as before: (x - lower) / width
    np.testing.assert_array_equal(mixed.linear().to_unit(x), (x - mixed.lower) / mixed.width)


def test_numpy_and_torch_agree(mixed: ParameterSpace) -> None:
    torch = pytest.importorskip("torch")
    u = np.random.default_rng(3).random((7, 3))
    x = mixed.from_unit(u)
    for dtype, tol in ((torch.float64, 1e-14), (torch.float32, 1e-6)):
        xt = mixed.from_unit(torch.tensor(u, dtype=dtype))
        assert isinstance(xt, torch.Tensor) and xt.dtype == dtype
        np.testing.assert_allclose(xt.double().numpy(), x, rtol=tol)
        ut = mixed.to_unit(torch.tensor(x, dtype=dtype))
        np.testing.assert_allclose(ut.double().numpy(), u, atol=tol * 10)


@pytest.mark.parametrize("where", ["to_unit", "from_unit"])
def test_jacobians_match_finite_differences(mixed: ParameterSpace, where: str) -> None:
    rng = np.random.default_rng(11)
    u = rng.uniform(0.05, 0.95, (5, 3))
    point = u if where == "from_unit" else mixed.from_unit(u)
    f = getattr(mixed, where)
    jac = getattr(mixed, f"{where}_jacobian")(point)
    assert jac.shape == point.shape
    # central differences, step relative to each coordinate's size: truncation ~h^2
    h = 1e-6 * np.maximum(np.abs(point), 1e-3)
    fd = (f(point + h) - f(point - h)) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=1e-7)
    # the two Jacobians are reciprocal (the maps are inverse to each other)
    if where == "from_unit":
        np.testing.assert_allclose(jac * mixed.to_unit_jacobian(mixed.from_unit(u)), 1.0)


def test_torch_jacobian_matches_autograd(mixed: ParameterSpace) -> None:
    torch = pytest.importorskip("torch")
    u = torch.tensor(np.random.default_rng(5).random((4, 3)), dtype=torch.float64)
    u.requires_grad_(True)
    (grad,) = torch.autograd.grad(mixed.from_unit(u).sum(), u)
    np.testing.assert_allclose(grad.numpy(), mixed.from_unit_jacobian(u.detach()).numpy())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"scales": ["log", "linear"]},
            r"log-scaled parameter needs a lower bound > 0; got a: lower=0",
        ),
        ({"scales": ["linear", "ln"]}, r"Unknown parameter scale for b: 'ln'; use one of"),
        ({"scales": ["linear"]}, r"Got 1 scales for 2 parameters"),
    ],
)
def test_bad_scales(kwargs: dict, match: str) -> None:
    with pytest.raises(InputDataError, match=match):
        ParameterSpace(["a", "b"], [0.0, 1.0], [1.0, 2.0], **kwargs)


def test_scales_in_equality_dict_and_concat(mixed: ParameterSpace) -> None:
    assert mixed != mixed.linear()
    assert ParameterSpace.from_dict(mixed.to_dict()) == mixed
    # a linear space's description is what it always was (prepare's space.json unchanged)
    assert "scales" not in mixed.linear().to_dict()
    joint = ParameterSpace.concat(
        mixed.linear(), ParameterSpace(["z"], [1.0], [2.0], scales=["log"])
    )
    assert joint.names == ("a", "k", "e", "z")
    assert joint.scales == ("linear", "linear", "linear", "log")
    # log_where_positive: the surrogate network's rule
    assert mixed.linear().log_where_positive().scales == ("linear", "log", "log")
    # the study's exceedance is in linear units whatever the scales
    x = np.array([[2.0, 5.0, 20.0]])
    np.testing.assert_allclose(mixed.exceedance(x), [0.5 + 10 / (10 - 1e-3)])


def test_romnet_inputs_bit_identical_to_the_trained_map() -> None:
    """RomNet.unit is the space's transform and equals the float32 map the networks were
    trained with (log of float32 bounds), bit for bit; old weights carrying that map's
    buffers still load."""
    torch = pytest.importorskip("torch")
    from femcal.surrogates.romnet import RomNet

    lower = np.array([-1.0, 0.5, 1e-3, 2.0])
    upper = np.array([1.0, 50.0, 10.0, 3.0])
    net = RomNet(lower, upper, hidden=(8,), n_members=2)
    x = torch.tensor(
        ParameterSpace(list("abcd"), lower, upper).sample_uniform(64, np.random.default_rng(0)),
        dtype=torch.float32,
    )
    lo = torch.tensor(lower, dtype=torch.float32)
    hi = torch.tensor(upper, dtype=torch.float32)
    mask = lo > 0
    log_lo = torch.log(torch.where(mask, lo, torch.ones_like(lo)))
    log_hi = torch.log(torch.where(mask, hi, torch.ones_like(hi)))
    linear = (x - lo) / (hi - lo)
    logged = (torch.log(torch.where(mask, x, torch.ones_like(x))) - log_lo) / (log_hi - log_lo)
    legacy = torch.where(mask, logged, linear)
    assert torch.equal(net.unit(x), legacy)
    back = torch.where(
        mask, torch.exp(log_lo + legacy * (log_hi - log_lo)), lo + legacy * (hi - lo)
    )
    assert torch.equal(net.params_from_unit(legacy), back)
    state = net.state_dict() | {"log_mask": mask, "log_lower": log_lo, "log_upper": log_hi}
    again = RomNet(lower, upper, hidden=(8,), n_members=2)
    again.load_state_dict(state)  # strict: the legacy buffers are dropped, nothing else
    assert torch.equal(
        again(torch.zeros(3, dtype=torch.long), torch.ones(3), x[:3]),
        net(torch.zeros(3, dtype=torch.long), torch.ones(3), x[:3]),
    )


def test_pickle_keeps_the_definition_and_reads_old_states(mixed: ParameterSpace) -> None:
    import pickle

    assert pickle.loads(pickle.dumps(mixed)) == mixed
    # a state saved before scales existed (e.g. in a baseline's skops file): all linear
    old = ParameterSpace.__new__(ParameterSpace)
    old.__setstate__({"names": ("a",), "lower": [0.0], "upper": [2.0], "units": ("1",)})
    assert old.scales == ("linear",)
    np.testing.assert_allclose(old.to_unit([[1.0]]), [[0.5]])
