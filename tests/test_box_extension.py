"""experiments.box_extension: the first-order step beyond the box on a linear world."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.box_extension import extension


def _world(shift: np.ndarray, seed: int = 0):
    """Curves linear in 3 parameters; the truth lies ``shift`` past a fit at the box's edge."""
    rng = np.random.default_rng(seed)
    jac = rng.normal(size=(4, 10, 3))
    sd = np.full((4, 10), 0.05)
    resid = np.einsum("jmd,d->jm", jac, shift) + rng.normal(scale=0.05, size=(4, 10))
    return jac, resid, sd


def test_a_disc_just_past_its_upper_bound_is_explained():
    jac, resid, sd = _world(np.array([0.2, 0.0, 0.0]))
    unit = np.array([1.0, 0.5, 0.5])  # the first parameter pressed at its upper bound
    row = extension(jac, resid, sd, unit, {0: "upper"}, cap=0.5)
    # 40 points of unit-sd noise: chi2_beyond about n (sd sqrt(2n) ~ 9), the miss almost gone
    assert row["n"] == 40
    assert row["chi2_disc"] > 10 * row["n"]
    assert row["chi2_beyond"] == pytest.approx(row["n"], abs=25)
    assert row["explained"] > 0.95


def test_the_step_moves_outward_only_and_no_further_than_the_cap():
    jac, resid, sd = _world(np.array([-0.2, 0.0, 0.0]))  # the data pull back inside the box
    unit = np.array([1.0, 0.5, 0.5])
    inward = extension(jac, resid, sd, unit, {0: "upper"}, cap=0.5)
    assert inward["explained"] < 0.2  # only the other two, which do not carry the miss, move
    jac, resid, sd = _world(np.array([2.0, 0.0, 0.0]))  # two box widths past the bound
    far = extension(jac, resid, sd, np.array([1.0, 0.5, 0.5]), {0: "upper"}, cap=0.5)
    assert far["chi2_beyond"] > 10 * far["n"]  # capped at half a box: the rest stays missed


def test_nothing_measured_gives_none():
    jac, resid, sd = _world(np.zeros(3))
    assert extension(jac, np.full_like(resid, np.nan), sd, np.full(3, 0.5), {}, 0.5) is None
