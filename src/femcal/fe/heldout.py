"""The FE surrogate's error on held-out FE configurations, added to its training report.

A surrogate's validation error is measured on curves drawn from its own training
configurations; its error on configurations it never saw, by moment band and load case, is what
a calibration meets. The FE pipeline's ``train`` stage adds these figures to the training
report (``reports/train-<split>.json``, beside the DVC metrics file in ``reports/metrics/``):

* ``heldout_mae_deg_0_5`` and ``heldout_mae_deg_5_10``: MAE (deg) at 0.5-5 Nm and 5.5-10 Nm
  over every held-out point FE reached (``heldout_mae_mpa_...`` for a surrogate of the
  intradiscal pressure, ``train.<split>.target: idp_mpa``);
* ``heldout_mae_deg_by_load_case``: band -> load case -> MAE;
* ``heldout_n_points`` (band -> points) and ``heldout_n_configurations``;
* ``n_train_configurations``: the configurations of the table the surrogate was trained on.

Command line (from ``fe/``, after ``femcal train --split large``; the model, its training table
and target come from the ``train.large`` section of ``params.yaml``, the report is
``reports/train-large.json``)::

    python -m femcal.fe.heldout --split large
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import InputDataError
from femcal.schema import LOAD_CASES

#: Moment bands, Nm (inclusive): the in vitro protocols, and the moments above them.
BANDS: tuple[tuple[float, float], ...] = ((0.5, 5.0), (5.5, 10.0))


#: The unit of each target column, as it appears in the report's keys.
UNITS = {"rom_deg": "deg", "idp_mpa": "mpa"}


def band_key(band: tuple[float, float], unit: str = "deg") -> str:
    """The report key of a band's MAE: (0.5, 5) -> ``heldout_mae_deg_0_5``."""
    return f"heldout_mae_{unit}_{int(band[0])}_{int(band[1])}"


def heldout_errors(
    surrogate: Any,
    heldout: pd.DataFrame,
    train: pd.DataFrame,
    bands: Sequence[tuple[float, float]] = BANDS,
    target: str = "rom_deg",
) -> dict[str, Any]:
    """The surrogate's MAE on held-out FE rows, by moment band and load case.

    Parameters
    ----------
    surrogate : object
        A fitted surrogate (``predict`` of a tidy table, degrees).
    heldout : pandas.DataFrame, shape (n, ...)
        Tidy FE rows of configurations the surrogate never saw: ``config_id``, ``load_case``,
        ``moment_nm``, the parameters and ``rom_deg`` (rows without a finite ``rom_deg``, the
        levels a failed FE run never reached, are left out).
    train : pandas.DataFrame
        The tidy table it was trained on (its ``config_id`` counted; each split numbers its
        configurations on its own).
    bands : sequence of (float, float)
        Moment bands, Nm, inclusive.
    target : {"rom_deg", "idp_mpa"}
        The column the surrogate predicts.

    Returns
    -------
    dict
        The keys of the module docstring; a band without a held-out point is left out.

    Raises
    ------
    InputDataError
        No held-out row has a finite value of ``target``, or ``target`` is unknown.
    """
    if target not in UNITS:
        raise InputDataError(
            f"heldout_errors: target must be one of {sorted(UNITS)}; got {target!r}."
        )
    rows = heldout[np.isfinite(pd.to_numeric(heldout[target], errors="coerce"))]
    if rows.empty:
        raise InputDataError(
            f"heldout_errors: the held-out table has no finite {target}; give FE curves the "
            "surrogate was not trained on (e.g. data/prepared/test.csv)."
        )
    err = np.abs(np.asarray(surrogate.predict(rows), dtype=float) - rows[target].to_numpy())
    unit = UNITS[target]
    moment = rows["moment_nm"].to_numpy(dtype=float)
    case = rows["load_case"].to_numpy()
    out: dict[str, Any] = {}
    by_case: dict[str, dict[str, float]] = {}
    n_points: dict[str, int] = {}
    for band in bands:
        sel = (moment >= band[0] - 1e-9) & (moment <= band[1] + 1e-9)
        if not sel.any():
            continue
        name = f"{band[0]:g}-{band[1]:g}"
        out[band_key(band, unit)] = float(err[sel].mean())
        n_points[name] = int(sel.sum())
        by_case[name] = {
            lc: float(err[sel & (case == lc)].mean())
            for lc in LOAD_CASES
            if (sel & (case == lc)).any()
        }
    out[f"heldout_mae_{unit}_by_load_case"] = by_case
    out["heldout_n_points"] = n_points
    out["heldout_n_configurations"] = int(rows["config_id"].nunique())
    out["n_train_configurations"] = int(train["config_id"].nunique())
    return out


def add_to_report(report: Path, figures: dict[str, Any]) -> dict[str, Any]:
    """``figures`` merged into the JSON report ``report`` (written whole); returns it.

    Raises
    ------
    InputDataError
        The report is absent or not a JSON object.
    """
    try:
        current = json.loads(report.read_text())
    except FileNotFoundError as exc:
        raise InputDataError(
            f"{report}: no training report to add the held-out error to; run `femcal train` "
            "first (the FE pipeline's train stage does)."
        ) from exc
    except json.JSONDecodeError as exc:
        raise InputDataError(f"{report} is not valid JSON ({exc}); re-run `femcal train`.") from exc
    if not isinstance(current, dict):
        raise InputDataError(f"{report} holds a {type(current).__name__}, not a JSON object.")
    merged = {**current, **figures}
    tmp = report.with_name(report.name + ".tmp")
    tmp.write_text(json.dumps(merged, indent=2) + "\n")
    tmp.replace(report)
    return merged


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line of :func:`heldout_errors`, run from ``fe/`` (module docstring)."""
    from femcal.config import load_params
    from femcal.tracking import load_surrogate, open_model

    parser = argparse.ArgumentParser(prog="python -m femcal.fe.heldout", description=__doc__)
    parser.add_argument("--split", default="large", help="a section of train in params.yaml")
    parser.add_argument(
        "--heldout",
        type=Path,
        default=Path("data/prepared/test.csv"),
        help="tidy FE rows of configurations the surrogate never saw",
    )
    args = parser.parse_args(argv)
    params = load_params("params.yaml")
    section = (params.get("train") or {}).get(args.split) or {}
    prepared = Path((params.get("data") or {}).get("prepared_dir") or "data/prepared")
    train = prepared / f"{section.get('split') or args.split}.csv"
    surrogate = load_surrogate(open_model(f"models/surrogate-{args.split}"))
    figures = heldout_errors(
        surrogate,
        pd.read_csv(args.heldout),
        pd.read_csv(train, usecols=["config_id"]),
        target=section.get("target") or "rom_deg",
    )
    add_to_report(Path("reports") / f"train-{args.split}.json", figures)
    print(json.dumps({k: v for k, v in figures.items() if not isinstance(v, dict)}))
    return figures


if __name__ == "__main__":
    main()
