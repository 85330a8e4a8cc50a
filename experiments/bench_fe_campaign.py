"""Benchmark: the FE campaign on Dask, one worker against two, and the full campaign's figures.

A Latin-hypercube design of ``--n`` configurations (default 64) over the study's bounds, the
four pure-moment load cases at 1..5 Nm, CalculiX with the ``--preset`` mesh (default
"default"). Three runs, each into a campaign store in a work folder:

1. the first ``--subset`` configurations (default 8) with ONE worker (fresh store);
2. the same configurations with TWO workers (fresh store): the speed-up is the ratio of the
   two wall times (local cluster start-up included in both);
3. all ``--n`` configurations with two workers, resuming the store of run 2 (its jobs are
   not recomputed): CPU seconds per configuration, failure rate and every failure's reason.

Writes ``bench_fe_campaign.md`` and ``bench_fe_campaign.json`` into
``experiments/results/bench_fe_campaign/``.

Usage (from the project root; on a quiet machine, the timing is wall-clock)::

    .venv/bin/python -m experiments.bench_fe_campaign [--n 64] [--preset default] [--subset 8]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments.common import RESULTS
from femcal.fe.campaign import CampaignResult, run_campaign
from femcal.fe.design import design
from femcal.fe.options import CampaignOptions
from femcal.stages.simulate import fe_space

#: The study's ParameterBounds.csv.
BOUNDS = {
    "C10Nucleus": [0.03, 0.21],
    "C01Nucleus": [0.0075, 0.0525],
    "C10Annulus": [0.065, 0.455],
    "K1Annulus": [1.0, 50.0],
    "K2Annulus": [10.0, 200.0],
    "Kappa": [0.0, 0.33],
    "K1Circ": [-0.2, 0.0],
    "K2Circ": [-0.2, 0.0],
    "K1Rad": [-0.2, 0.0],
    "K2Rad": [-0.2, 0.0],
    "FiberAngle": [7.5, 52.5],
    "FiberAngleCirc": [0.0, 0.3],
    "FiberAngleRad": [0.0, 0.2],
}
MOMENTS = (1.0, 2.0, 3.0, 4.0, 5.0)


def _run(settings: dict, design_df, store: Path, n_workers: int) -> tuple[CampaignResult, dict]:
    load = os.getloadavg()[0]
    result = run_campaign(
        "calculix",
        settings,
        design_df,
        CampaignOptions(n_workers=n_workers, keep_failed=False, progress=True),
        store=store,
        moments=MOMENTS,
    )
    return result, {"load_average_1min_before": round(load, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=64, help="configurations of the full campaign")
    parser.add_argument("--preset", default="default", help="mesh preset: coarse, default, fine")
    parser.add_argument("--subset", type=int, default=8, help="configurations timed 1 vs 2")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out",
        default=str(RESULTS / "bench_fe_campaign" / "bench_fe_campaign"),
        help="report path stem",
    )
    parser.add_argument("--work", help="folder for the campaign stores (default: a temp folder)")
    args = parser.parse_args()

    settings = {"geometry": args.preset}
    subset = min(args.subset, args.n)
    space = fe_space(BOUNDS)
    full = design(space, args.n, np.random.default_rng(args.seed))
    part = full.iloc[:subset].reset_index(drop=True)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench-fe-"))
    work.mkdir(parents=True, exist_ok=True)
    for name in ("one.jsonl", "two.jsonl"):
        (work / name).unlink(missing_ok=True)

    one, one_info = _run(settings, part, work / "one.jsonl", n_workers=1)
    two, two_info = _run(settings, part, work / "two.jsonl", n_workers=2)
    total, total_info = _run(settings, full, work / "two.jsonl", n_workers=2)

    cpu = total.cpu_seconds_per_config()
    failures = total.failures()
    reasons = failures["reason"].value_counts().to_dict() if len(failures) else {}
    report = {
        "preset": args.preset,
        "n_configurations": args.n,
        "n_jobs": total.n_jobs,
        "subset_configurations": subset,
        "subset_jobs": one.n_jobs,
        "wall_seconds_1_worker": round(one.wall_seconds, 2),
        "wall_seconds_2_workers": round(two.wall_seconds, 2),
        "speedup_2_vs_1": round(one.wall_seconds / two.wall_seconds, 3),
        "subset_cpu_seconds_1_worker": round(float(one.records["cpu_seconds"].sum()), 2),
        "subset_cpu_seconds_2_workers": round(float(two.records["cpu_seconds"].sum()), 2),
        "worker_python_cpu_seconds_per_configuration_mean": round(
            float(total.records.groupby("config_id")["worker_cpu_seconds"].sum().mean()), 3
        ),
        "full_wall_seconds_resumed": round(total.wall_seconds, 2),
        "full_jobs_resumed_from_store": total.n_skipped,
        "cpu_seconds_per_configuration": {
            "mean": round(float(cpu.mean()), 3),
            "median": round(float(cpu.median()), 3),
            "min": round(float(cpu.min()), 3),
            "max": round(float(cpu.max()), 3),
        },
        "failure_rate": total.failure_rate,
        "n_failed": int(len(failures)),
        "failures": failures.to_dict(orient="records"),
        "failure_reasons": {str(k): int(v) for k, v in reasons.items()},
        "solver_versions": total.summary()["solver_versions"],
        "load_average": {"one": one_info, "two": two_info, "full": total_info},
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
        },
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    lines = [
        "# FE campaign on Dask: one worker vs two",
        "",
        f"CalculiX {', '.join(report['solver_versions'])}, mesh preset `{args.preset}`, four "
        f"pure-moment load cases at 1..5 Nm, LHS design (seed {args.seed}); "
        f"{report['machine']['cpus']} CPUs, {report['date']}. "
        "`experiments/bench_fe_campaign.py`.",
        "",
        f"## Speed-up ({subset} configurations = {one.n_jobs} jobs, same jobs both times)",
        "",
        "| workers | wall (s) | solver CPU (s) | load average before |",
        "| --- | --- | --- | --- |",
        f"| 1 | {one.wall_seconds:.1f} | {report['subset_cpu_seconds_1_worker']:.1f} | "
        f"{one_info['load_average_1min_before']} |",
        f"| 2 | {two.wall_seconds:.1f} | {report['subset_cpu_seconds_2_workers']:.1f} | "
        f"{two_info['load_average_1min_before']} |",
        "",
        f"Speed-up 2 vs 1 worker: **{report['speedup_2_vs_1']:.2f}x** (wall times include "
        "the local cluster's start-up).",
        "",
        f"## Full campaign ({args.n} configurations = {total.n_jobs} jobs, 2 workers)",
        "",
        f"Resumed from the 2-worker store ({total.n_skipped} jobs not recomputed); wall "
        f"{total.wall_seconds:.1f} s for the rest.",
        "",
        "| CPU seconds per configuration (4 load cases) | mean | median | min | max |",
        "| --- | --- | --- | --- | --- |",
        "| solver (ccx) | {mean:.2f} | {median:.2f} | {min:.2f} | {max:.2f} |".format(
            **report["cpu_seconds_per_configuration"]
        ),
        "",
        "Beside the solver, each worker spends "
        f"{report['worker_python_cpu_seconds_per_configuration_mean']:.2f} CPU s per "
        "configuration in Python (deck writing, mesh, parsing the results).",
        "",
        f"Failure rate: **{report['failure_rate']:.3f}** ({report['n_failed']} of "
        f"{total.n_jobs} jobs).",
        "",
    ]
    if len(failures):
        lines += ["| config | load case | attempts | reason |", "| --- | --- | --- | --- |"]
        for f in report["failures"]:
            reason = str(f["reason"]).replace("|", "/")
            lines.append(f"| {f['config_id']} | {f['load_case']} | {f['attempts']} | {reason} |")
        lines.append("")
    out.with_suffix(".md").write_text("\n".join(lines))
    print("\n".join(lines))
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
