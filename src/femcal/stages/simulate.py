"""Stage ``simulate`` (fe/dvc.yaml): an FE campaign on Dask, written in the study's layout."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.fe.runtime import FeRuntime, fe_runtime, fe_space
from femcal.paths import setting_path
from femcal.stages.common import (
    StageSettings,
    output_folder,
    typed,
    write_metrics,
)

__all__ = ["SimulateSettings", "describe", "fe_runtime", "fe_space", "run", "run_simulate"]

#: Failed jobs listed one by one in the stage's report (all of them are in runs.csv).
MAX_FAILURES_LISTED = 10

#: The summary keys the stage's DVC metrics file holds.
METRICS_KEYS = (
    "n_configurations",
    "n_jobs",
    "n_ok",
    "n_failed",
    "failure_rate",
    "cpu_seconds_per_configuration",
    "cpu_seconds_total",
    "failure_reasons",
    "failed_levels_reached",
    "moments",
    "campaign_wall_seconds",
    "campaign_runs",
)


@dataclass(frozen=True)
class SimulateSettings(StageSettings):
    """The ``fe`` section of fe/params.yaml, with the command line's overrides."""

    fe: FeRuntime
    bounds: Any
    splits: Mapping[str, int]
    seed: int
    batches: Sequence[int | Mapping[str, Any]]
    load_cases: Sequence[str]
    moments: Sequence[float]
    out_dir: Path
    scratch_dir: Path | None = None
    retry_timeouts: bool = False

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> SimulateSettings:
        cfg = typed(params, "fe")
        out = output_folder(params, args, "fe")  # before the campaign
        scratch = cfg.scratch_dir
        return cls(
            fe=fe_runtime(params, args, "fe"),
            bounds=cfg.bounds,
            splits=cfg.splits,
            seed=cfg.seed,
            batches=list(cfg.batches),
            load_cases=list(cfg.load_cases),
            moments=list(cfg.moments),
            out_dir=out,
            scratch_dir=setting_path(params, scratch) if scratch else None,
            retry_timeouts=bool(args.get("retry_timeouts")),
            metrics_file=args.get("metrics_file"),
        )


def run(settings: SimulateSettings) -> dict[str, Any]:
    """Run the campaign and write the dataset; returns the campaign's result and summary."""
    result, summary = run_simulate(**settings.call_args())
    # only when asked (the DVC stage)
    # the headline; every figure of METRICS_KEYS in its details file (details_path)
    write_metrics(
        settings.metrics_file, {k: summary[k] for k in METRICS_KEYS}, "simulate", details=True
    )
    return {"result": result, "summary": summary, "out": str(settings.out_dir)}


def describe(figures: Mapping[str, Any]) -> list[str]:
    result, summary = figures["result"], figures["summary"]
    cpu = summary["cpu_seconds_per_configuration"]
    lines = [
        f"FE campaign: {result.n_jobs} jobs ({summary['n_configurations']} configurations x 4 "
        f"load cases), {result.n_skipped} already in {result.store}, {result.n_run} run now on "
        f"{result.n_workers or 0} workers in {result.wall_seconds:.1f} s",
        f"failure rate {summary['failure_rate']:.3f} ({summary['n_failed']} failed); CPU "
        f"seconds per configuration: mean {cpu['mean']:.2f}, max {cpu['max']:.2f}; solver "
        f"{', '.join(summary['solver_versions'])}",
    ]
    for cause, n in summary["failure_reasons"].items():
        lines.append(f"  failed: {n} x {cause}")
    for f in summary["failures"][:MAX_FAILURES_LISTED]:
        lines.append(
            f"  failed: config {f['config_id']} ({f['split']} row {f['row']}) {f['load_case']}: "
            f"{f['reason']}"
        )
    if len(summary["failures"]) > MAX_FAILURES_LISTED:
        lines.append(
            f"  ... and {len(summary['failures']) - MAX_FAILURES_LISTED} more failed jobs "
            "(all of them: runs.csv and campaign.json)"
        )
    lines.append(f"dataset: {figures['out']} (the study's layout; runs.csv, campaign.json)")
    return lines


def run_simulate(
    *,
    fe: FeRuntime,
    bounds: Any,
    splits: Mapping[str, int],
    seed: int,
    batches: Sequence[int | Mapping[str, Any]],
    load_cases: Sequence[str],
    moments: Sequence[float],
    out_dir: Path,
    scratch_dir: Path | None = None,
    retry_timeouts: bool = False,
):
    """The FE campaign (Dask, durable store, resume) and its dataset in the study's layout.

    ``fe`` names the solver, its settings, the campaign store and the Dask cluster.
    ``retry_timeouts`` runs the stored jobs that failed on their time limit again (a record
    made under a wall-clock limit depends on the machine's load; the other failures are the
    model's and stay).

    Returns
    -------
    result : CampaignResult
    summary : dict
        The dataset's ``campaign.json`` (counts, failure rate and reasons, CPU seconds per
        configuration, solver version, wall seconds, workers).

    ``out_dir`` is all or nothing (:func:`femcal.fe.dataset.write_dataset`), and checked
    before the campaign runs.
    """
    from femcal.outputs import check_destination

    check_destination(out_dir)
    from femcal.errors import ConfigError
    from femcal.fe.campaign import timed_out
    from femcal.fe.dataset import write_dataset
    from femcal.fe.design import split_design
    from femcal.fe.store import settings_hash
    from femcal.schema import LOAD_CASES

    if sorted(load_cases) != sorted(LOAD_CASES):
        raise ConfigError(
            f"fe.load_cases is {list(load_cases)}; a dataset in the study's layout needs all "
            f"four load cases {list(LOAD_CASES)}."
        )
    space = fe_space(bounds)
    design_df = split_design(space, splits, seed, batches)
    result = fe.campaign(
        design_df,
        names=space.names,
        load_cases=LOAD_CASES,
        moments=moments,
        scratch_dir=scratch_dir,
        retry_failed=timed_out if retry_timeouts else False,
    )
    summary = write_dataset(
        design_df,
        result.records.to_dict(orient="records"),
        out_dir,
        space=space,
        moments=moments,
        campaign_info={
            "solver": fe.solver,
            "settings": dict(fe.settings),
            "settings_hash": settings_hash(fe.solver, fe.settings),
            "seed": int(seed),
            "splits": {k: int(v) for k, v in splits.items()},
            "batches": list(batches),
            "store": str(fe.store),
        },
    )
    return result, summary
