"""Benchmark: how well one polynomial in log-moment writes an FE curve (RomNet's form).

:class:`femcal.surrogates.romnet.RomNet` writes each configuration's curve of a load case as a
polynomial in the standardised log-moment: of the log-RoM (``log_target``) or of the pressure
itself (the IDP head). Whatever the network learns, a curve that no polynomial of that degree
reproduces is a floor under the surrogate's error. This benchmark fits every curve of the FE
campaign store by least squares, for each degree, and reports the representation error: the
MAE per curve (mean, 95th percentile, worst) over the campaign's moments (0.5..10 Nm) and over
the study's 1..5 Nm. It chose ``moment_degree: 5`` in fe/params.yaml.

Only the levels a job reached count (a stopped job's curve is shorter); curves with fewer than
``degree + 3`` points are left out of that degree.

Writes ``bench_fe_curve_form.md`` and ``bench_fe_curve_form.json`` into
``experiments/results/bench_fe_curve_form/``.

Usage (from the project root)::

    .venv/bin/python -m experiments.bench_fe_curve_form [--campaign fe/data/campaign/runs.jsonl.gz]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from experiments.common import REPO, RESULTS
from femcal.fe.store import CampaignStore


def curve_errors(
    levels: np.ndarray, values: np.ndarray, degree: int, *, log_values: bool
) -> np.ndarray:
    """Absolute error of a least-squares polynomial of ``degree`` in the standardised log-moment.

    Parameters
    ----------
    levels : ndarray, shape (m,)
        Moments, Nm (> 0).
    values : ndarray, shape (m,)
        The curve (NaN where not reached); > 0 where ``log_values``.
    degree : int
    log_values : bool
        Fit the log of the values (RoM) or the values (pressure).

    Returns
    -------
    ndarray, shape (k,)
        Absolute error at the k finite points, in the values' unit (empty: too few points).
    """
    ok = np.isfinite(values) & ((values > 0) if log_values else True)
    if ok.sum() < degree + 3:
        return np.zeros(0)
    x = np.log(levels[ok])
    z = (x - x.mean()) / x.std()
    y = np.log(values[ok]) if log_values else values[ok]
    fit = np.polyval(np.polyfit(z, y, degree), z)
    return np.abs((np.exp(fit) if log_values else fit) - values[ok])


def summarise(records: list[dict], key: str, degrees: range, *, log_values: bool, band=None):
    rows = []
    for degree in degrees:
        mae = []
        for rec in records:
            levels = np.asarray(rec["levels"], dtype=float)
            values = np.array([np.nan if v is None else v for v in rec[key]], dtype=float)
            if band is not None:
                inside = (levels >= band[0] - 1e-9) & (levels <= band[1] + 1e-9)
                levels, values = levels[inside], values[inside]
            err = curve_errors(levels, values, degree, log_values=log_values)
            if err.size:
                mae.append(err.mean())
        mae = np.asarray(mae)
        if not mae.size:  # too few levels for this degree (e.g. 9 moments in 1..5 Nm)
            continue
        rows.append(
            {
                "degree": degree,
                "n_curves": int(mae.size),
                "mae_mean": float(mae.mean()),
                "mae_p95": float(np.percentile(mae, 95)),
                "mae_max": float(mae.max()),
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--campaign", default="fe/data/campaign/runs.jsonl.gz")
    ap.add_argument("--out", default=str(RESULTS / "bench_fe_curve_form" / "bench_fe_curve_form"))
    args = ap.parse_args()
    records = list(CampaignStore(REPO / args.campaign).finished().values())
    degrees = range(2, 8)
    result = {
        "campaign": args.campaign,
        "n_jobs": len(records),
        "moments": records[0]["levels"] if records else [],
        "rom_deg": summarise(records, "rom_deg", degrees, log_values=True),
        "rom_deg_1_5_nm": summarise(records, "rom_deg", degrees, log_values=True, band=(1, 5)),
        "idp_mpa": summarise(records, "idp_mpa", degrees, log_values=False),
    }
    out = REPO / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    md = [
        "# One polynomial in log-moment per FE curve: the floor under RomNet's form",
        "",
        f"Reproduce: `.venv/bin/python -m experiments.bench_fe_curve_form` "
        f"(`experiments/bench_fe_curve_form.py` wrote this file). Campaign store "
        f"`{args.campaign}`: {len(records)} jobs (each a configuration x load case curve; "
        "only the levels a job reached). Least-squares fit per curve in the standardised "
        "log-moment; MAE per curve, then its mean, 95th percentile and worst over the curves.",
        "",
    ]
    for key, title, unit in (
        ("rom_deg", "RoM (log-RoM fitted), 0.5..10 Nm", "deg"),
        ("rom_deg_1_5_nm", "RoM (log-RoM fitted), the study's 1..5 Nm only", "deg"),
        ("idp_mpa", "IDP (fitted linearly: it can be <= 0), 0.5..10 Nm", "MPa"),
    ):
        md += [
            f"## {title}",
            "",
            f"| degree | curves | mean MAE ({unit}) | 95th percentile | worst |",
            "|---|---|---|---|---|",
        ]
        md += [
            f"| {r['degree']} | {r['n_curves']} | {r['mae_mean']:.4f} | {r['mae_p95']:.4f} | "
            f"{r['mae_max']:.4f} |"
            for r in result[key]
        ]
        md.append("")
    out.with_suffix(".md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
