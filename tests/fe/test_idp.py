"""Published pressures against calibrated discs: the force that reaches them, and the IDP head."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from femcal.errors import ConfigError
from femcal.fe.idp import idp_head_error, implied_forces, published_table, published_values
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

WILKE = {
    "source": "Wilke et al. 1999, Spine 24(8):755-762",
    "condition": "relaxed standing",
    "idp_mpa": 0.50,
    "kind": "in vivo",
    "subjects": 1,
    "level": "L4-L5",
}
FORCES = [100.0, 300.0, 1000.0, 2000.0]


def test_implied_force_interpolates_from_zero_and_never_extrapolates():
    idp = np.array(
        [
            [0.1, 0.3, 1.0, 2.0],  # 1 MPa per kN: 0.5 MPa at 500 N
            [0.2, 0.6, 2.0, 4.0],  # twice as stiff in pressure: 250 N
            [0.01, 0.03, 0.1, 0.2],  # never reaches 0.5 MPa within 2000 N
            [np.nan, 0.3, 1.0, 2.0],  # a failed force is skipped, not fatal
            [0.1, 0.3, 0.2, 2.0],  # not increasing: no answer rather than a wrong one
        ]
    )
    f = implied_forces(FORCES, idp, 0.5)
    assert f[:2] == pytest.approx([500.0, 250.0])
    assert np.isnan(f[2]) and f[3] == pytest.approx(500.0) and np.isnan(f[4])
    # below the first force: from (0 N, 0 MPa), the FE disc has no pre-stress
    assert implied_forces(FORCES, idp[:1], 0.05) == pytest.approx([50.0])


def test_published_table_summarises_reached_and_beyond():
    idp = np.array([[0.1, 0.3, 1.0, 2.0], [0.01, 0.03, 0.1, 0.2]])
    table, summary = published_table(["a", "b"], FORCES, idp, published_values([WILKE]))
    assert table["specimen"].tolist() == ["a", "b"]
    assert table["implied_force_n"].iloc[0] == pytest.approx(500.0)
    (row,) = summary
    assert row["condition"] == "relaxed standing" and row["n_reached"] == 1
    assert row["n_beyond"] == 1 and row["force_n_median"] == pytest.approx(500.0)
    assert row["max_force_n"] == 2000.0


def test_published_values_errors():
    """Each entry is checked by the settings model: the position, the field, its doc, the fix."""
    fix = r"Each entry of validate\.idp_published is a mapping \{source, condition"
    with pytest.raises(ConfigError, match=r"idp_published\[0\]\.level: missing setting; add it"):
        published_values([{k: v for k, v in WILKE.items() if k != "level"}])
    with pytest.raises(
        ConfigError, match=r"idp_published\[0\]\.idp_mpa: Input should be greater than 0"
    ):
        published_values([{**WILKE, "idp_mpa": -0.5}])
    with pytest.raises(ConfigError, match=r"idp_published\[1\]: expected a mapping .*" + fix):
        published_values([WILKE, "0.5 MPa"])
    with pytest.raises(ConfigError, match=r"kind: Input should be 'in vivo' or 'in vitro'"):
        published_values([{**WILKE, "kind": "in silico"}])


class _Linear:
    """A pressure 'head' of known form: 0.1 MPa per Nm, whatever the load case."""

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        return 0.1 * X["moment_nm"].to_numpy()


def test_idp_head_error_compares_where_fe_has_a_pressure():
    moments = np.array([1.0, 2.0])
    fe = np.full((1, 4, 2), np.nan)
    fe[0, 0] = [0.1, 0.3]  # Flexion: off by 0.1 MPa at 2 Nm
    fe[0, 3] = [0.1, np.nan]  # AxialRotation: one level failed
    params = np.ones((1, len(PARAMETER_NAMES)))
    table, summary = idp_head_error(_Linear(), ["s"], params, moments, fe)
    assert len(table) == 3 and summary["n_points"] == 3
    assert summary["mae_mpa"] == pytest.approx(0.1 / 3)
    assert summary["mae_mpa_per_load_case"][LOAD_CASES[0]] == pytest.approx(0.05)
    assert np.isnan(summary["mae_mpa_per_load_case"][LOAD_CASES[1]])
