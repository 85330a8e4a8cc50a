"""Predictive FE validation: the bands, the noise, and the score, with a stand-in FE model."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from femcal.errors import FemcalError, InputDataError
from femcal.fe.predictive import (
    bands,
    fit_targets,
    predictive_error,
    run_predictive,
    split_moment,
)
from femcal.measurements import from_arrays
from femcal.schema import PARAMETER_NAMES

MOMENTS = np.arange(1, 21) * 0.5


def truth(n: int = 3):
    """RoM = a * M**0.7 per specimen (a = 1, 2, 3 ...), all load cases alike."""
    a = np.arange(1, n + 1, dtype=float)
    rom = a[:, None, None] * np.ones((1, 4, 1)) * MOMENTS[None, None, :] ** 0.7
    return from_arrays([f"S{i}" for i in range(n)], MOMENTS, rom)


def test_bands_are_disjoint_and_inclusive():
    assert split_moment(MOMENTS) == 5.0
    fit, pred = bands(MOMENTS, 5.0)
    assert MOMENTS[fit].tolist() == [1.0 + 0.5 * i for i in range(9)]
    assert MOMENTS[pred].tolist() == [5.5 + 0.5 * i for i in range(10)]
    assert not np.any(fit & pred)


def test_a_grid_that_stops_at_5_nm_is_split_at_its_middle_moment():
    grid = [1.0, 2.0, 3.0, 4.0, 5.0]
    assert split_moment(grid) == 3.0
    fit, pred = bands(grid, 3.0)
    assert fit.tolist() == [True, True, True, False, False]
    assert pred.tolist() == [False, False, False, True, True]
    assert split_moment([6.0, 8.0, 10.0]) == 8.0


def test_fit_targets_keep_only_the_fit_band_and_add_seeded_noise():
    long = truth().to_long()
    clean = fit_targets(long, 0.05, None, 5.0)
    assert clean["moment_nm"].between(1.0, 5.0).all()
    a = fit_targets(long, 0.05, np.random.default_rng(1), 5.0)
    b = fit_targets(long, 0.05, np.random.default_rng(1), 5.0)
    pd.testing.assert_frame_equal(a, b)
    noise = a["rom_deg"] - clean["rom_deg"]
    assert 0.03 < noise.std() < 0.07


def test_predictive_error_reads_each_band():
    t = truth().rom_deg
    fe = t.copy()
    fe[:, :, bands(MOMENTS, 5.0)[1]] += 0.2
    out = predictive_error(t, fe, MOMENTS, 5.0)
    assert out["predict_mae_deg"] == pytest.approx(0.2)
    assert out["fit_band_mae_deg"] == pytest.approx(0.0)
    assert out["n_points_predicted"] == 3 * 4 * 10


def test_run_predictive_with_a_stand_in_model():
    """The 'FE model' is RoM = C10Nucleus * M**0.7; the calibration recovers C10Nucleus from
    the 1-5 Nm points it is given (a least-squares fit), so FE predicts 5.5-10 Nm exactly
    without noise and nearly so with it."""
    data = truth()
    seen: dict[str, pd.DataFrame] = {}

    def curves(x, ids):
        rom = x[:, :1, None] * np.ones((1, 4, 1)) * MOMENTS[None, None, :] ** 0.7
        return rom, 0.01 * rom

    def calibrate(points, variant):
        seen[variant] = points
        rows = []
        for name, part in points.groupby("specimen"):
            basis = part["moment_nm"].to_numpy() ** 0.7
            a = float(basis @ part["rom_deg"].to_numpy() / (basis @ basis))
            rows.append({"specimen": name, **dict.fromkeys(PARAMETER_NAMES, 0.1), "C10Nucleus": a})
        return pd.DataFrame(rows)

    out = run_predictive(data, curves, calibrate, 0.05, seed=3)
    assert out["n_specimens"] == 3 and out["fe_runs_per_specimen_max"] == 1
    assert out["fe_predictive_mae_deg"] == pytest.approx(0.0, abs=1e-9)
    assert 0 < out["fe_predictive_mae_deg_noisy"] < 0.05
    assert seen["clean"]["moment_nm"].max() == 5.0 and out["split_nm"] == 5.0


def test_curves_without_a_predicted_band_are_refused():
    short = from_arrays(["S0"], [0.5, 1.0], np.ones((1, 4, 2)))
    with pytest.raises(InputDataError, match=r"needs at least two moments from 1 Nm on") as info:
        run_predictive(short, None, None, 0.05, seed=0)
    assert isinstance(info.value, FemcalError)
