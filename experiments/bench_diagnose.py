"""Benchmark: the missing-effect search, closed world (issue 4) and open world (issue 11).

Two kinds of cohorts, both built from the FE curves of the study's Test set (not the surrogate),
noise sd 0.05 deg:

* ``three``: :func:`femcal.effects.planted.make_cohort` (params.yaml ``plant``): ``none``,
  ``facet_contact``, ``ligament_tension``, ``neutral_zone`` with femcal's own formulas, 12
  specimens each, 1..5 Nm in 0.5 Nm steps. Seed 0 is the pipeline's ``data/planted``.
* ``hidden``: :func:`experiments.hidden_cohorts.make_hidden_cohort`: laws unlike femcal's,
  the combinations facet + ligament and neutral zone + facet, an out-of-library softening (truth
  ``unexplained``) and ``none``, 8 specimens per class, protocols 1..5 Nm x 0.5, 1.25..5 Nm
  and 1.25..7.5 Nm x 1.25 mixed in one file (NaN where not measured). Seeds 0, 1, 2025 and
  4711 tune (:data:`experiments.hidden_cohorts.TUNING_SEEDS`);
  :data:`experiments.hidden_cohorts.HOLDOUT_SEEDS` are held out and run only with
  ``--holdout``; the fresh, criterion, polish and elimination seeds of
  :mod:`experiments.hidden_cohorts` are unseen cohorts of earlier changes of the search (each
  group its own report rows).

The surrogate is the registered champion; its own error enters sigma per moment as in the
diagnose stage (:meth:`femcal.moments.MomentPolicy.sigma_surrogate` with params.yaml
``moments``: larger beyond the trained 1..5 Nm), and the recalibration weights the points by
their inverse variances ``noise^2 / w + sd(M)^2`` and counts each specimen's error scale as
``femcal calibrate --noise-deg`` does (:meth:`~femcal.moments.MomentPolicy.point_weights`,
``calibrate(..., weight_sd=hypot(noise, sd))``).

A verdict is right when the set of registered effects it names equals the truth's; for the
out-of-library class when it contains ``unexplained`` and names no registered effect; for
``none`` when it is ``none``. A verdict ``<right effects>+unexplained`` counts as right (the
report counts them). The bars, per cohort:

(a) right verdicts >= 90 % among specimens with an effect where the disc alone misses by more
    than 2 sigma (disc-alone MAE > 2 x noise);
(b) ``none`` specimens given any other verdict <= 10 %;
(c) for the three-class cohorts: (a) and (b) as before;
(d) the cohort recalibrated as a user would, ``calibrate(EffectModel(base, found))`` with found =
    every registered effect named by any verdict: the mean MAE of every class the library covers
    within 1.5 x that of the ``none`` class (the ratio per class); for the out-of-library class
    also the MAE of the diagnosis' discrepancy fit;
(e) the diagnosis of 50 specimens <= 60 s on 2 cores (wall scaled to 50 specimens; CPU too).

Writes ``bench_diagnose.md`` and ``bench_diagnose.json`` into
``experiments/results/bench_diagnose/`` (``--out`` for another folder); the bars are also pooled per
group of cohorts (tuning, fresh, held out) with Wilson 95 % intervals. ``--from-json A.json
--from-json B.json`` writes one report from earlier runs (no diagnosis), e.g. to put a run of other
seeds beside the main one. ``--timing-only`` runs the diagnosis alone (a minute per cohort): bar
(e), and bars (a) and (b) too (eligibility comes from the diagnosis' own disc-alone fit), but none
of the visibility, ceiling and recalibration columns; with ``--diagnose-option KEY=VALUE`` its files
are named after the options (``bench_diagnose_timing_criterion-aic.md``), so an ablation never
overwrites the default's report. Run it alone: other processes on the 2 cores slow torch down badly.

Usage (from the project root, after ``make repro``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_diagnose \
        [--cohorts three,hidden] [--seeds 0,1] [--holdout] [--max-specimens N] [--out DIR]
"""

from __future__ import annotations

