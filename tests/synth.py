"""A tidy synthetic FE table (the prepared layout) from a smooth, known RoM function."""

from __future__ import annotations

import numpy as np
import pandas as pd

from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.space import ParameterSpace

STUDY_LOWER = [0.03, 0.0075, 0.065, 1, 10, 0, -0.2, -0.2, -0.2, -0.2, 7.5, 0, 0]
STUDY_UPPER = [0.21, 0.0525, 0.455, 50, 200, 0.33, 0, 0, 0, 0, 52.5, 0.3, 0.2]


def study_space() -> ParameterSpace:
    return ParameterSpace(PARAMETER_NAMES, STUDY_LOWER, STUDY_UPPER)


def rom_function(u: np.ndarray, lc: int, moment: np.ndarray) -> np.ndarray:
    """A smooth, positive, increasing-in-moment RoM (deg) of unit-box parameters u (n, 13)."""
    stiff = 0.6 + 0.8 * u[:, 2] + 0.5 * u[:, 3] * u[:, 10] + 0.2 * np.sin(3 * u[:, 0] + lc)
    return (2.0 + lc) * np.log1p(moment / stiff)


def true_curves(
    x: np.ndarray, ids: np.ndarray | None = None, moments=(1, 2, 3, 4, 5)
) -> np.ndarray:
    """The synthetic study's model at physical parameters x (k, 13): curves (k, 4, m) in deg.

    ``ids`` is ignored; with it the function is an FE model's curves
    (:data:`femcal.fe.refine.FECurves`), as the FE tests' stand-in for the solver.
    """
    u = study_space().to_unit(np.asarray(x, dtype=float))
    m = np.asarray(moments, dtype=float)
    return np.stack(
        [
            np.stack([rom_function(u, k, np.array([mm])) for mm in m], axis=1)
            for k in range(len(LOAD_CASES))
        ],
        axis=1,
    )


def tidy_table(n_configs: int, seed: int, moments=(1, 2, 3, 4, 5)) -> pd.DataFrame:
    """Rows (config x load case x moment) with physical parameters and synthetic rom_deg."""
    space = study_space()
    rng = np.random.default_rng(seed)
    x = space.sample_lhs(n_configs, rng)
    u = space.to_unit(x)
    rows = []
    for c in range(n_configs):
        for k, lc in enumerate(LOAD_CASES):
            for m in moments:
                rom = float(rom_function(u[c : c + 1], k, np.array([float(m)]))[0])
                rows.append(
                    {
                        "config_id": c,
                        "load_case": lc,
                        "moment_nm": float(m),
                        **dict(zip(space.names, x[c])),
                        "rom_deg": rom,
                        "idp_mpa": 0.1 * m,
                        "status": "ok",
                    }
                )
    return pd.DataFrame(rows)


def long_csv(path, curves: np.ndarray, moments=(1, 2, 3, 4, 5)):
    """Write RoM curves (n, 4, m) as a long measurement CSV (``spec-<i>``; NaN points left out)."""
    rows = [
        (f"spec-{i}", lc, m, spec[j, k])
        for i, spec in enumerate(curves)
        for j, lc in enumerate(LOAD_CASES)
        for k, m in enumerate(moments)
        if np.isfinite(spec[j, k])
    ]
    pd.DataFrame(rows, columns=["specimen", "load_case", "moment_nm", "rom_deg"]).to_csv(
        path, index=False
    )
    return path


def parallel_curves(fe_m, fe_rom, lcs, law, moments):
    """Curves with a parallel element M_e(phi) on load cases ``lcs`` (bisection, numpy): the
    disc's FE curves ``fe_rom`` (4, m) at ``fe_m`` sharing each applied moment with ``law``."""
    from femcal.effects.planted import fe_rotation

    applied = np.broadcast_to(moments, (4, len(moments)))
    lo, hi = np.log(applied * 1e-3), np.log(applied).copy()
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        md = np.exp(mid)
        g = md + law(fe_rotation(fe_m, fe_rom, md)) - applied
        hi, lo = np.where(g > 0, mid, hi), np.where(g > 0, lo, mid)
    out = fe_rotation(fe_m, fe_rom, applied).copy()
    solved = fe_rotation(fe_m, fe_rom, np.exp(0.5 * (lo + hi)))
    out[lcs] = solved[lcs]
    return out
