"""The FE campaign's design: scipy.stats.qmc's Latin hypercube, seeded, stratified, bounded.

No solver needed: these tests only build designs.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.stats import qmc

from femcal.errors import ConfigError
from femcal.fe.design import SPLIT_SAMPLING, design, latin_hypercube, split_design
from femcal.schema import PARAMETER_NAMES

from synth import study_space

SPACE = study_space()
NAMES = list(SPACE.names)


def _strata(x: np.ndarray, n: int) -> np.ndarray:
    """The stratum (0 .. n-1) of every coordinate, in the unit box."""
    return np.floor(SPACE.to_unit(x) * n).astype(int)


@pytest.mark.parametrize("n", [1, 2, 8, 17, 64])
def test_lhs_one_point_per_stratum_inside_the_bounds(n: int) -> None:
    x = latin_hypercube(SPACE, n, np.random.default_rng(11))
    assert x.shape == (n, SPACE.dim)
    assert SPACE.contains(x).all()
    strata = _strata(x, n)
    for j in range(SPACE.dim):  # every column: exactly one point per stratum of n
        np.testing.assert_array_equal(np.sort(strata[:, j]), np.arange(n))


def test_lhs_is_scipy_qmc_with_the_same_generator() -> None:
    expected = qmc.scale(
        qmc.LatinHypercube(d=SPACE.dim, seed=np.random.default_rng(7)).random(10),
        SPACE.lower,
        SPACE.upper,
    )
    np.testing.assert_array_equal(latin_hypercube(SPACE, 10, np.random.default_rng(7)), expected)


def test_same_seed_same_design_other_seed_other_design() -> None:
    a = design(SPACE, 16, np.random.default_rng(5))
    b = design(SPACE, 16, np.random.default_rng(5))
    c = design(SPACE, 16, np.random.default_rng(6))
    pd.testing.assert_frame_equal(a, b)
    assert not np.allclose(a[NAMES], c[NAMES])
    assert a.columns.tolist() == ["config_id", *NAMES]
    assert a["config_id"].tolist() == list(range(16))
    assert SPACE.contains(a[NAMES].to_numpy()).all()
    strata = _strata(a[NAMES].to_numpy(), 16)
    assert all(sorted(strata[:, j]) == list(range(16)) for j in range(SPACE.dim))


def test_split_design_seed_contract() -> None:
    counts = {"large": 12, "small": 4, "test": 5}
    s1 = split_design(SPACE, counts, seed=3)
    pd.testing.assert_frame_equal(s1, split_design(SPACE, counts, seed=3))
    s2 = split_design(SPACE, counts, seed=4)
    assert not np.allclose(s1[list(PARAMETER_NAMES)], s2[list(PARAMETER_NAMES)])
    assert s1["config_id"].tolist() == list(range(21))
    for k, name in enumerate(SPLIT_SAMPLING):  # each split from default_rng([seed, k])
        part = s1[s1["split"] == name][NAMES].to_numpy()
        rng = np.random.default_rng([3, k])
        if SPLIT_SAMPLING[name] == "lhs":
            np.testing.assert_array_equal(part, latin_hypercube(SPACE, counts[name], rng))
            strata = _strata(part, counts[name])
            assert all(sorted(strata[:, j]) == list(range(counts[name])) for j in range(13))
        else:  # Test: independent uniform draws, untouched by the LHS implementation
            np.testing.assert_array_equal(part, SPACE.sample_uniform(counts[name], rng))
    # Resizing Large leaves Small and Test unchanged (own random stream per split).
    s3 = split_design(SPACE, {**counts, "large": 20}, seed=3)
    for name in ("small", "test"):
        np.testing.assert_array_equal(
            s1[s1["split"] == name][NAMES].to_numpy(), s3[s3["split"] == name][NAMES].to_numpy()
        )


def test_split_design_batches_keep_every_stored_configuration() -> None:
    counts = {"large": 12, "small": 4, "test": 5}
    base = split_design(SPACE, counts, seed=3)
    grown = split_design(SPACE, counts, seed=3, batches=[6, 8])
    # every configuration of the base design keeps its id and values (its job hash)
    pd.testing.assert_frame_equal(grown.iloc[: len(base)], base)
    assert grown["config_id"].tolist() == list(range(21 + 14))
    assert (grown["split"].iloc[len(base) :] == "large").all()
    for b, (start, n) in enumerate([(21, 6), (27, 8)], start=1):  # default_rng([seed, 0, b])
        part = grown[NAMES].to_numpy()[start : start + n]
        expected = latin_hypercube(SPACE, n, np.random.default_rng([3, 0, b]))
        np.testing.assert_array_equal(part, SPACE.clip(expected))
    # adding a batch leaves the earlier ones unchanged
    pd.testing.assert_frame_equal(split_design(SPACE, counts, seed=3, batches=[6]), grown.iloc[:27])
    with pytest.raises(ConfigError, match=r"fe.batches\[1\] has 0 configurations; each batch"):
        split_design(SPACE, counts, seed=3, batches=[6, 0])


def test_a_batch_over_a_narrowed_box_samples_only_there() -> None:
    counts = {"large": 12, "small": 4, "test": 5}
    soft = {"FiberAngle": [7.5, 30.0], "Kappa": [0.165, 0.33]}
    grown = split_design(SPACE, counts, seed=3, batches=[6, {"n": 16, "bounds": soft}])
    base = split_design(SPACE, counts, seed=3, batches=[6])
    pd.testing.assert_frame_equal(grown.iloc[: len(base)], base)
    part = grown.iloc[len(base) :]
    assert len(part) == 16 and (part["split"] == "large").all()
    for name, (lo, hi) in soft.items():  # inside the narrowed range, one point per stratum
        assert part[name].between(lo, hi).all()
        strata = np.floor((part[name].to_numpy() - lo) / (hi - lo) * 16).astype(int)
        assert sorted(strata) == list(range(16))
    other = [n for n in NAMES if n not in soft]  # the rest spans the whole box
    assert SPACE.contains(part[NAMES].to_numpy()).all()
    assert (
        part[other].max() - part[other].min()
        > 0.8 * (SPACE.upper - SPACE.lower)[[NAMES.index(n) for n in other]]
    ).all()
    with pytest.raises(
        ConfigError, match=r"fe.batches\[0\].bounds.Kappa is \[0.2, 0.5\]; a batch narrows"
    ):
        split_design(SPACE, counts, seed=3, batches=[{"n": 4, "bounds": {"Kappa": [0.2, 0.5]}}])
    with pytest.raises(ConfigError, match=r"fe.batches\[0\].bounds names 'Kapa', not a parameter"):
        split_design(SPACE, counts, seed=3, batches=[{"n": 4, "bounds": {"Kapa": [0.1, 0.2]}}])


def test_design_errors() -> None:
    with pytest.raises(ConfigError, match=r"at least one configuration; got n=0"):
        design(SPACE, 0, np.random.default_rng(0))
    with pytest.raises(ConfigError, match=r"Unknown design method 'sobol'; use 'lhs' or"):
        design(SPACE, 4, np.random.default_rng(0), method="sobol")
