"""experiments.fe_ligament_residuals: the error split by band and load case, the specimens
examined, and the element laws composed with a disc given by its own curves."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from experiments.fe_ligament_residuals import (
    band_mae,
    examined,
    parallel_curves,
    point_errors,
    split_mae,
)
from femcal.effects.base import get_effect
from femcal.schema import LOAD_CASES

MOMENTS = np.arange(1, 21) * 0.5


def test_the_error_splits_by_band_and_load_case():
    curves = pd.DataFrame(
        {
            "specimen": ["a"] * 4,
            "load_case": ["Flexion", "Flexion", "Extension", "Extension"],
            "moment_nm": [1.0, 6.0, 1.0, 6.0],
            "measured_rom_deg": [1.0, 2.0, 1.0, np.nan],
            "calibrated_rom_deg": [1.1, 2.3, 0.8, 3.0],
        }
    )
    errors = point_errors(curves)
    assert len(errors) == 3  # the point without a measurement is left out
    row = split_mae(errors).loc["a"]
    assert row["mae"] == pytest.approx(0.2)
    assert row["mae_0.5-5"] == pytest.approx(0.15) and row["mae_5.5-10"] == pytest.approx(0.3)
    assert row["mae_Flexion"] == pytest.approx(0.2) and row["mae_Extension"] == pytest.approx(0.2)
    assert np.isnan(row["mae_AxialRotation"])
    residual = np.full((4, len(MOMENTS)), np.nan)
    residual[0, [1, 11]] = [0.1, -0.3]
    figures = band_mae(residual, MOMENTS)
    assert figures["mae"] == pytest.approx(0.2) and figures["mae_5.5-10"] == pytest.approx(0.3)
    assert np.isnan(figures["mae_Extension"])


def test_the_examined_specimens_exceed_the_ratio_in_the_element_classes():
    hidden = {
        "disc_only_floor_mae_deg": 0.05,
        "specimens": [
            {"specimen": "0", "class": "none", "after_mae_deg": 0.2},
            {"specimen": "1", "class": "ligaments", "after_mae_deg": 0.08},
            {"specimen": "2", "class": "both", "after_mae_deg": 0.07},
            {"specimen": "3", "class": "facets", "after_mae_deg": 0.3},
        ],
    }
    assert examined(hidden) == ["1"]  # 0.08 > 1.5 x 0.05 > 0.07


def test_parallel_elements_balance_the_moment_beside_a_disc_curve():
    # a linear disc (2 deg per Nm) and a ligament in flexion and lateral bending
    disc = np.tile(2.0 * MOMENTS, (4, 1))
    effect = get_effect("ligament_tension")()
    units = np.array([0.2, 0.6, 0.4])  # slack, stiffness, toe in their unit boxes
    rom = parallel_curves(disc, MOMENTS, [effect], [units])
    p = effect.from_unit(torch.tensor(units[None], dtype=torch.float64))
    with torch.no_grad():
        carried = effect.moment(torch.tensor(rom[None]), p).numpy()[0]
    for i, lc in enumerate(LOAD_CASES):
        if lc in effect.load_cases:  # the disc's share plus the ligament's is the moment
            np.testing.assert_allclose(rom[i] / 2.0 + carried[i], MOMENTS, rtol=2e-3)
            assert (rom[i] < disc[i]).all()
        else:  # the disc alone
            np.testing.assert_allclose(rom[i], disc[i], rtol=1e-9)
    # a disc curve that stops at 5 Nm: the rotation is defined while the disc's share is below
    short = disc.copy()
    short[:, MOMENTS > 5.0] = np.nan
    rom = parallel_curves(short, MOMENTS, [effect], [units])
    assert np.isnan(rom[3, MOMENTS > 5.0]).all() and np.isfinite(rom[0, MOMENTS <= 5.0]).all()