import argparse
import ast
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from experiments.ceiling import components_identifiable, components_visible, truth_preferred
from experiments.common import RESULTS, reproduce_command
from experiments.diagnose_report import merge_reports, write, write_timing
from experiments.diagnosis import (
    BAR_NONE,
    BAR_RATIO,
    BAR_RIGHT,
    BAR_SECONDS,
    UNEXPLAINED,
    hidden_cohort,
    hidden_seeds,
    judge_cohort,
    restrict,
    rival_counts,
    run_diagnosis,
    setup,
    three_class_cohort,
)
from experiments.hidden_cohorts import (
    HOLDOUT_SEEDS,
)
from femcal.calibration import calibrate
from femcal.effects.composite import EffectModel
from femcal.effects.planted import NONE
from femcal.schema import LOAD_CASES

#: The planted parameters reported with their uncertainty, per effect (three-class cohorts).
REPORTED = {
    "facet_contact": ("facet_gap_deg", "facet_stiffness"),
    "ligament_tension": ("ligament_slack_deg", "ligament_stiffness"),
    "neutral_zone": ("nz_range_deg", "nz_moment_nm"),
}


# ------------------------------------------------------------------------------ cohorts


# ------------------------------------------------------------------------------ verdicts


# ------------------------------------------------------------------------------ one cohort


