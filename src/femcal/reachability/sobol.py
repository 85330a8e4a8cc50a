"""Scrambled Sobol' points in numpy: the points ``scipy.stats.qmc.Sobol`` draws, bit for bit.

:func:`scrambled_sobol` gives ``scipy.stats.qmc.Sobol(d, scramble=True, seed=rng)
.random_base2(m)`` without importing ``scipy.stats`` (which imports all its distributions:
about a quarter of a CPU-second, on the path of every ``femcal calibrate``). The construction
is the standard one: Joe and Kuo's direction numbers (criterion D(6), read from the ``.npz``
file scipy ships), a left linear matrix scramble and a digital shift drawn from a generator
spawned from ``rng``, and the points in Gray-code order. ``tests/test_reachability_sobol.py``
checks it against scipy for several dimensions, sizes and seeds.

References: P. Bratley and B. L. Fox, Algorithm 659, ACM TOMS 14(1), 1988; S. Joe and F. Y.
Kuo, Remark on Algorithm 659, ACM TOMS 29(1), 2003; J. Matoušek, On the L2-discrepancy for
anchored boxes, J. Complexity 14, 1998 (the linear matrix scramble).
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

import numpy as np

from femcal.errors import ConfigError

#: Bits of each coordinate (scipy's default): points are multiples of 2**-BITS.
BITS = 30


@functools.cache
def _direction_table() -> tuple[np.ndarray, np.ndarray]:
    """Joe and Kuo's primitive polynomials (21201,) and initial direction numbers
    (21201, 18), from scipy's data file (found without importing scipy.stats)."""
    spec = importlib.util.find_spec("scipy")
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover - a dependency
        raise ConfigError(
            "The Sobol' direction numbers come with scipy, which is not installed; got no "
            "'scipy' package. Install femcal's dependencies (pip install -e .)."
        )
    path = Path(list(spec.submodule_search_locations)[0]) / "stats" / "_sobol_direction_numbers.npz"
    with np.load(path) as table:
        return table["poly"].astype(np.int64), table["vinit"].astype(np.int64)


def _direction_matrix(dim: int) -> np.ndarray:
    """The direction numbers of the first ``dim`` coordinates, shape (dim, BITS), int64; entry
    ``(d, c)`` is ``m_c * 2**(BITS - 1 - c)`` (``m_c`` the c-th direction integer, odd and
    below ``2**(c + 1)``)."""
    poly, vinit = _direction_table()
    if dim > poly.size:
        raise ConfigError(
            f"Sobol' points have at most {poly.size} coordinates; got {dim}. Use fewer parameters."
        )
    v = np.ones((dim, BITS), dtype=np.int64)
    for d in range(1, dim):
        p = int(poly[d])
        degree = p.bit_length() - 1
        row = [int(x) for x in vinit[d, :degree]]
        for j in range(degree, BITS):
            # the recurrence of the primitive polynomial's coefficients (Bratley and Fox)
            value = row[j - degree]
            for k in range(degree):
                if (p >> (degree - 1 - k)) & 1:
                    value ^= row[j - k - 1] << (k + 1)
            row.append(value)
        v[d] = row[:BITS]
    return v << np.arange(BITS - 1, -1, -1, dtype=np.int64)


def scrambled_sobol(dim: int, m: int, rng: np.random.Generator) -> np.ndarray:
    """The first ``2**m`` scrambled Sobol' points in the unit cube, shape (2**m, dim).

    Equal to ``scipy.stats.qmc.Sobol(dim, scramble=True, seed=rng).random_base2(m)``: the
    scramble is drawn from ``rng.spawn(1)[0]`` (as scipy does, so ``rng``'s own stream is left
    where it was); the same ``rng`` state gives the same points.

    Parameters
    ----------
    dim : int
        Coordinates per point, >= 1.
    m : int
        log2 of the number of points, 0 <= m <= 30.
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (2**m, dim), float64
        Multiples of ``2**-30`` in [0, 1).

    Raises
    ------
    ConfigError
        ``dim`` or ``m`` out of range.
    """
    dim, m = int(dim), int(m)
    if dim < 1 or not 0 <= m <= BITS:
        raise ConfigError(
            f"scrambled_sobol needs dim >= 1 and 0 <= m <= {BITS}; got dim={dim}, m={m}. "
            "Ask for 2**m points of at least one coordinate."
        )
    v = _direction_matrix(dim)
    child = rng.spawn(1)[0]
    weights = np.int64(1) << np.arange(BITS, dtype=np.int64)
    shift = child.integers(2, size=(dim, BITS), dtype=np.uint32).astype(np.int64) @ weights
    ltm = np.tril(child.integers(2, size=(dim, BITS, BITS), dtype=np.uint32)).astype(np.int64)
    ltm[:, np.arange(BITS), np.arange(BITS)] = 1
    # Linear matrix scramble: bit (BITS-1-p) of a scrambled number is the parity of row p of
    # the lower-triangular matrix (column 0 the most significant bit) and the number's bits.
    msb_first = weights[::-1]
    rows = ltm @ msb_first  # (dim, BITS): row p of each matrix as an integer
    parity = np.bitwise_count(rows[:, :, None] & v[:, None, :]) & 1  # (dim, p, j)
    v = (parity.astype(np.int64) * msb_first[None, :, None]).sum(axis=1)  # (dim, BITS)
    # Gray-code order: point i is the shift XOR the direction numbers of the bits of i ^ (i >> 1)
    index = np.arange(2**m, dtype=np.int64)
    gray = index ^ (index >> 1)
    quasi = np.broadcast_to(shift, (index.size, dim)).copy()
    for k in range(m):
        take = ((gray >> k) & 1).astype(bool)
        quasi[take] ^= v[:, k]
    return quasi * (1.0 / 2**BITS)
