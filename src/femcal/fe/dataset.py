"""A campaign's results as a dataset in the study's own file layout.

:func:`write_dataset` writes one folder per split (``Large/``, ``Small/``, ``Test/``) with the
study's file names (:data:`femcal.prepare.SPLITS`: the names are the study's, e.g.
``MaterialConfigurations_Small_128.csv`` whatever the number of configurations), so
:func:`femcal.prepare.read_split` and ``femcal prepare`` read it unchanged:

* ``MaterialConfigurations*.csv``: row i = configuration i of the split, 13 columns;
* ``ParameterBounds.csv``: the sampling box (row 1 minimum, row 2 maximum);
* ``ROM_Results_<LC>_<sfx>wMoment.csv`` and ``IDP_Results_...``: header ``0.0,1.0,...`` (the
  applied moments in Nm, with the unloaded 0 Nm column, value 0.0), row i = configuration i.
  A failed run keeps the values of the levels it reached and leaves the rest of its row
  empty: ``prepare`` marks those rows ``failed`` with NaN outputs. Nothing is written as zero.

Beside the splits: ``design.csv`` (config_id, split, row in the split, parameters),
``runs.csv`` (one row per job: status, reason, solver version, deck hash, attempts, CPU
seconds, worker) and ``campaign.json`` (counts, failure rate, every failure's reason, CPU
seconds per configuration, solver versions, settings).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import InputDataError
from femcal.outputs import OutputStage
from femcal.prepare import BOUNDS_FILE, SPLITS
from femcal.schema import LOAD_CASES, STATUS_FAILED, STATUS_OK
from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

RUNS_FILE = "runs.csv"
SUMMARY_FILE = "campaign.json"
DESIGN_FILE = "design.csv"


def _num(value: float) -> str:
    """A float as text that reads back exactly."""
    return repr(float(value))


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
    lines = [",".join(header)] + [",".join(row) for row in rows]
    path.write_text("\n".join(lines) + "\n")


def _reached(rom: Sequence[Any]) -> tuple[int, str]:
    """Levels reached: the leading run of positive finite RoM values, and why it stops."""
    for j, v in enumerate(rom):
        if v is None or not math.isfinite(float(v)):
            return j, ""
        if float(v) <= 0.0:
            return j, f"non-positive RoM {float(v)!r} at level {j + 1}"
    return len(rom), ""


def _curve_cells(values: Sequence[Any], n_reached: int, m: int) -> list[str]:
    """``0.0`` for the unloaded state, the reached values, then empty cells (not reached)."""
    cells = ["0.0"]
    for j in range(m):
        v = values[j] if j < len(values) else None
        ok = j < n_reached and v is not None and math.isfinite(float(v))
        cells.append(_num(v) if ok else "")
        if not ok:
            n_reached = j  # a gap ends the curve: later cells stay empty
    return cells


def write_dataset(
    design_df: pd.DataFrame,
    records: Sequence[Mapping[str, Any]],
    out_dir: str | Path,
    *,
    space: ParameterSpace,
    moments: Sequence[float],
    campaign_info: Mapping[str, Any] | None = None,
    allow_missing: bool = False,
) -> dict[str, Any]:
    """Write a campaign as a dataset in the study's layout (see the module docstring).

    Parameters
    ----------
    design_df : pandas.DataFrame, shape (n, 1 + d) or (n, 2 + d)
        ``config_id``, optional ``split`` (``large``/``small``/``test``; default ``large``)
        and the parameters ``space.names``.
    records : sequence of mapping
        Store records (:mod:`femcal.fe.campaign`) of the design's jobs under the four
        pure-moment load cases at ``moments``.
    out_dir : str or Path
        The dataset folder, all or nothing (:mod:`femcal.outputs`): written beside it, then
        moved into place; an earlier dataset femcal wrote there is moved aside, a folder
        holding other files is refused (:class:`~femcal.errors.OutputFolderError`).
    space : ParameterSpace
        The sampling box (``ParameterBounds.csv``).
    moments : sequence of float, length m
        Levels (Nm) of the jobs.
    campaign_info : mapping, optional
        Extra entries for ``campaign.json`` (seed, wall seconds, workers, settings ...).
    allow_missing : bool, optional
        Write jobs that are not in the store as empty rows (status ``missing`` in
        ``runs.csv``) instead of raising.

    Returns
    -------
    dict
        The content of ``campaign.json``.

    Raises
    ------
    InputDataError
        A job of the design has no record (and not ``allow_missing``), or a record's levels
        differ from ``moments``.
    """
    out_dir = Path(out_dir)
    moments = [float(m) for m in moments]
    df = design_df.copy()
    if "split" not in df.columns:
        df["split"] = "large"
    unknown = sorted(set(df["split"]) - set(SPLITS))
    if unknown:
        raise InputDataError(f"The design names unknown splits {unknown}; use {sorted(SPLITS)}.")
    by_job = {(int(r["config_id"]), str(r["load_case"])): r for r in records}
    stage = OutputStage(out_dir, command="simulate").open()
    tmp = stage.path
    runs: list[dict[str, Any]] = []
    design_rows: list[dict[str, Any]] = []
    try:
        for split in SPLITS:
            part = df[df["split"] == split].sort_values("config_id").reset_index(drop=True)
            if part.empty:
                continue
            _write_split(tmp, split, part, space, moments, by_job, allow_missing, runs)
            for i, cid in enumerate(part["config_id"].astype(int)):
                design_rows.append({"config_id": cid, "split": split, "row": i})
        summary = _write_tables(tmp, df, design_rows, runs, space, moments, campaign_info)
        stage.commit()
    except BaseException:
        stage.discard()
        raise
    logger.info(
        "FE dataset %s: %d configurations, %d jobs, %d failed.",
        out_dir,
        summary["n_configurations"],
        summary["n_jobs"],
        summary["n_failed"],
    )
    return summary


def _write_split(
    tmp: Path,
    split: str,
    part: pd.DataFrame,
    space: ParameterSpace,
    moments: Sequence[float],
    by_job: Mapping[tuple[int, str], Mapping[str, Any]],
    allow_missing: bool,
    runs: list[dict[str, Any]],
) -> None:
    """Write one split's folder in the study's layout; append its jobs to ``runs``.

    ``part`` holds the split's configurations in ``config_id`` order (row i of every file).
    """
    layout = SPLITS[split]
    folder = tmp / layout.folder
    folder.mkdir()
    _write_csv(
        folder / BOUNDS_FILE,
        list(space.names),
        [[_num(v) for v in space.lower], [_num(v) for v in space.upper]],
    )
    x = part[list(space.names)].to_numpy(dtype=float)
    _write_csv(
        folder / layout.configurations,
        list(space.names),
        [[_num(v) for v in row] for row in x],
    )
    for lc in LOAD_CASES:
        rom_rows, idp_rows = [], []
        for i, cid in enumerate(part["config_id"].astype(int)):
            rec = by_job.get((cid, lc))
            run = {"config_id": cid, "split": split, "row": i, "load_case": lc}
            if rec is None:
                if not allow_missing:
                    raise InputDataError(
                        f"Configuration {cid} ({split} row {i}), load case {lc}: no "
                        "result in the campaign store. Rerun the campaign (`femcal "
                        "simulate` resumes) before writing the dataset."
                    )
                rom_rows.append(["0.0"] + [""] * len(moments))
                idp_rows.append(["0.0"] + [""] * len(moments))
                runs.append({**run, "status": "missing", "levels_reached": 0})
                continue
            rom, idp, info = _job_cells(rec, cid, lc, moments)
            rom_rows.append(rom)
            idp_rows.append(idp)
            runs.append({**run, **info})
        header = ["0.0"] + [_num(v) for v in moments]
        _write_csv(folder / layout.results("ROM", lc), header, rom_rows)
        _write_csv(folder / layout.results("IDP", lc), header, idp_rows)


def _job_cells(
    rec: Mapping[str, Any], cid: int, lc: str, moments: Sequence[float]
) -> tuple[list[str], list[str], dict[str, Any]]:
    """One stored job's RoM and IDP cells (:func:`_curve_cells`) and its ``runs.csv`` entries.

    A run that stops short of the last level is failed, whatever its stored status.
    """
    m = len(moments)
    levels = [float(v) for v in rec.get("levels", [])]
    if not np.allclose(levels, moments):
        raise InputDataError(
            f"Configuration {cid}, load case {lc}: the stored run has levels "
            f"{levels}, the dataset asks for {moments}. Use the moments of "
            "the campaign (fe.moments), or rerun it."
        )
    rom = list(rec.get("rom_deg") or [])
    n_reached, why = _reached(rom)
    status, reason = str(rec.get("status")), str(rec.get("reason") or "")
    if n_reached < m and status == STATUS_OK:
        status = STATUS_FAILED
        reason = why or f"no RoM from level {n_reached + 1} on"
        logger.warning("Configuration %d, %s: %s.", cid, lc, reason)
    info = {
        "status": status,
        "reason": reason,
        "levels_reached": n_reached,
        "solver": rec.get("solver", ""),
        "solver_version": rec.get("solver_version", ""),
        "deck_hash": rec.get("deck_hash", ""),
        "attempts": rec.get("attempts"),
        "cpu_seconds": rec.get("cpu_seconds"),
        "worker_cpu_seconds": rec.get("worker_cpu_seconds"),
        "wall_seconds": rec.get("wall_seconds"),
        "worker": rec.get("worker", ""),
        "host": rec.get("host", ""),
        "campaign_run": rec.get("campaign_run", ""),
        "started_at": rec.get("started_at"),
        "finished_at": rec.get("finished_at"),
    }
    idp = _curve_cells(list(rec.get("idp_mpa") or []), n_reached, m)
    return _curve_cells(rom, n_reached, m), idp, info


def _write_tables(
    tmp: Path,
    df: pd.DataFrame,
    design_rows: Sequence[Mapping[str, Any]],
    runs: Sequence[Mapping[str, Any]],
    space: ParameterSpace,
    moments: Sequence[float],
    campaign_info: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """Write ``design.csv``, ``runs.csv`` and ``campaign.json`` beside the splits; return the
    content of ``campaign.json``."""
    design_out = df.merge(pd.DataFrame(design_rows), on=["config_id", "split"], how="left")
    design_out = design_out[["config_id", "split", "row", *space.names]]
    design_out.to_csv(tmp / DESIGN_FILE, index=False)
    runs_df = pd.DataFrame(runs)
    for col in ("reason", "solver", "solver_version", "deck_hash", "worker", "host"):
        if col not in runs_df.columns:
            runs_df[col] = ""
    runs_df = runs_df.sort_values(["config_id", "load_case"]).reset_index(drop=True)
    runs_df.to_csv(tmp / RUNS_FILE, index=False)
    summary = summarize_runs(runs_df, moments=moments, extra=campaign_info)
    (tmp / SUMMARY_FILE).write_text(json.dumps(summary, indent=2, default=str) + "\n")
    return summary


def _campaign_wall(stored: pd.DataFrame) -> dict[str, Any]:
    """Wall seconds per run of the campaign (its records' first start to last end)."""
    cols = ("campaign_run", "started_at", "finished_at")
    if any(c not in stored.columns for c in cols):
        return {"campaign_wall_seconds": float("nan"), "campaign_runs": []}
    df = stored.assign(
        started_at=pd.to_numeric(stored["started_at"], errors="coerce"),
        finished_at=pd.to_numeric(stored["finished_at"], errors="coerce"),
    ).dropna(subset=["started_at", "finished_at"])
    runs = [
        {
            "campaign_run": str(run),
            "jobs": int(len(g)),
            "workers": int(g["worker"].nunique()) if "worker" in g else 0,
            "wall_seconds": float(g["finished_at"].max() - g["started_at"].min()),
        }
        for run, g in df.groupby(df["campaign_run"].astype(str), sort=False)
    ]
    runs.sort(key=lambda r: -r["jobs"])
    return {
        "campaign_wall_seconds": float(sum(r["wall_seconds"] for r in runs))
        if runs
        else float("nan"),
        "campaign_runs": runs,
    }


def summarize_runs(
    runs: pd.DataFrame, *, moments: Sequence[float], extra: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Campaign figures from a ``runs.csv`` table.

    Returns
    -------
    dict
        ``n_configurations`` (total and per split), ``n_jobs``, ``n_ok``, ``n_failed``,
        ``n_missing``, ``failure_rate`` (failed / stored jobs), ``failures`` (config, split,
        row, load case, levels reached, reason), ``failure_reasons`` (cause -> count, the
        solver's message without exit code, levels and attempt), ``failed_levels_reached``
        (median and min over failed jobs, of ``n_of`` levels), CPU seconds per
        configuration (mean, median, min, max, total), solver versions, ``moments`` (the
        levels simulated, Nm), ``campaign_wall_seconds`` (what the campaign took: over the
        runs of ``femcal simulate`` that produced the records, a resumed campaign's pauses
        left out, each run from its first job's start to its last job's end),
        ``campaign_runs`` (their number and workers each), ``extra``.
    """
    status = runs["status"].astype(str)
    stored = runs[status != "missing"]
    failed = runs[status == STATUS_FAILED]
    cpu = pd.to_numeric(stored["cpu_seconds"], errors="coerce").groupby(stored["config_id"]).sum()
    # The cause without its details (exit code, levels reached, attempt), so that one abort
    # counts once whatever level it stopped at.
    causes = failed["reason"].fillna("").astype(str).str.replace(r"\s*\(.*\)\s*$", "", regex=True)
    reasons = causes.value_counts()
    reached = pd.to_numeric(failed["levels_reached"], errors="coerce")
    out: dict[str, Any] = {
        "n_configurations": int(runs["config_id"].nunique()),
        "n_configurations_per_split": {
            str(k): int(v) for k, v in runs.groupby("split")["config_id"].nunique().items()
        },
        "n_jobs": int(len(runs)),
        "n_ok": int((status == STATUS_OK).sum()),
        "n_failed": int(len(failed)),
        "n_missing": int((status == "missing").sum()),
        "failure_rate": float(len(failed) / len(stored)) if len(stored) else float("nan"),
        "failures": [
            {
                "config_id": int(r.config_id),
                "split": str(r.split),
                "row": int(r.row),
                "load_case": str(r.load_case),
                "levels_reached": int(r.levels_reached),
                "reason": str(r.reason),
            }
            for r in failed.itertuples()
        ],
        "failure_reasons": {str(k): int(v) for k, v in reasons.items()},
        "failed_levels_reached": {
            "median": float(reached.median()) if len(reached) else float("nan"),
            "min": float(reached.min()) if len(reached) else float("nan"),
            "n_of": len(moments),
        },
        "cpu_seconds_per_configuration": {
            "mean": float(cpu.mean()) if len(cpu) else float("nan"),
            "median": float(cpu.median()) if len(cpu) else float("nan"),
            "min": float(cpu.min()) if len(cpu) else float("nan"),
            "max": float(cpu.max()) if len(cpu) else float("nan"),
        },
        "cpu_seconds_total": float(cpu.sum()),
        "solver_versions": sorted(
            {str(v) for v in stored.get("solver_version", pd.Series(dtype=str)).dropna()}
        ),
        "moments": [float(v) for v in moments],
        **_campaign_wall(stored),
    }
    if extra:
        out.update({str(k): v for k, v in extra.items()})
    return out
