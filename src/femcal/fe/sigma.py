"""Is the surrogate's stated error honest? Its sd against FE on held-out configurations.

The diagnosis and calibrate count the surrogate's own error as an sd
(:meth:`femcal.moments.MomentPolicy.sigma_surrogate`: the error the model states by moment,
from its validation rows or a held-out split, ``train.<split>.stated_error_split``, relative
to the RoM at each point where the model records it, grown beyond the trained range).
Against FE curves the surrogate never saw, a calibrated sd holds about 95 % of the
errors within 2 sd (Gaussian errors) in every moment band; much less means the diagnosis sees
physics in the surrogate's error, much more that it hides effects in an inflated sd.

Command line (from ``fe/``, the FE pipeline's ``sigma`` stage)::

    python -m femcal.fe.sigma --metrics-file reports/metrics/sigma.json
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.dvc_metrics import write as write_dvc_metrics
from femcal.errors import InputDataError
from femcal.schema import LOAD_CASES

#: Moment bands reported, Nm (inclusive): the in vitro protocols, and the moments above them.
BANDS: tuple[tuple[float, float], ...] = ((0.5, 5.0), (5.5, 10.0))

#: The share of errors within 2 sd that a calibrated sd gives: 90-98 % (95.4 % if Gaussian).
COVERAGE_TARGET: tuple[float, float] = (0.90, 0.98)


def _band_name(band: tuple[float, float]) -> str:
    return f"{band[0]:g}-{band[1]:g}"


def sigma_coverage(
    surrogate: Any,
    table: pd.DataFrame,
    policy: Any,
    bands: Sequence[tuple[float, float]] = BANDS,
) -> dict[str, Any]:
    """The share of held-out errors within 2 sd of the surrogate's stated error, by band.

    Parameters
    ----------
    surrogate : object
        A fitted surrogate (``predict`` of a tidy table, degrees).
    table : pandas.DataFrame, shape (n, ...)
        Held-out tidy rows: ``load_case``, ``moment_nm``, the parameters and ``rom_deg``
        (rows without a finite ``rom_deg``, the levels a failed FE run never reached, are
        left out).
    policy : MomentPolicy
        The surrogate's moment policy (:meth:`MomentPolicy.for_surrogate`).
    bands : sequence of (float, float)
        Moment bands, Nm, inclusive.

    Returns
    -------
    dict
        ``coverage_2sigma``, ``mae_deg``, ``rms_deg``, ``sigma_deg`` (the mean stated sd) and
        ``n_points``, each a mapping band -> value; ``by_load_case``: band -> load case ->
        ``{coverage_2sigma, mae_deg}``; ``target`` (the calibrated range).

    Raises
    ------
    InputDataError
        No row has a finite ``rom_deg``.
    """
    rows = table[np.isfinite(pd.to_numeric(table["rom_deg"], errors="coerce"))]
    if rows.empty:
        raise InputDataError(
            "sigma_coverage: the held-out table has no finite rom_deg; give FE curves the "
            "surrogate was not trained on (e.g. data/prepared/test.csv)."
        )
    err = np.asarray(surrogate.predict(rows), dtype=float) - rows["rom_deg"].to_numpy(float)
    moment = rows["moment_nm"].to_numpy(dtype=float)
    # the sd the diagnosis gives a point of these curves (relative to the RoM where it can)
    truth = rows["rom_deg"].to_numpy(float)
    sd = np.asarray(policy.sigma_surrogate(moment, truth), dtype=float)
    within = np.abs(err) <= 2.0 * sd
    out: dict[str, Any] = {
        k: {} for k in ("coverage_2sigma", "mae_deg", "rms_deg", "sigma_deg", "n_points")
    }
    out["by_load_case"] = {}
    for band in bands:
        name = _band_name(band)
        sel = (moment >= band[0] - 1e-9) & (moment <= band[1] + 1e-9)
        if not sel.any():
            continue
        out["coverage_2sigma"][name] = float(within[sel].mean())
        out["mae_deg"][name] = float(np.abs(err[sel]).mean())
        out["rms_deg"][name] = float(np.sqrt(np.mean(err[sel] ** 2)))
        out["sigma_deg"][name] = float(sd[sel].mean())
        out["n_points"][name] = int(sel.sum())
        lc = rows["load_case"].to_numpy()
        out["by_load_case"][name] = {
            case: {
                "coverage_2sigma": float(within[sel & (lc == case)].mean()),
                "mae_deg": float(np.abs(err[sel & (lc == case)]).mean()),
            }
            for case in LOAD_CASES
            if (sel & (lc == case)).any()
        }
    out["target"] = list(COVERAGE_TARGET)
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line of :func:`sigma_coverage`, run from ``fe/`` (module docstring)."""
    from femcal.config import load_params, settings_of
    from femcal.moments import MomentPolicy
    from femcal.tracking import load_surrogate, open_model

    parser = argparse.ArgumentParser(prog="python -m femcal.fe.sigma", description=__doc__)
    parser.add_argument(
        "--model-uri",
        default="models/surrogate-champion",
        help="the surrogate whose stated error is checked (what calibrate and diagnose use)",
    )
    parser.add_argument(
        "--heldout",
        type=Path,
        default=Path("data/prepared/test.csv"),
        help="tidy FE rows of configurations the surrogate never saw",
    )
    parser.add_argument("--metrics-file", type=Path, default=Path("reports/metrics/sigma.json"))
    args = parser.parse_args(argv)
    params = load_params("params.yaml")
    moments = settings_of(params).require("moments")
    surrogate = load_surrogate(open_model(args.model_uri))
    growth, limit = moments.error_growth, moments.max_log_ratio
    policy = MomentPolicy.for_surrogate(
        surrogate,
        growth=(growth.below, growth.above),
        max_log_ratio=(limit.below, limit.above),
    )
    figures = sigma_coverage(surrogate, pd.read_csv(args.heldout), policy)
    figures.update(model_uri=args.model_uri, heldout=str(args.heldout))
    write_dvc_metrics(args.metrics_file, "sigma", figures, details=True)
    print(json.dumps({"coverage_2sigma": figures["coverage_2sigma"]}))
    return figures


if __name__ == "__main__":
    main()
