"""The predictive ceiling's pure helpers (experiments/fe_predictive_ceiling.py): the long table
as an array, and the store's runs read back at exactly the parameters asked. No CalculiX, no
surrogate."""

from __future__ import annotations

import numpy as np
import pandas as pd

import experiments.fe_predictive_ceiling as fpc
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

MOMENTS = np.array([1.0, 2.0, 5.5])


def test_long_to_array_places_each_point_and_leaves_the_rest_nan():
    long = pd.DataFrame(
        {
            "specimen": ["b", "a", "a"],
            "load_case": ["Extension", "Flexion", "AxialRotation"],
            "moment_nm": [2.0, 1.0, 5.5],
            "rom_deg": [3.0, 1.5, 7.0],
        }
    )
    out = fpc.long_to_array(long, ["a", "b"], MOMENTS)
    assert out.shape == (2, len(LOAD_CASES), MOMENTS.size)
    assert out[1, LOAD_CASES.index("Extension"), 1] == 3.0
    assert out[0, LOAD_CASES.index("Flexion"), 0] == 1.5
    assert out[0, LOAD_CASES.index("AxialRotation"), 2] == 7.0
    assert np.isfinite(out).sum() == 3


def _record(config_id, x, load_case, rom):
    return {
        "config_id": config_id,
        "load_case": load_case,
        "parameters": dict(zip(PARAMETER_NAMES, x)),
        "rom_deg": rom,
    }


def test_stored_curves_take_only_runs_at_the_very_parameters():
    x = np.linspace(0.1, 1.3, len(PARAMETER_NAMES))[None, :]
    other = x[0] + 1e-6  # a later run of the same configuration number elsewhere
    records = [
        _record(7, x[0], "Flexion", [1.0, None, 3.0]),
        _record(7, other, "Extension", [9.0, 9.0, 9.0]),
        _record(8, x[0], "Extension", [9.0, 9.0, 9.0]),
    ]
    out = fpc.stored_curves(records, x, np.array([7]), MOMENTS.size)
    assert out.shape == (1, len(LOAD_CASES), MOMENTS.size)
    np.testing.assert_array_equal(out[0, 0], [1.0, np.nan, 3.0])
    assert np.isnan(out[0, 1:]).all()
