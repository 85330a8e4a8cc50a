"""Benchmark: do calibrate's identifiability ranges cover the truth when measurements are noisy?

The study's 64 synthetic Test specimens (their FE RoM at 1..5 Nm, true parameters known),
with Gaussian measurement noise added (sd 0.05 deg, seeded): one measurement per point, or
the mean of ``k`` repeated measurements (noise sd 0.05 / sqrt(k), weight ``k``), as
``femcal calibrate`` reads repeated rows. Each is calibrated with ``pgd`` (params.yaml's
options, the Large split's configurations as starts) twice, with the weights and error scale
``femcal calibrate`` uses:

- **without a measurement noise** (``noise_deg`` left out): each point weighs ``w / sd(M)^2``
  and the ranges count the surrogate's error sd alone;
- **with it** (``--noise-deg 0.05``): each point weighs ``1 / (noise^2 / w + sd(M)^2)``
  (:meth:`femcal.moments.MomentPolicy.point_weights`) and the ranges count each specimen's
  own sd of a point of average weight (``calibrate(..., weight_sd=hypot(noise, sd))``,
  :attr:`femcal.calibration.base.CalibrationProblem.point_sd`).

A last case measures half the specimens (the odd ones) ``k`` times at every point and the
others once, and also calibrates it with one error scale for the whole file (the average,
:meth:`~femcal.moments.MomentPolicy.average_sd`): the coverage of each half shows whether
each specimen's ranges count its own noise.

Reported per case: MAE against the measured points and against the noise-free FE curves, the
coverage of the true parameters by the 2-sigma ranges (all 13, and the parameters RoM
determines: those whose range in the noise-free calibration is narrower than half the box), and
the ranges' mean width; with the noise, the specimens flagged ``beyond noise`` (chi-square
p < 0.01 on the points less the fit's effective parameters, and with one degree of freedom per
point for comparison: false alarms, as the disc model describes FE curves). Last, the planted cohort
(hidden effects) calibrated with the disc alone and with its found effects: the specimens
flagged per true class. Writes
``experiments/results/bench_calibrate_noise/bench_calibrate_noise.md`` and ``.json``.

Usage (from the project root, after ``make repro``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_calibrate_noise
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

from experiments.common import REPO, RESULTS
from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.calibration.base import chi2_p_value
from femcal.calibration.report import BEYOND_NOISE_P, coverage
from femcal.config import load_params, section
from femcal.datasets import load_split
from femcal.jobs.calibrate import calibration_options
from femcal.measurements import read_measurements
from femcal.moments import MomentPolicy
from femcal.stages.common import moment_settings
from femcal.tracking import load_surrogate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default=str(REPO / "params.yaml"))
    parser.add_argument("--noise-deg", type=float, default=0.05)
    parser.add_argument("--repeats", default="1,10", help="comma-separated k")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", default=str(RESULTS / "bench_calibrate_noise" / "bench_calibrate_noise")
    )
    args = parser.parse_args()
    repeats = [int(k) for k in args.repeats.split(",")]

    params = load_params(args.params)
    cfg = section(params, "calibrate")
    entry = cfg["datasets"]["test"]
    meas = read_measurements(REPO / (entry["measurements"] if isinstance(entry, dict) else entry))
    test, space = load_split(REPO / section(params, "data", "prepared_dir"), "test")
    x_true = test.drop_duplicates("config_id")[list(space.names)].to_numpy(dtype=float)
    surrogate = load_surrogate(REPO / cfg["model_uri"])
    policy = MomentPolicy.for_surrogate(surrogate, **_policy_args(params))
    model = SurrogateCurveModel(surrogate, meas.moments)
    bank = REPO / cfg["start_bank"]
    truth = meas.rom_deg  # (64, 4, 5): noise-free FE curves
    rng = np.random.default_rng(args.seed)

    def run(y, weight, noise, per_specimen=True):
        # As the calibrate stage does (femcal.jobs.calibrate.run_calibration).
        w = policy.point_weights(meas.moments, weight, noise)
        sd = None if noise is None else policy.average_sd(meas.moments, weight, noise)
        opts = calibration_options(
            "pgd", cfg["options"]["pgd"], surrogate=surrogate, start_bank=bank, point_sd_deg=sd
        )
        own = noise is not None and per_specimen
        weight_sd = policy.unit_sd(noise) if own else None
        return calibrate(
            model, y, weight=w, method="pgd", seed=0, options=opts, weight_sd=weight_sd
        )

    clean = run(truth, np.ones_like(truth), None)
    determined = (clean.x_high - clean.x_low) / space.width < 0.5  # (64, 13)
    rows = []
    cases = [(f"{k} at every point", np.full(truth.shape, float(k))) for k in repeats]
    top = np.ones(truth.shape)
    top[..., -1] = max(repeats)  # repeats at the largest moment only: the weights differ
    cases.append((f"{max(repeats)} at {meas.moments[-1]:g} Nm, 1 elsewhere", top))
    odd = np.arange(len(truth)) % 2 == 1
    mixed = np.ones(truth.shape)
    mixed[odd] = max(repeats)  # some specimens repeated, the others not: the scales differ
    cases.append((f"{max(repeats)} at every point for the odd specimens, 1 for the others", mixed))
    noise_label = f"noise_deg {args.noise_deg:g}"
    for case, weight in cases:
        y = truth + rng.normal(0.0, 1.0, truth.shape) * args.noise_deg / np.sqrt(weight)
        runs = [("without noise_deg", None, True), (noise_label, args.noise_deg, True)]
        if weight is mixed:
            runs.append((f"{noise_label}, one scale for the file", args.noise_deg, False))
        for label, noise, per_specimen in runs:
            res = run(y, weight, noise, per_specimen)
            inside = (x_true >= res.x_low - 1e-9) & (x_true <= res.x_high + 1e-9)
            row = {
                "repeats": case,
                "calibration": label,
                "mae_measured_deg": float(np.mean(res.mae_deg)),
                "mae_fe_truth_deg": float(np.nanmean(np.abs(res.prediction - truth))),
                "coverage_all": float(np.mean(coverage(res, x_true))),
                "coverage_determined": float(inside[determined].mean()),
                "range_width_mean": float(np.mean((res.x_high - res.x_low) / space.width)),
            }
            if res.p_value is not None:  # the model explains FE curves: flags are false alarms
                row["n_beyond_noise"] = int(np.sum(res.p_value < BEYOND_NOISE_P))
                row["n_beyond_noise_all_dof"] = int(flagged_all_dof(res).sum())
                row["n_effective_median"] = float(np.median(res.n_effective))
                row["n_refitted"] = int(res.info.get("n_refitted", 0))
                row["rms_z_median"] = float(np.median(res.rms_z))
            if weight is mixed:  # each half's own coverage of its determined pairs
                single, repeated = determined & ~odd[:, None], determined & odd[:, None]
                row["coverage_determined_single"] = float(inside[single].mean())
                row["coverage_determined_repeated"] = float(inside[repeated].mean())
            rows.append(row)
            print(rows[-1], flush=True)
    planted = _planted(params, cfg, surrogate, policy, bank, args.noise_deg)
    out = {
        "machine": f"{platform.machine()}, {platform.system()}",
        "noise_deg": args.noise_deg,
        "seed": args.seed,
        "surrogate_error_deg": policy.error_deg,
        "n_specimens": int(len(truth)),
        "n_determined": int(determined.sum()),
        "rows": rows,
        "planted": planted,
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.with_suffix(".json").write_text(json.dumps(out, indent=2) + "\n")
    path.with_suffix(".md").write_text(_markdown(out, args))
    print(f"wrote {path.with_suffix('.md')}")


def _planted(params, cfg, surrogate, policy, bank, noise: float) -> list[dict]:
    """The planted cohort (the plant stage's hidden effects, its own noise) calibrated as
    ``femcal calibrate --noise-deg`` does, with the disc alone and with the effects of its
    ``calibrate.datasets.planted`` entry: per true class, the specimens flagged "beyond noise"."""
    import pandas as pd

    from femcal.effects.composite import EffectModel

    entry = cfg["datasets"]["planted"]
    path = REPO / entry["measurements"]
    meas = read_measurements(path)
    truth = pd.read_csv(path.parent / "truth.csv").set_index("specimen")
    labels = truth.loc[list(meas.specimens), "effect"].to_numpy()
    w = policy.point_weights(meas.moments, meas.weight, noise)
    sd = policy.average_sd(meas.moments, meas.weight, noise, meas.mask())
    opts = calibration_options(
        "pgd", cfg["options"]["pgd"], surrogate=surrogate, start_bank=bank, point_sd_deg=sd
    )
    disc = SurrogateCurveModel(surrogate, meas.moments)
    rows = []
    for effects in ([], list(entry.get("effects", []))):
        model = EffectModel(disc, effects) if effects else disc
        res = calibrate(
            model,
            meas.rom_deg,
            weight=w,
            method="pgd",
            seed=0,
            options=opts,
            weight_sd=policy.unit_sd(noise),
        )
        flagged = res.p_value < BEYOND_NOISE_P
        for label in sorted(set(labels)):
            sel = labels == label
            rows.append(
                {
                    "model": "+".join(["disc", *effects]),
                    "class": str(label),
                    "n": int(sel.sum()),
                    "n_beyond_noise": int(flagged[sel].sum()),
                    "n_beyond_noise_all_dof": int(flagged_all_dof(res)[sel].sum()),
                    "n_effective_median": float(np.median(res.n_effective[sel])),
                    "n_refitted": int(res.info.get("n_refitted", 0)),
                    "rms_z_median": float(np.median(res.rms_z[sel])),
                }
            )
            print(rows[-1], flush=True)
    return rows


def flagged_all_dof(res) -> np.ndarray:
    """Per specimen (n,): flagged by the conservative test (one degree of freedom per point)."""
    return chi2_p_value(res.chi2, res.n_points) < BEYOND_NOISE_P


def _policy_args(params) -> dict:
    m = moment_settings(params)
    return {"growth": m["error_growth"], "max_log_ratio": m["max_log_ratio"]}


def _markdown(out: dict, args) -> str:
    lines = [
        "# Calibration of noisy and repeated measurements: ranges with and without the noise",
        "",
        "Reproduce: `OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_calibrate_noise"
        f" --noise-deg {args.noise_deg:g} --repeats {args.repeats} --seed {args.seed}`",
        "",
        f"The study's {out['n_specimens']} Test specimens (FE RoM at 1..5 Nm, true parameters "
        f"known) with Gaussian noise of sd {out['noise_deg']:g} deg added (seed {out['seed']}); "
        "k repeats at a point = their mean (sd / sqrt(k), weight k), as `femcal calibrate` "
        "reads repeated rows. `pgd` with params.yaml's options; the surrogate's in-range error sd "
        f"{out['surrogate_error_deg']:.4f} deg. Without `noise_deg`, a point weighs w / sd(M)² "
        "and the ranges count the surrogate's error alone; with it, 1 / (noise²/w + sd(M)²) "
        "and the sd of a point of average weight, sqrt(noise²/k + sd²). Coverage: share of "
        "true parameter values inside the 2σ ranges, over all 13 parameters and over the "
        f"{out['n_determined']} (specimen, parameter) pairs the noise-free calibration "
        "determines (range narrower than half the box).",
        "",
        "| repeats | calibration | weighted MAE vs measured (°) | MAE vs noise-free FE (°) | "
        "coverage, all | coverage, determined | mean range width (box) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in out["rows"]:
        lines.append(
            f"| {r['repeats']} | {r['calibration']} | {r['mae_measured_deg']:.4f} | "
            f"{r['mae_fe_truth_deg']:.4f} | {r['coverage_all']:.3f} | "
            f"{r['coverage_determined']:.3f} | {r['range_width_mean']:.3f} |"
        )
    halves = [r for r in out["rows"] if "coverage_determined_single" in r]
    if halves:
        lines += [
            "",
            "Where some specimens are repeated and others not, the coverage of each half's "
            "determined pairs (one scale for the file = the average point's sd for every "
            "specimen):",
            "",
            "| calibration | coverage, determined, single measurements | coverage, determined, "
            "repeated |",
            "| --- | --- | --- |",
        ]
        for r in halves:
            lines.append(
                f"| {r['calibration']} | {r['coverage_determined_single']:.3f} | "
                f"{r['coverage_determined_repeated']:.3f} |"
            )
    alarms = [r for r in out["rows"] if "n_beyond_noise" in r]
    if alarms:
        lines += [
            "",
            f"Does the model explain the data within the noise? With `noise_deg`, "
            "`femcal calibrate` flags a specimen `beyond noise` where its residuals' chi-square "
            "(on the points less the fit's effective parameters, the trace of its hat matrix) "
            f"has p < {BEYOND_NOISE_P:g}. The FE curves "
            "of the Test set are what the disc model describes, so each flag here is a false "
            "alarm. pgd first refits, from four times the starts, every specimen its fit "
            "leaves beyond the noise (`retry_alpha`), and keeps the better fit. For comparison, "
            "the flags of the conservative test with one degree of freedom per point:",
            "",
            "| repeats | calibration | refitted by pgd | flagged beyond noise | flagged, one "
            "degree of freedom per point | median effective parameters | median RMS residual "
            "/ sd |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in alarms:
            lines.append(
                f"| {r['repeats']} | {r['calibration']} | {r.get('n_refitted', 0)} | "
                f"{r['n_beyond_noise']} / {out['n_specimens']} | "
                f"{r.get('n_beyond_noise_all_dof', '-')} / {out['n_specimens']} | "
                f"{r.get('n_effective_median', float('nan')):.1f} | {r['rms_z_median']:.2f} |"
            )
    if out.get("planted"):
        lines += [
            "",
            "The planted cohort (`data/planted`, the plant stage's hidden effects on FE curves, "
            "noise 0.05°), calibrated with the disc alone and with the effects `femcal "
            "diagnose` found (params.yaml `calibrate.datasets.planted`):",
            "",
            "| model | true class | flagged beyond noise | flagged, one degree of freedom per "
            "point | median effective parameters | median RMS residual / sd |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for r in out["planted"]:
            lines.append(
                f"| {r['model']} | {r['class']} | {r['n_beyond_noise']} / {r['n']} | "
                f"{r.get('n_beyond_noise_all_dof', '-')} / {r['n']} | "
                f"{r.get('n_effective_median', float('nan')):.1f} | {r['rms_z_median']:.2f} |"
            )
        refits = {r["model"]: r.get("n_refitted", 0) for r in out["planted"]}
        lines += [
            "",
            "Refitted by pgd (of "
            f"{sum(r['n'] for r in out['planted']) // max(len(refits), 1)}): "
            + ", ".join(f"{m} {k}" for m, k in refits.items())
            + ".",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
