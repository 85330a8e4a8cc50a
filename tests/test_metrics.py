import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import r2_score

from femcal.errors import InputDataError
from femcal.metrics import curve_metrics, r2_score_along, surrogate_scores
from femcal.schema import LOAD_CASES


def test_r2_matches_scikit_learn():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(7, 5))
    yhat = y + 0.3 * rng.normal(size=y.shape)
    ours = r2_score_along(y, yhat, axis=1)
    ref = [r2_score(a, b) for a, b in zip(y, yhat)]
    np.testing.assert_allclose(ours, ref, rtol=1e-12)


def test_r2_degenerate_constant_truth():
    y = np.ones((2, 5))
    assert r2_score_along(y, y, axis=1).tolist() == [1.0, 1.0]
    assert r2_score_along(y, y + 1, axis=1).tolist() == [0.0, 0.0]


def test_curve_metrics_by_hand():
    y = np.array([[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0]]])
    yhat = y.copy()
    yhat[0, 1, :] += 0.5
    m = curve_metrics(y, yhat)
    assert m["mae"][0] == pytest.approx(0.25)
    np.testing.assert_allclose(m["mae_per_load_case"][0], [0.0, 0.5])
    # R² of a constant shift of 0.5 on [2, 4, 6]: 1 - 3*0.25/8
    np.testing.assert_allclose(m["r2_per_load_case"][0], [1.0, 1 - 0.75 / 8])
    assert m["r2_mean"][0] == pytest.approx((1 + 1 - 0.75 / 8) / 2)


def test_curve_metrics_ignores_missing_measurements():
    y = np.array([[[1.0, np.nan, 3.0], [np.nan, np.nan, np.nan]]])
    yhat = np.array([[[1.5, 100.0, 3.0], [9.0, 9.0, 9.0]]])
    m = curve_metrics(y, yhat)
    assert m["mae"][0] == pytest.approx(0.25)
    assert np.isnan(m["mae_per_load_case"][0, 1])
    assert np.isnan(m["r2_per_load_case"][0, 1])
    assert np.isfinite(m["r2_mean"][0])


def test_curve_metrics_shape_error():
    with pytest.raises(InputDataError, match=r"shape \(n, n_load_cases, n_moments\)"):
        curve_metrics(np.zeros((2, 3)), np.zeros((2, 3)))


def _table(n_configs=3):
    rows = []
    for c in range(n_configs):
        for lc in LOAD_CASES:
            for m in range(1, 6):
                rows.append(
                    {
                        "config_id": c,
                        "load_case": lc,
                        "moment_nm": float(m),
                        "rom_deg": (c + 1) * np.log1p(m),
                        "status": "ok",
                    }
                )
    return pd.DataFrame(rows)


def test_surrogate_scores_exact_and_shifted():
    t = _table()
    exact = surrogate_scores(t, t["rom_deg"].to_numpy())
    assert exact["mae"] == 0.0 and exact["r2_mean"] == 1.0 and exact["r2_curve_mean"] == 1.0
    shifted = surrogate_scores(t, t["rom_deg"].to_numpy() + 0.1)
    assert shifted["mae"] == pytest.approx(0.1)
    for lc in LOAD_CASES:
        assert shifted[f"mae_{lc}"] == pytest.approx(0.1)
    assert shifted["r2_mean"] < 1.0


def test_surrogate_scores_skip_failed_rows():
    t = _table()
    t.loc[0, "status"] = "failed"
    t.loc[0, "rom_deg"] = np.nan
    pred = t["rom_deg"].fillna(0).to_numpy()
    s = surrogate_scores(t, pred)
    assert s["mae"] == 0.0


def test_surrogate_scores_length_error():
    with pytest.raises(InputDataError, match="Got 3 predictions for a table of 60 rows"):
        surrogate_scores(_table(), np.zeros(3))
