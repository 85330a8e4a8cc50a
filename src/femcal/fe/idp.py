"""Intradiscal pressure (IDP) of calibrated discs against published values and the IDP head.

The calibration sees only the RoM; the nucleus pressure is a second output it never fitted,
so it is the validation's independent check. Two kinds of published values meet the FE model:

* an in vitro range under a known axial force (``validate.idp_literature``, force in N ->
  {low, mean, high}): each disc's FE pressure at that force is inside or outside
  (:class:`femcal.fe.validate.LiteratureRange`);
* a value without a known force, typically in vivo in a posture (``validate.idp_published``,
  e.g. Wilke et al. 1999: relaxed standing 0.50 MPa): the force at which each calibrated disc
  reaches it, interpolated in its FE pressure-force curve (:func:`implied_forces`), to be read
  against the compressive load of that posture.

The IDP head (``train@idp``, a surrogate trained on the campaign's pressures under the four
moments) is compared with FE at the validated parameters (:func:`idp_head_error`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
from pydantic import TypeAdapter, ValidationError

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.settings._format import problems
from femcal.settings.fe import PublishedIdp

IDP_PUBLISHED_CSV = "idp_published.csv"
IDP_HEAD_CSV = "idp_head.csv"
_PUBLISHED = ("validate", "idp_published")


def published_values(entries: Sequence[Any]) -> list[PublishedIdp]:
    """``validate.idp_published`` as :class:`femcal.settings.fe.PublishedIdp` entries: each
    mapping (or entry) checked by that settings model, which declares its fields once.

    Raises
    ------
    ConfigError
        An entry is not a mapping, lacks a field or holds a bad value: every problem, with its
        position, the field's doc and what was given.
    """
    try:
        return TypeAdapter(list[PublishedIdp]).validate_python(list(entries))
    except ValidationError as exc:
        found = "; ".join(message for _, message in problems(exc, prefix=_PUBLISHED))
    raise ConfigError(
        f"{found}. Each entry of validate.idp_published is a mapping {{source, condition, "
        "idp_mpa, kind, subjects, level}, e.g. {source: 'Wilke et al. 1999, Spine "
        "24(8):755-762', condition: relaxed standing, idp_mpa: 0.50, kind: in vivo, subjects: "
        "1, level: L4-L5}."
    )


def implied_forces(forces: Sequence[float], idp_mpa: np.ndarray, value: float) -> np.ndarray:
    """The axial force at which each disc's FE pressure reaches ``value``.

    Linear interpolation in each disc's pressure-force curve, anchored at 0 MPa under 0 N
    (the FE disc has no swelling pre-stress). A disc that does not reach ``value`` within the
    largest force, or whose curve is not increasing, gets NaN: nothing is extrapolated.

    Parameters
    ----------
    forces : sequence of float, length f
        Axial compressive forces, N, increasing.
    idp_mpa : ndarray, shape (n, f)
        FE pressure of each disc at each force (NaN where a run failed).
    value : float
        The pressure, MPa.

    Returns
    -------
    ndarray, shape (n,)
        Force in N (NaN where not reached).
    """
    f = np.concatenate([[0.0], np.asarray(forces, dtype=float)])
    out = np.full(idp_mpa.shape[0], np.nan)
    for i, row in enumerate(np.asarray(idp_mpa, dtype=float)):
        p = np.concatenate([[0.0], row])
        ok = np.isfinite(p)
        fi, pi = f[ok], p[ok]
        if pi.size < 2 or np.any(np.diff(pi) <= 0) or not pi[0] <= value <= pi[-1]:
            continue
        out[i] = float(np.interp(value, pi, fi))
    return out


def published_table(
    specimens: Sequence[str],
    forces: Sequence[float],
    idp_mpa: np.ndarray,
    published: Sequence[PublishedIdp],
) -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """Per disc and published value, the force that reaches it; and a summary per value.

    Returns
    -------
    table : DataFrame
        One row per (specimen, published value): ``specimen, source, condition, kind,
        idp_mpa, implied_force_n`` (NaN: not reached within the largest force).
    summary : list of dict
        Per published value: its fields, ``force_n_min``, ``force_n_median``,
        ``force_n_max`` over the discs that reach it, ``n_reached`` and ``n_beyond`` (discs
        that stay below it up to ``max(forces)``).
    """
    rows, summary = [], []
    top = max(forces) if len(forces) else float("nan")
    idp = np.asarray(idp_mpa, dtype=float)
    highest = np.array([np.nanmax(r) if np.isfinite(r).any() else np.nan for r in idp])
    for entry in published:
        f = implied_forces(forces, idp_mpa, entry.idp_mpa)
        for s, fi in zip(specimens, f):
            rows.append(
                {
                    "specimen": s,
                    "source": entry.source,
                    "condition": entry.condition,
                    "kind": entry.kind,
                    "idp_mpa": entry.idp_mpa,
                    "implied_force_n": fi,
                }
            )
        reached = f[np.isfinite(f)]
        beyond = int(np.sum(highest < entry.idp_mpa))
        summary.append(
            {
                **entry.model_dump(),
                "force_n_min": float(reached.min()) if reached.size else float("nan"),
                "force_n_median": float(np.median(reached)) if reached.size else float("nan"),
                "force_n_max": float(reached.max()) if reached.size else float("nan"),
                "n_reached": int(reached.size),
                "n_beyond": beyond,
                "max_force_n": top,
            }
        )
    columns = ["specimen", "source", "condition", "kind", "idp_mpa", "implied_force_n"]
    return pd.DataFrame(rows, columns=columns), summary


def idp_head_error(
    head: Any,
    specimens: Sequence[str],
    parameters: np.ndarray,
    moments: np.ndarray,
    fe_idp_mpa: np.ndarray,
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The IDP head's pressures at the validated parameters against FE's, under the moments.

    Parameters
    ----------
    head : surrogate
        A fitted surrogate of the pressure (``train.<split>.target: idp_mpa``): ``predict``
        on rows ``load_case, moment_nm`` and the 13 parameters.
    specimens : sequence of str, length n
    parameters : ndarray, shape (n, 13)
        Physical parameters (those FE was run with).
    moments : ndarray, shape (m,)
    fe_idp_mpa : ndarray, shape (n, 4, m)
        FE pressure under each load case and moment (NaN where not simulated or failed).

    Returns
    -------
    table : DataFrame
        ``specimen, load_case, moment_nm, fe_idp_mpa, head_idp_mpa`` where FE has a value.
    summary : dict
        ``mae_mpa`` (all points), ``mae_mpa_per_load_case``, ``n_points`` and the FE
        pressures' spread (``fe_idp_mpa_min``, ``fe_idp_mpa_max``) for scale.
    """
    n, m = len(specimens), len(moments)
    spec, lc, mom = np.meshgrid(
        np.arange(n), np.arange(len(LOAD_CASES)), np.arange(m), indexing="ij"
    )
    spec, lc, mom = spec.reshape(-1), lc.reshape(-1), mom.reshape(-1)
    fe = np.asarray(fe_idp_mpa, dtype=float).reshape(-1)
    keep = np.isfinite(fe)
    X = pd.DataFrame(np.asarray(parameters, dtype=float)[spec[keep]], columns=list(PARAMETER_NAMES))
    X.insert(0, "moment_nm", np.asarray(moments, dtype=float)[mom[keep]])
    X.insert(0, "load_case", np.asarray(LOAD_CASES, dtype=object)[lc[keep]])
    pred = np.asarray(head.predict(X), dtype=float) if keep.any() else np.zeros(0)
    table = pd.DataFrame(
        {
            "specimen": np.asarray(specimens, dtype=object)[spec[keep]],
            "load_case": X["load_case"].to_numpy(),
            "moment_nm": X["moment_nm"].to_numpy(),
            "fe_idp_mpa": fe[keep],
            "head_idp_mpa": pred,
        }
    )
    err = np.abs(table["head_idp_mpa"] - table["fe_idp_mpa"])
    summary = {
        "mae_mpa": float(err.mean()) if len(err) else float("nan"),
        "mae_mpa_per_load_case": {
            c: float(err[table["load_case"] == c].mean())
            if (table["load_case"] == c).any()
            else float("nan")
            for c in LOAD_CASES
        },
        "n_points": int(len(table)),
        "fe_idp_mpa_min": float(table["fe_idp_mpa"].min()) if len(table) else float("nan"),
        "fe_idp_mpa_max": float(table["fe_idp_mpa"].max()) if len(table) else float("nan"),
    }
    return table, summary
