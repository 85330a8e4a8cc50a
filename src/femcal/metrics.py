"""Error metrics of the study, on RoM curves and on tidy tables.

Definitions follow Atad et al. (section "Evaluation metrics"): the MAE averages the absolute
error over load cases and moments; the mean R² averages over load cases an R² computed across
the moments of one load case.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from femcal.errors import InputDataError
from femcal.schema import LOAD_CASES


def r2_score_along(y: np.ndarray, yhat: np.ndarray, axis: int = -1) -> np.ndarray:
    """Coefficient of determination along ``axis``.

    Parameters
    ----------
    y, yhat : ndarray, same shape
        Ground truth and prediction.
    axis : int
        The axis that holds the samples of one R² (the moments of a curve, say).

    Returns
    -------
    ndarray
        ``1 - SS_res / SS_tot`` with ``axis`` removed. A constant ``y`` gives 1.0 when the
        prediction is exact and 0.0 otherwise, as scikit-learn does.
    """
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    if y.shape != yhat.shape:
        raise InputDataError(f"Shapes differ: truth {y.shape}, prediction {yhat.shape}.")
    ss_res = np.sum((y - yhat) ** 2, axis=axis)
    ss_tot = np.sum((y - np.mean(y, axis=axis, keepdims=True)) ** 2, axis=axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = 1.0 - ss_res / ss_tot
    degenerate = ss_tot == 0
    return np.where(degenerate, np.where(ss_res == 0, 1.0, 0.0), r2)


def curve_metrics(y: np.ndarray, yhat: np.ndarray) -> dict[str, np.ndarray]:
    """Per-specimen metrics of RoM curves (the study's calibration metrics).

    Parameters
    ----------
    y, yhat : ndarray, shape (n, n_load_cases, n_moments)
        Measured (or FE) and predicted RoM in degrees. NaN entries in ``y`` (missing
        measurements) are left out of every average.

    Returns
    -------
    dict
        ``mae`` (n,), ``r2_mean`` (n,), ``mae_per_load_case`` (n, n_load_cases),
        ``r2_per_load_case`` (n, n_load_cases) — NaN for a load case with no data.
    """
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    if y.ndim != 3 or y.shape != yhat.shape:
        raise InputDataError(
            f"Curves must have shape (n, n_load_cases, n_moments) and match; got {y.shape} and "
            f"{yhat.shape}."
        )
    mask = np.isfinite(y)
    err = np.where(mask, np.abs(y - yhat), 0.0)
    count = mask.sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        mae_lc = err.sum(axis=2) / count
        mean_y = np.where(mask, y, 0.0).sum(axis=2, keepdims=True) / count[..., None]
        ss_res = np.where(mask, (y - yhat) ** 2, 0.0).sum(axis=2)
        ss_tot = np.where(mask, (y - mean_y) ** 2, 0.0).sum(axis=2)
        r2_lc = 1.0 - ss_res / ss_tot
    r2_lc = np.where(ss_tot == 0, np.where(ss_res == 0, 1.0, 0.0), r2_lc)
    r2_lc = np.where(count > 0, r2_lc, np.nan)
    total = mask.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        mae = err.sum(axis=(1, 2)) / total
    return {
        "mae": mae,
        "r2_mean": np.nanmean(r2_lc, axis=1) if r2_lc.size else np.full(len(y), np.nan),
        "mae_per_load_case": mae_lc,
        "r2_per_load_case": r2_lc,
    }


def surrogate_scores(
    table: pd.DataFrame, prediction: np.ndarray, *, target: str = "rom_deg"
) -> dict[str, float]:
    """Test-set scores of a surrogate on a tidy table (rows with status "ok" only).

    Parameters
    ----------
    table : DataFrame, n rows
        Columns ``config_id``, ``load_case``, ``moment_nm``, ``status`` and ``target``.
    prediction : ndarray, shape (n,)
        Predicted values for every row of ``table``.

    Returns
    -------
    dict
        ``mae`` (mean absolute error over all rows), ``r2_mean`` (R² per load case pooled over
        configurations and moments, averaged over load cases), ``r2_curve_mean`` (the study's
        per-specimen mean R²: R² across the moments of each configuration's curve, averaged over
        configurations and load cases), and ``mae_<LoadCase>``, ``r2_<LoadCase>`` per load case.
    """
    prediction = np.asarray(prediction, dtype=float).reshape(-1)
    if len(prediction) != len(table):
        raise InputDataError(f"Got {len(prediction)} predictions for a table of {len(table)} rows.")
    ok = (table["status"] == "ok").to_numpy() if "status" in table else np.ones(len(table), bool)
    df = table.loc[ok, ["config_id", "load_case", "moment_nm", target]].copy()
    df["pred"] = prediction[ok]
    df["abs_err"] = (df[target] - df["pred"]).abs()
    out: dict[str, float] = {"mae": float(df["abs_err"].mean())}
    r2s, curve_r2s = [], []
    for lc in LOAD_CASES:
        part = df[df["load_case"] == lc]
        if part.empty:
            continue
        out[f"mae_{lc}"] = float(part["abs_err"].mean())
        r2 = float(r2_score_along(part[target].to_numpy(), part["pred"].to_numpy(), axis=0))
        out[f"r2_{lc}"] = r2
        r2s.append(r2)
        per_curve = [
            float(r2_score_along(g[target].to_numpy(), g["pred"].to_numpy(), axis=0))
            for _, g in part.groupby("config_id")
            if len(g) > 1
        ]
        if per_curve:
            out[f"r2_curve_{lc}"] = float(np.mean(per_curve))
            curve_r2s.append(out[f"r2_curve_{lc}"])
    out["r2_mean"] = float(np.mean(r2s)) if r2s else float("nan")
    out["r2_curve_mean"] = float(np.mean(curve_r2s)) if curve_r2s else float("nan")
    return out