def one_cohort(cohort: dict[str, Any], ctx: dict[str, Any]) -> dict[str, Any]:
    """Diagnose a cohort, recalibrate it with the found effects, and compute every bar."""
    rom = cohort["rom_deg"]
    labels, classes = cohort["labels"], [c for c in cohort["classes"] if c in cohort["labels"]]
    n = len(labels)
    diag, wall, cpu, model, weight = run_diagnosis(cohort, ctx)
    j = judge_cohort(cohort, diag)
    verdicts, named, right = j["verdicts"], j["named"], j["right"]
    extra_unexplained, base_mae = j["extra_unexplained"], j["base_mae"]
    is_none, eligible = j["is_none"], j["eligible"]
    # (a') the stricter subset: every hidden component would also be visible on its own
    each_visible = eligible & components_visible(cohort, ctx, model, weight)
    # (a'') each effect of a combination also shows beyond the other true effects
    identifiable = eligible & components_identifiable(cohort, ctx, model, weight)
    # (a*) the ceiling: the true combination is the library's preferred model
    pref, margin = truth_preferred(
        cohort, ctx, model, weight, np.asarray(diag.sigma_by_moment), diag
    )
    within = eligible & pref
    disc_mae_fit = np.array(
        [
            np.nan if d is None else float(d)
            for d in (getattr(s, "discrepancy_mae_deg", None) for s in diag.specimens)
        ]
    )

    # (d) the user's way: recalibrate the cohort with every registered effect any verdict named.
    found = sorted({e for nm in named for e in nm})
    opts = ctx["cal_opts"]
    disc = calibrate(
        model, rom, weight=weight, method="pgd", options=opts, seed=0, weight_sd=ctx["weight_sd"]
    )
    t1 = time.perf_counter()
    full = (
        calibrate(
            EffectModel(model, found),
            rom,
            weight=weight,
            method="pgd",
            options=opts,
            seed=0,
            weight_sd=ctx["weight_sd"],
        )
        if found
        else disc
    )
    t_full = time.perf_counter() - t1
    per_lc = {}
    for name, res in (("disc alone", disc), ("with " + ("+".join(found) or "nothing"), full)):
        err = np.abs(res.prediction - rom)
        per_lc[name] = {lc: float(np.nanmean(err[:, j])) for j, lc in enumerate(LOAD_CASES)}
    # A recalibration that returns NaN is a failure of bar (d); the means are over the finite
    # MAEs and the NaNs are counted (per class and in the cohort).
    recal_nan = ~np.isfinite(full.mae_deg)
    none_floor = _finite_mean(full.mae_deg[is_none])
    per_class = {}
    for c in classes:
        sel = labels == c
        covered = bool(cohort["expected"][int(np.flatnonzero(sel)[0])]) and c != UNEXPLAINED
        recal = _finite_mean(full.mae_deg[sel])
        el = eligible[sel]
        per_class[c] = {
            "n": int(sel.sum()),
            "n_eligible": int(el.sum()),
            "right": int(right[sel].sum()),
            "right_eligible": int(right[sel][el].sum()),
            "n_each_visible": int(each_visible[sel].sum()),
            "right_each_visible": int(right[sel][each_visible[sel]].sum()),
            "n_identifiable": int(identifiable[sel].sum()),
            "right_identifiable": int(right[sel][identifiable[sel]].sum()),
            "extra_unexplained": int(extra_unexplained[sel].sum()),
            "disc_mae_diagnosis": float(np.mean(base_mae[sel])),
            "disc_mae": float(np.mean(disc.mae_deg[sel])),
            "recalibrated_mae": recal,
            "recalibrated_nan": int(recal_nan[sel].sum()),
            "ratio_to_none": recal / none_floor if c != NONE else 1.0,
            "covered": covered,
            "discrepancy_mae": float(np.nanmean(disc_mae_fit[sel]))
            if np.isfinite(disc_mae_fit[sel]).any()
            else None,
        }
    covered_ratios = [v["ratio_to_none"] for c, v in per_class.items() if v["covered"]]
    per_protocol = {}
    for p in dict.fromkeys(cohort["protocol"].tolist()):
        sel = (cohort["protocol"] == p) & eligible
        per_protocol[p] = {
            "n_eligible": int(sel.sum()),
            "right_eligible": int(right[sel].sum()),
            "none_given_effect": int((verdicts[is_none & (cohort["protocol"] == p)] != NONE).sum()),
            "n_none": int((is_none & (cohort["protocol"] == p)).sum()),
        }
    confusion = pd.crosstab(
        pd.Series(labels, name="truth"), pd.Series(verdicts, name="verdict")
    ).reindex(classes)
    specimens = [
        {
            "specimen": s.specimen,
            "class": str(labels[i]),
            "protocol": str(cohort["protocol"][i]),
            "verdict": str(verdicts[i]),
            "named": named[i],
            "right": bool(right[i]),
            "eligible": bool(eligible[i]),
            "each_component_visible": bool(each_visible[i]),
            "identifiable": bool(identifiable[i]),
            "truth_preferred": bool(pref[i]),
            "truth_bic_margin": None if np.isnan(margin[i]) else float(margin[i]),
            "disc_mae": float(base_mae[i]),
            "recalibrated_mae": float(full.mae_deg[i]),
            "discrepancy_mae": None if np.isnan(disc_mae_fit[i]) else float(disc_mae_fit[i]),
        }
        for i, s in enumerate(diag.specimens)
    ]
    bars = {
        "a_right_eligible": float(np.mean(right[eligible])) if eligible.any() else float("nan"),
        "a_right_each_visible": float(np.mean(right[each_visible]))
        if each_visible.any()
        else float("nan"),
        "a_right_identifiable": float(np.mean(right[identifiable]))
        if identifiable.any()
        else float("nan"),
        "a_right_truth_preferred": float(np.mean(right[within])) if within.any() else float("nan"),
        "a_ceiling": float(np.mean(within[eligible])) if eligible.any() else float("nan"),
        "b_none_given_effect": float(np.mean(verdicts[is_none] != NONE))
        if is_none.any()
        else float("nan"),
        "d_worst_ratio": float(max(covered_ratios)) if covered_ratios else float("nan"),
        "e_wall_per_50": wall * 50 / n,
        "e_cpu_per_50": cpu * 50 / n,
    }
    bars["pass"] = {
        "a": bool(bars["a_right_eligible"] >= BAR_RIGHT),
        "b": bool(bars["b_none_given_effect"] <= BAR_NONE),
        "d": bool(bars["d_worst_ratio"] <= BAR_RATIO) and not recal_nan.any(),
        "e": bool(bars["e_wall_per_50"] <= BAR_SECONDS),
    }
    return {
        "kind": cohort["kind"],
        "seed": cohort["seed"],
        "holdout": cohort["kind"] == "hidden" and cohort["seed"] in HOLDOUT_SEEDS,
        "n_specimens": n,
        "moments": [float(m) for m in cohort["moments"]],
        "sigma_deg": float(diag.sigma_deg),
        "sigma_by_moment": None
        if getattr(diag, "sigma_by_moment", None) is None
        else [float(s) for s in diag.sigma_by_moment],
        "n_eligible": int(eligible.sum()),
        "n_right_eligible": int(right[eligible].sum()),
        **rival_counts(j),
        "n_each_visible": int(each_visible.sum()),
        "n_right_each_visible": int(right[each_visible].sum()),
        "n_identifiable": int(identifiable.sum()),
        "n_right_identifiable": int(right[identifiable].sum()),
        "n_truth_preferred": int(within.sum()),
        "n_right_truth_preferred": int(right[within].sum()),
        "n_none": int(is_none.sum()),
        "n_none_given_effect": int((verdicts[is_none] != NONE).sum()),
        "n_extra_unexplained": int(extra_unexplained.sum()),
        "bars": bars,
        "per_class": per_class,
        "per_protocol": per_protocol,
        "confusion": {
            str(t): {str(v): int(k) for v, k in row.items() if k} for t, row in confusion.iterrows()
        },
        "found_effects": found,
        "none_floor_mae": none_floor,
        "n_recalibrated_nan": int(recal_nan.sum()),
        "per_load_case": per_lc,
        "parameters": parameter_table(diag, cohort, named, right)
        if cohort["kind"] == "three"
        else [],
        "seconds": wall,
        "cpu_seconds": cpu,
        "recalibration_seconds": t_full,
        "specimens": specimens,
    }


