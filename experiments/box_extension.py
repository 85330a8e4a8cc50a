"""The disc carried beyond its box, to first order: does it tell a disc outside the box apart?

The out-of-box reading (:mod:`femcal.diagnose.outside`) decides from the shapes of the fitted
effects and of the discrepancy. A pressed disc-alone fit leaves residuals that change sign
along a curve, so a discrepancy's share of the curves reads as an element there (its flatness
is 0), and a pre-tensioned element acts from 0 Nm as a stiffer disc's stand-in does. This
experiment measures another piece of evidence: the disc-alone fit's pressed parameters moved
past their bounds.

For each specimen the reading looks at (:func:`femcal.diagnose.beyond.box_evidence`: at least
``BOUNDS_PRESSED`` parameters on a bound, or points beyond the envelope) it solves, on the
disc-alone fit's weighted residuals ``b = (measured - fit) / sd`` and its curves' Jacobian ``J``
(network coordinates, the box is [0, 1]^d), the bounded linear least-squares problem
``min |J s / sd - b|^2`` (:func:`scipy.optimize.lsq_linear`): each pressed parameter moves
outward only, by at most ``--extend`` box widths; every other parameter stays in the box. It
records

* ``explained``: ``(chi2_disc - chi2_beyond) / (chi2_disc - n)``, the share of the disc
  alone's misfit beyond the measured points' count that the step removes (above 1 where the
  step fits better than the noise);
* ``beyond_per_point``: ``chi2_beyond / n``, about 1 where the extended disc explains the
  curves within the noise and the surrogate's error;
* ``final_per_point``: the verdict's model's ``chi2 / n`` (``adequacy.final`` of
  ``diagnosis.json``).

The diagnosis runs as ``femcal diagnose`` does, in this process, with the two functions wrapped
(the verdicts are those of the command). Run from a folder whose params.yaml and models the
command reads (the project root after ``make repro``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.box_extension --out DIR \\
        --measurements COHORT/measurements.csv --truth COHORT/truth.json [--model-uri URI] \\
        [--start-bank CSV] [--truth-all outside_box]

``--truth`` is an edge cohort's ``truth.json`` (``experiments.edge_cohorts``: each specimen's
``truth``) or an FE cohort's ``answers.csv`` (``class``); ``--truth-all`` gives every specimen
one class (the FE discs outside the box of ``experiments.fe_outside_box``). Writes
``DIR/extension.json`` and ``DIR/diagnosis/``, and prints a Markdown table per class.
``--report DIR [DIR ...]`` prints that table over the specimens of several such folders.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: How far past its bound a pressed parameter may move, in box widths.
EXTEND_UNITS = 0.5
#: ``chi2_beyond / n`` up to which the extended disc counts as explaining the curves.
WITHIN = 1.2


def extension(
    jac: np.ndarray, resid: np.ndarray, sd: np.ndarray, unit: np.ndarray, pressed: dict, cap: float
) -> dict[str, float] | None:
    """The first-order step beyond the box of one specimen (module docstring).

    Parameters
    ----------
    jac : ndarray, shape (4, m, d)
        The disc-alone curves' Jacobian in network coordinates.
    resid, sd : ndarray, shape (4, m)
        Measured minus the disc-alone fit, and each point's sd (deg); NaN where not measured.
    unit : ndarray, shape (d,)
        The disc-alone fit in unit coordinates.
    pressed : dict
        Parameter index -> ``lower`` or ``upper`` for the parameters on a bound.
    cap : float
        The largest move past a bound, in box widths.

    Returns
    -------
    dict or None
        ``n``, ``chi2_disc``, ``chi2_beyond``, ``explained``; None where nothing is measured.
    """
    from scipy.optimize import lsq_linear

    ok = np.isfinite(resid) & np.isfinite(sd) & (sd > 0)
    if not ok.any():
        return None
    a, b = jac[ok] / sd[ok][:, None], resid[ok] / sd[ok]
    u = np.clip(np.asarray(unit, dtype=float), 0.0, 1.0)
    lo, hi = -u, 1.0 - u
    for d, side in pressed.items():
        lo[d], hi[d] = (0.0, cap) if side == "upper" else (-cap, 0.0)
    lo, hi = np.minimum(lo, hi - 1e-12), np.maximum(hi, lo + 1e-12)
    step = lsq_linear(a.astype(float), b.astype(float), bounds=(lo, hi)).x
    n, chi2_disc = int(ok.sum()), float(b @ b)
    chi2_beyond = float(np.sum((a @ step - b) ** 2))
    excess = chi2_disc - n
    return {
        "n": n,
        "chi2_disc": chi2_disc,
        "chi2_beyond": chi2_beyond,
        "explained": (chi2_disc - chi2_beyond) / excess if excess > 0 else 0.0,
    }


def hook(out: Path, cap: float) -> None:
    """Wrap the diagnosis' out-of-box reading so that each process writes the extension of
    every specimen it looks at to ``out/extension-<pid>.json``."""
    import femcal.diagnose.decide as decide
    import femcal.diagnose.outside as outside

    assess, box_evidence, names = outside.assess, outside.box_evidence, {}

    def assess_named(state, *args, **kwargs):
        names["specimens"] = list(state.specimens)
        return assess(state, *args, **kwargs)

    def evidence(base, measured, sigma, pred0, unit, sigma_m, env=None, jac0=None):
        found = box_evidence(base, measured, sigma, pred0, unit, sigma_m, env, jac0)
        params = list(base.space.names)
        rows = {}
        for i, ev in enumerate(found):
            if ev["looks"] and jac0 is not None:
                pressed = {params.index(p): side for p, side in ev["on_bounds"].items()}
                row = extension(jac0[i], measured[i] - pred0[i], sigma[i], unit[i], pressed, cap)
                rows[names["specimens"][i]] = {**(row or {}), "pressed": len(pressed)}
        if rows:
            path = out / f"extension-{os.getpid()}.json"
            old = json.loads(path.read_text()) if path.is_file() else {}
            path.write_text(json.dumps({**old, **rows}))
        return found

    outside.assess = decide.assess = assess_named
    outside.box_evidence = evidence


def truths(path: Path | None, every: str | None) -> dict[str, str]:
    """Specimen -> class from an edge cohort's truth.json or an FE cohort's answers.csv."""
    if path is None:
        return {}
    if path.suffix == ".json":
        return {r["specimen"]: r["truth"] for r in json.loads(path.read_text())}
    with path.open() as f:
        return {r["specimen"]: r["class"] for r in csv.DictReader(f)}


def table(rows: dict[str, dict[str, Any]]) -> str:
    """Per class: specimens looked at, the share explained and the extended disc's fit."""
    lines = [
        "| class | looked at | explained, median (range) | chi2_beyond / n, median (range) "
        f"| chi2_beyond / n <= {WITHIN} (of them, the verdict names the box) "
        "| verdict's model chi2 / n, median |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for cls in sorted({r["class"] for r in rows.values()}):
        part = [r for r in rows.values() if r["class"] == cls and "n" in r]
        f = np.array([r["explained"] for r in part])
        per = np.array([r["chi2_beyond"] / r["n"] for r in part])
        fin = np.array([r["final_per_point"] for r in part])
        named = np.array(["outside_box" in r["verdict"] for r in part])
        lines.append(
            f"| {cls} | {len(part)} | {np.median(f):.2f} ({f.min():.2f}-{f.max():.2f}) | "
            f"{np.median(per):.2f} ({per.min():.2f}-{per.max():.2f}) | "
            f"{int(np.sum(per <= WITHIN))} ({int(np.sum(named & (per <= WITHIN)))}) | "
            f"{np.median(fin):.2f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict[str, dict[str, Any]]:
    """Command line (module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m experiments.box_extension")
    ap.add_argument("--measurements", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--report", type=Path, nargs="+", help="pool the folders' extension.json")
    ap.add_argument("--truth", type=Path, default=None, help="truth.json or answers.csv")
    ap.add_argument("--truth-all", default=None, help="one class for every specimen")
    ap.add_argument("--model-uri", default=None)
    ap.add_argument("--start-bank", default=None)
    ap.add_argument("--noise-deg", default="0.05")
    ap.add_argument("--extend", type=float, default=EXTEND_UNITS, help="box widths past a bound")
    args = ap.parse_args(argv)
    if args.report:
        pooled = {}
        for folder in args.report:
            found = json.loads((folder / "extension.json").read_text())
            pooled.update({f"{folder.name}/{k}": v for k, v in found.items()})
        print(table(pooled))
        return pooled
    if args.measurements is None or args.out is None:
        ap.error("give --measurements and --out (or --report)")
    args.out.mkdir(parents=True, exist_ok=True)
    for old in args.out.glob("extension-*.json"):
        old.unlink()
    hook(args.out, args.extend)
    from femcal.cli import main as femcal

    command = ["diagnose", "-q", "--plots", "false", "--noise-deg", args.noise_deg]
    command += ["--measurements", str(args.measurements), "--out", str(args.out / "diagnosis")]
    for flag, value in (("--model-uri", args.model_uri), ("--start-bank", args.start_bank)):
        command += [flag, value] if value else []
    femcal(command)
    rows: dict[str, dict[str, Any]] = {}
    for part in sorted(args.out.glob("extension-*.json")):
        rows.update(json.loads(part.read_text()))
    diagnosis = json.loads((args.out / "diagnosis" / "diagnosis.json").read_text())
    truth = truths(args.truth, args.truth_all)
    for record in diagnosis:
        if record["specimen"] in rows:
            row = rows[record["specimen"]]
            row["class"] = args.truth_all or truth.get(record["specimen"], "?")
            row["verdict"] = record["verdict"]
            row["final_per_point"] = record["adequacy"]["final"]["chi2"] / max(row.get("n", 1), 1)
    (args.out / "extension.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
