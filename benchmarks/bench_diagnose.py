"""Benchmark: the missing-effect search on planted cohorts (issue 4's bars), side by side.

Cohorts are built by :func:`femcal.effects.planted.make_cohort` from the FE curves of the study's
Test set (log-log interpolation between FE moments, not the surrogate), 4 classes (``none``,
``facet_contact``, ``ligament_tension``, ``neutral_zone``), 12 specimens each, noise sd 0.05
deg, moments 1..5 Nm in 0.5 Nm steps. Cohort seed 0 is the pipeline's ``data/planted``.
The surrogate is the registered champion; its own error enters sigma as in the diagnose stage.

For each cohort:

1. Verdicts: share right among planted specimens whose disc-alone MAE exceeds 2 x noise (bar:
   >= 90 %), share of ``none`` specimens given an effect (bar: <= 10 %), confusion matrix.
2. The error with the found effect: (a) per specimen, the fit of its diagnosed effect; (b) the
   user's way: ``calibrate`` with every effect the cohort diagnosis found (params.yaml's
   ``calibrate.effects``). Bar: planted specimens' mean MAE within 1.5 x that of ``none``.
3. Effect parameters +- sd against the planted truth (share within 2 sd, median sd).
4. Time of the whole diagnosis (bar: 40 specimens under a minute on 2 cores), wall and CPU.

Writes ``reports/bench_diagnose.md`` and ``reports/bench_diagnose.json``. Run it alone: other
processes on the 2 cores slow torch down badly.

Usage (from the project root, after ``make repro``)::

    .venv/bin/python benchmarks/bench_diagnose.py [--cohorts 2]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from femcal.calibration import CurveModel, calibrate
from femcal.config import load_params, section
from femcal.diagnose import diagnose
from femcal.effects.composite import EffectModel
from femcal.effects.planted import NONE, make_cohort
from femcal.pipeline import calibration_options, load_split, training_configurations
from femcal.prepare import wide_rom
from femcal.schema import LOAD_CASES
from femcal.tracking import configure_tracking, load_surrogate, resolve_model_version

REPO = Path(__file__).resolve().parents[1]
CLASSES = (NONE, "facet_contact", "ligament_tension", "neutral_zone")
#: The planted parameters reported with their uncertainty, per effect.
REPORTED = {
    "facet_contact": ("facet_gap_deg", "facet_stiffness"),
    "ligament_tension": ("ligament_slack_deg", "ligament_stiffness"),
    "neutral_zone": ("nz_range_deg", "nz_moment_nm"),
}


def one_cohort(seed, *, surrogate, fe_moments, fe_rom, plant, cal_opts, start_bank, sur_err):
    cohort = make_cohort(
        fe_moments,
        fe_rom,
        classes=CLASSES,
        n_per_class=plant["n_per_class"],
        moments=plant["moments"],
        noise_deg=plant["noise_deg"],
        rng=np.random.default_rng(seed),
    )
    noise = plant["noise_deg"]
    model = CurveModel(surrogate, cohort.moments)
    truth = cohort.truth.set_index("specimen").loc[cohort.specimens]
    planted = truth["effect"].to_numpy()
    cpu0, t0 = time.process_time(), time.perf_counter()
    diag = diagnose(
        model,
        cohort.rom_deg,
        specimens=cohort.specimens,
        noise_deg=noise,
        surrogate_error_deg=sur_err,
        start_bank=start_bank,
        seed=seed,
    )
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    verdicts = np.array([s.verdict for s in diag.specimens])
    base_mae = np.array([s.baseline_mae_deg for s in diag.specimens])
    eligible = (planted != NONE) & (base_mae > 2 * noise)
    # (a) each specimen with its diagnosed effect (the disc alone for "none").
    found_mae = np.array(
        [next(r["mae_deg"] for r in s.ranking if r["effect"] == s.verdict) for s in diag.specimens]
    )
    # (b) the user's way: recalibrate the cohort with every effect the diagnosis found.
    found = sorted({v for v in verdicts if v != NONE})
    disc = calibrate(model, cohort.rom_deg, method="pgd", options=cal_opts, seed=0)
    t1 = time.perf_counter()
    full = calibrate(EffectModel(model, found), cohort.rom_deg, method="pgd", options=cal_opts)
    t_full = time.perf_counter() - t1
    per_lc = {}
    for name, res in (("disc alone", disc), ("with " + "+".join(found), full)):
        err = np.abs(res.prediction - cohort.rom_deg)
        per_lc[name] = {lc: float(np.nanmean(err[:, j])) for j, lc in enumerate(LOAD_CASES)}
    # Effect parameters +- sd against the truth, for correctly diagnosed specimens.
    params = []
    for i, s in enumerate(diag.specimens):
        if s.verdict == NONE or s.verdict != planted[i]:
            continue
        fit = next(r for r in s.ranking if r["effect"] == s.verdict)
        for name in REPORTED[s.verdict]:
            p = fit["parameters"][name]
            params.append(
                {
                    "specimen": s.specimen,
                    "effect": s.verdict,
                    "parameter": name,
                    "value": p["value"],
                    "sd": p["sd"],
                    "truth": float(truth.iloc[i][name]),
                    "unit": p["unit"],
                }
            )
    pf = pd.DataFrame(params)
    if len(pf):
        pf["within_2sd"] = (pf["value"] - pf["truth"]).abs() <= 2 * pf["sd"]
    confusion = pd.crosstab(pd.Series(planted, name="planted"), pd.Series(verdicts, name="verdict"))
    is_none = planted == NONE
    return {
        "seed": seed,
        "n_specimens": len(planted),
        "sigma_deg": diag.sigma_deg,
        "n_eligible": int(eligible.sum()),
        "right_among_eligible": float(np.mean(verdicts[eligible] == planted[eligible])),
        "right_among_all_planted": float(np.mean(verdicts[~is_none] == planted[~is_none])),
        "none_given_effect": float(np.mean(verdicts[is_none] != NONE)),
        "confusion": {
            str(p): {str(v): int(n) for v, n in row.items()} for p, row in confusion.iterrows()
        },
        "disc_mae": {c: float(base_mae[planted == c].mean()) for c in CLASSES},
        "found_effect_mae_planted": float(found_mae[~is_none].mean()),
        "found_effect_mae_none": float(found_mae[is_none].mean()),
        "found_effects": found,
        "recalibrated_mae": {c: float(full.mae_deg[planted == c].mean()) for c in CLASSES},
        "recalibrated_mae_planted": float(full.mae_deg[~is_none].mean()),
        "recalibrated_mae_none": float(full.mae_deg[is_none].mean()),
        "disc_mae_planted": float(disc.mae_deg[~is_none].mean()),
        "recalibration_seconds": t_full,
        "per_load_case": per_lc,
        "parameters": pf,
        "seconds": wall,
        "cpu_seconds": cpu,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cohorts", type=int, default=2, help="cohort seeds 0..N-1")
    args = ap.parse_args()
    torch.manual_seed(0)
    params = load_params(REPO / "params.yaml")
    configure_tracking(store_dir=REPO / section(params, "mlflow", "store_dir"))
    model_uri = section(params, "calibrate", "model_uri")
    surrogate = load_surrogate(model_uri)
    version = resolve_model_version(model_uri)
    val = float(getattr(surrogate, "best_val_mae_deg_", float("nan")))
    sur_err = val * float(np.sqrt(np.pi / 2)) if np.isfinite(val) else 0.0
    prepared = REPO / section(params, "data", "prepared_dir")
    test, _ = load_split(prepared, "test")
    _, fe_moments, fe_rom = wide_rom(test)
    plant = {
        "n_per_class": section(params, "plant", "n_per_class"),
        "moments": [float(m) for m in section(params, "plant", "moments")],
        "noise_deg": section(params, "plant", "noise_deg"),
    }
    bank_path = REPO / section(params, "calibrate", "start_bank")
    start_bank = training_configurations(bank_path)
    cal_opts = calibration_options(
        "pgd",
        section(params, "calibrate", "options", "pgd"),
        surrogate=surrogate,
        start_bank=bank_path,
    )
    rows = [
        one_cohort(
            seed,
            surrogate=surrogate,
            fe_moments=fe_moments,
            fe_rom=fe_rom,
            plant=plant,
            cal_opts=cal_opts,
            start_bank=start_bank,
            sur_err=sur_err,
        )
        for seed in range(args.cohorts)
    ]
    write(rows, version=version, sur_err=sur_err, plant=plant)


def write(rows, *, version, sur_err, plant):
    out = REPO / "reports"
    lines = [
        "# Missing-effect search on planted cohorts",
        "",
        f"Machine: {platform.processor() or platform.machine()}, "
        f"{torch.get_num_threads()} torch threads. Surrogate: "
        f"{version['name']}/{version['version'] if version else '?'}, its error "
        f"{sur_err:.4f} deg (sd) added to the noise in quadrature. Cohorts: "
        f"{plant['n_per_class']} specimens per class, noise {plant['noise_deg']} deg, FE curves "
        "of the Test set. `benchmarks/bench_diagnose.py` wrote this file.",
        "",
        "## The issue's bars",
        "",
        "| cohort seed | specimens | right verdict where the disc alone fails (>= 90 %) | "
        "`none` given an effect (<= 10 %) | planted MAE with the found effect / `none` MAE "
        "(<= 1.5) | same, recalibrated with all found effects | diagnosis wall (CPU) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['n_specimens']} | {r['right_among_eligible']:.0%} "
            f"({r['n_eligible']} eligible) | {r['none_given_effect']:.0%} | "
            f"{r['found_effect_mae_planted']:.4f} / {r['found_effect_mae_none']:.4f} = "
            f"{r['found_effect_mae_planted'] / r['found_effect_mae_none']:.2f} | "
            f"{r['recalibrated_mae_planted']:.4f} / {r['recalibrated_mae_none']:.4f} = "
            f"{r['recalibrated_mae_planted'] / r['recalibrated_mae_none']:.2f} | "
            f"{r['seconds']:.1f} s ({r['cpu_seconds']:.1f} s) |"
        )
    lines += ["", "## Error per class: disc alone, and recalibrated with the found effects", ""]
    lines += ["| cohort | " + " | ".join(CLASSES) + " |", "|---" * (len(CLASSES) + 1) + "|"]
    for r in rows:
        lines.append(
            f"| {r['seed']}, disc alone | "
            + " | ".join(f"{r['disc_mae'][c]:.4f}" for c in CLASSES)
            + " |"
        )
        lines.append(
            f"| {r['seed']}, with {'+'.join(r['found_effects'])} | "
            + " | ".join(f"{r['recalibrated_mae'][c]:.4f}" for c in CLASSES)
            + " |"
        )
    lines += ["", "## Error per load case (whole cohort)", ""]
    lcs = LOAD_CASES
    lines += ["| cohort | model | " + " | ".join(lcs) + " |", "|---|---" + "|---" * 4 + "|"]
    for r in rows:
        for name, vals in r["per_load_case"].items():
            lines.append(
                f"| {r['seed']} | {name} | " + " | ".join(f"{vals[lc]:.4f}" for lc in lcs) + " |"
            )
    lines += ["", "## Confusion (rows planted, columns verdict)", ""]
    for r in rows:
        lines.append(f"Cohort {r['seed']}: `{json.dumps(r['confusion'])}`")
        lines.append("")
    lines += ["## Effect parameters +- sd (correct verdicts)", ""]
    lines += [
        "| cohort | parameter | n | within 2 sd | median sd | median abs. error |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        pf = r["parameters"]
        if not len(pf):
            continue
        for name, g in pf.groupby("parameter", sort=False):
            lines.append(
                f"| {r['seed']} | {name} ({g['unit'].iloc[0]}) | {len(g)} | "
                f"{g['within_2sd'].mean():.0%} | {g['sd'].median():.3g} | "
                f"{(g['value'] - g['truth']).abs().median():.3g} |"
            )
    (out / "bench_diagnose.md").write_text("\n".join(lines) + "\n")
    js = []
    for r in rows:
        r = dict(r)
        r["parameters"] = r["parameters"].to_dict("records")
        js.append(r)
    (out / "bench_diagnose.json").write_text(json.dumps(js, indent=2, default=float))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