def _finite_mean(x: np.ndarray) -> float:
    """Mean of the finite values (NaN when there are none)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else float("nan")


def parameter_table(diag, cohort, named, right) -> list[dict[str, Any]]:
    """Effect parameters +- sd against the planted truth, right single-effect verdicts."""
    truth = cohort["truth"]
    rows = []
    for i, s in enumerate(diag.specimens):
        if not right[i] or len(named[i]) != 1 or named[i][0] not in REPORTED:
            continue
        fit = next(
            (r for r in s.ranking if set(r.get("effects", [r["effect"]])) == set(named[i])), None
        )
        if fit is None:
            continue
        for name in REPORTED[named[i][0]]:
            p = fit["parameters"].get(name)
            if p is None:
                continue
            t = float(truth.iloc[i][name])
            rows.append(
                {
                    "specimen": s.specimen,
                    "effect": named[i][0],
                    "parameter": name,
                    "value": p["value"],
                    "sd": p["sd"],
                    "truth": t,
                    "unit": p["unit"],
                    "within_2sd": bool(abs(p["value"] - t) <= 2 * p["sd"]),
                }
            )
    return rows


# ------------------------------------------------------------------------------ main


def timing_row(cohort: dict[str, Any], ctx: dict[str, Any]) -> dict[str, Any]:
    """Diagnose a cohort alone (``--timing-only``): wall and CPU seconds, bars (a) and (b), and
    per specimen the verdict, the rival and the measurements that would settle it."""
    kind, seed = cohort["kind"], cohort["seed"]
    diag, wall, cpu, _, _ = run_diagnosis(cohort, ctx)
    n = len(cohort["specimens"])
    j = judge_cohort(cohort, diag)
    return {
        "kind": kind,
        "seed": seed,
        "holdout": kind == "hidden" and seed in HOLDOUT_SEEDS,
        "n_specimens": n,
        "seconds": wall,
        "cpu_seconds": cpu,
        "wall_per_50": wall * 50 / n,
        "cpu_per_50": cpu * 50 / n,
        "n_eligible": int(j["eligible"].sum()),
        "n_right_eligible": int(j["right"][j["eligible"]].sum()),
        **rival_counts(j),
        "n_none": int(j["is_none"].sum()),
        "n_none_given_effect": int((j["verdicts"][j["is_none"]] != NONE).sum()),
        "verdicts": j["verdicts"].tolist(),
        "classes": [str(c) for c in cohort["labels"]],
        "eligible": j["eligible"].tolist(),
        "right": j["right"].tolist(),
        "rivals": j["rivals"],
        # where the rival differs most (sigma) and the measurements to settle it
        "rival_sigma": [
            None if not s.next_measurement else s.next_measurement["difference_sigma"]
            for s in diag.specimens
        ],
        "rival_repeats": [
            None if not s.next_measurement else s.next_measurement.get("repeats_to_settle")
            for s in diag.specimens
        ],
    }


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cohorts", default="three,hidden", help="comma-separated: three, hidden")
    ap.add_argument("--seeds", default="0,1", help="tuning seeds of every cohort kind")
    ap.add_argument(
        "--holdout",
        action="store_true",
        help=f"also the held-out hidden cohorts {', '.join(map(str, HOLDOUT_SEEDS))}",
    )
    ap.add_argument("--max-specimens", type=int, default=None, help="per cohort (quick runs)")
    ap.add_argument(
        "--timing-only",
        action="store_true",
        help="only the diagnosis: bar (e) on a quiet machine, and bars (a) and (b); writes "
        "bench_diagnose_timing[_OPTIONS].md/.json, no recalibration, visibility or ceiling",
    )
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_diagnose", help="report folder")
    ap.add_argument(
        "--from-json",
        type=Path,
        action="append",
        default=[],
        metavar="PATH",
        help="rewrite the report from earlier runs' bench_diagnose.json (repeatable: their "
        "cohorts side by side), diagnosing nothing",
    )
    ap.add_argument(
        "--model-uri", default=None, help="the surrogate (default: params.yaml calibrate.model_uri)"
    )
    ap.add_argument(
        "--diagnose-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a keyword of femcal.diagnose.diagnose for an ablation (a Python literal), repeatable",
    )
    ap.add_argument(
        "--surrogate-error-in-range",
        type=float,
        default=None,
        metavar="DEG",
        help="an ablation: count the surrogate's error inside its trained moments as DEG "
        "instead of the policy's pre-fit sd (beyond them its growth is kept: sd(M)^2 = DEG^2 + "
        "sd_policy(M)^2 - sd_policy(in range)^2); see experiments/bench_postfit_error.py",
    )
    args = ap.parse_args(argv)
    if args.from_json:
        rows, meta = merge_reports(args.from_json)
        # --timing-only rows (no per-specimen table) join into a timing report
        (write_timing if all("specimens" not in r for r in rows) else write)(rows, meta, args.out)
        return
    options = {}
    for item in args.diagnose_option:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--diagnose-option: expected KEY=VALUE, got {item!r}")
        try:
            options[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            ap.error(f"--diagnose-option {key}: {value!r} is not a Python literal")
    kinds = [k.strip() for k in args.cohorts.split(",") if k.strip()]
    for k in kinds:
        if k not in ("three", "hidden"):
            ap.error(f"--cohorts: unknown kind '{k}' (three, hidden)")
    seeds = hidden_seeds(ap, args.seeds, args.holdout)
    torch.manual_seed(0)
    ctx = setup(args.model_uri, options, args.surrogate_error_in_range)
    fe_moments, fe_rom, plant, policy = (
        ctx["fe_moments"],
        ctx["fe_rom"],
        ctx["plant"],
        ctx["policy"],
    )
    jobs = [(k, s) for k in kinds for s in seeds]
    if args.holdout and "hidden" in kinds:
        jobs += [("hidden", s) for s in HOLDOUT_SEEDS if s not in seeds]
    rows = []
    for kind, seed in jobs:
        if kind == "three":
            cohort = three_class_cohort(seed, fe_moments, fe_rom, plant)
        else:
            cohort = hidden_cohort(seed, fe_moments, fe_rom, plant["noise_deg"])
        cohort = restrict(cohort, args.max_specimens)
        print(f"{kind} seed {seed}: {len(cohort['specimens'])} specimens ...", flush=True)
        if args.timing_only:
            rows.append(timing_row(cohort, ctx))
        else:
            rows.append(one_cohort(cohort, ctx))
    command = reproduce_command("bench_diagnose", argv)
    meta = {
        "command": command,
        "machine": platform.processor() or platform.machine(),
        "torch_threads": torch.get_num_threads(),
        "surrogate": ctx["surrogate_name"],
        "surrogate_error_deg": ctx["sur_err"],
        "moment_policy": None
        if policy is None
        else {"growth": policy.growth, "max_log_ratio": policy.max_log_ratio},
        "max_specimens": args.max_specimens,
        "diagnose_options": options,
        "surrogate_error_in_range": args.surrogate_error_in_range,
        "noise_deg": plant["noise_deg"],
    }
    if args.timing_only:
        write_timing(rows, meta, args.out)
    else:
        write(rows, meta, args.out)


# ------------------------------------------------------------------------------ report


if __name__ == "__main__":
    main()
