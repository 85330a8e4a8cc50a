"""The envelope's scrambled Sobol' points: scipy's, bit for bit, without importing scipy.stats."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.stats import qmc

from femcal.errors import ConfigError
from femcal.reachability.sobol import scrambled_sobol


@pytest.mark.parametrize("dim", [1, 2, 13, 17, 40])
@pytest.mark.parametrize("m", [0, 1, 4, 10])
@pytest.mark.parametrize("seed", [0, 1, 12345])
def test_the_points_of_scipy_bit_for_bit(dim: int, m: int, seed: int) -> None:
    expected = qmc.Sobol(dim, scramble=True, seed=np.random.default_rng(seed)).random_base2(m)
    got = scrambled_sobol(dim, m, np.random.default_rng(seed))
    assert got.dtype == expected.dtype == np.float64
    np.testing.assert_array_equal(got, expected)


def test_the_generator_is_left_as_scipy_leaves_it() -> None:
    """The scramble comes from a spawned generator: the caller's stream is untouched."""
    theirs, ours = np.random.default_rng(7), np.random.default_rng(7)
    qmc.Sobol(5, scramble=True, seed=theirs).random_base2(4)
    scrambled_sobol(5, 4, ours)
    np.testing.assert_array_equal(ours.random(4), theirs.random(4))
    np.testing.assert_array_equal(ours.spawn(1)[0].random(2), theirs.spawn(1)[0].random(2))


def test_out_of_range_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"dim >= 1 and 0 <= m <= 30; got dim=0, m=3"):
        scrambled_sobol(0, 3, np.random.default_rng(0))
    with pytest.raises(ConfigError, match=r"got dim=2, m=31\. Ask for 2\*\*m points"):
        scrambled_sobol(2, 31, np.random.default_rng(0))
    with pytest.raises(ConfigError, match=r"at most 21201 coordinates; got 21202"):
        scrambled_sobol(21202, 1, np.random.default_rng(0))


def test_drawing_imports_no_scipy_stats() -> None:
    code = (
        "import sys, numpy as np\n"
        "from femcal.reachability.sobol import scrambled_sobol\n"
        "u = scrambled_sobol(13, 10, np.random.default_rng(0))\n"
        "print(u.shape, 'scipy.stats' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["(1024,", "13)", "False"]
