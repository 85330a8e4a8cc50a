"""The study's step 4: FE re-simulation of calibrated parameters.

A calibration fits the surrogate, so its error is the error *through the surrogate*. Here the
calibrated parameters of every specimen go back into the FE model:

* the four pure-moment load cases at the measured moments give the honest, FE-evaluated
  calibration error against the measurement (per specimen and per load case), reported
  beside the surrogate-evaluated error of the calibration and the FE-vs-surrogate gap;
* axial compression at the validation forces (100, 300, 1000, 2000 N) gives the intradiscal
  pressure (a quantity the calibration never saw), compared with published in vitro ranges
  at a force and with published in vivo values through the force at which each disc reaches
  them (:mod:`femcal.fe.idp`); the IDP head, when given, is compared with FE's pressures
  under the moments.

With a surrogate and ``max_fe_runs > 1``, the calibration is first refined with FE in the
loop (:func:`femcal.fe.refine.refine_with_fe`) until FE confirms each fit or the budget of FE
runs is spent; the refined parameters are then validated as above (their moment runs come
back from the store), and the tables say what refinement did per specimen.

The FE runs go through :func:`femcal.fe.campaign.run_campaign` (Dask, durable store, resume).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError
from femcal.fe.base import COMPRESSION
from femcal.fe.campaign import CampaignResult
from femcal.fe.idp import (
    IDP_HEAD_CSV,
    IDP_PUBLISHED_CSV,
    idp_head_error,
    published_table,
)
from femcal.fe.options import ValidateOptions
from femcal.fe.runtime import FeRuntime
from femcal.schema import LOAD_CASES, PARAMETER_NAMES, STATUS_OK

logger = logging.getLogger(__name__)

VALIDATION_CSV = "validation.csv"
VALIDATION_JSON = "validation.json"
CURVES_CSV = "fe_curves.csv"
IDP_CSV = "idp.csv"
REFINE_CSV = "refine.csv"
REFINE_HISTORY_CSV = "refine_history.csv"


@dataclass(frozen=True)
class LiteratureRange:
    """IDP measured in vitro under one axial compressive force.

    Attributes
    ----------
    force_n : float
    low_mpa, mean_mpa, high_mpa : float
        Minimum, mean and maximum of the reported measurements.
    """

    force_n: float
    low_mpa: float
    mean_mpa: float
    high_mpa: float

    def contains(self, idp_mpa: np.ndarray) -> np.ndarray:
        """Whether each value lies in ``[low_mpa, high_mpa]``, shape (...) -> (...)."""
        v = np.asarray(idp_mpa, dtype=float)
        return (v >= self.low_mpa) & (v <= self.high_mpa)


def literature_ranges(settings: Mapping[Any, Any]) -> list[LiteratureRange]:
    """Parse ``validate.idp_literature`` (force in N -> {low, mean, high} in MPa).

    Raises
    ------
    ConfigError
        A force or a bound is not a number, or low <= mean <= high is violated.
    """
    out = []
    for force, entry in settings.items():
        try:
            f = float(force)
            low, mean, high = (float(entry[k]) for k in ("low", "mean", "high"))
        except (TypeError, ValueError, KeyError):
            raise ConfigError(
                f"validate.idp_literature: entry {force!r}: {entry!r} must be a force in N "
                "mapping to {low, mean, high} in MPa, e.g. 1000: {low: 0.5, mean: 0.8, "
                "high: 1.2}."
            ) from None
        if not (f > 0 and low <= mean <= high):
            raise ConfigError(
                f"validate.idp_literature: at {force} N need force > 0 and low <= mean <= high; "
                f"got low={low}, mean={mean}, high={high}."
            )
        out.append(LiteratureRange(f, low, mean, high))
    return sorted(out, key=lambda r: r.force_n)


@dataclass
class ValidationResult:
    """Per-specimen table, aggregate figures, and the campaign that ran the FE jobs.

    ``refine`` is the FE-in-the-loop refinement that came first (None without one).
    """

    table: pd.DataFrame
    summary: dict[str, Any]
    curves: pd.DataFrame
    idp: pd.DataFrame
    campaign: CampaignResult
    refine: Any = None


def _read_parameters(path: Path) -> pd.DataFrame:
    if not path.is_file():
        raise InputDataError(
            f"Calibrated parameters {path} do not exist; run the calibrate stage first (it "
            "writes parameters.csv) or give the right --calibration folder."
        )
    df = pd.read_csv(path, dtype={"specimen": str}, float_precision="round_trip")
    lacking = [c for c in ("specimen", *PARAMETER_NAMES) if c not in df.columns]
    if lacking:
        raise InputDataError(
            f"{path}: missing columns {lacking}; a calibration's parameters.csv holds "
            "'specimen' and the 13 material parameters."
        )
    return df


def _surrogate_curves(path: Path, specimens: Sequence[str], moments: np.ndarray) -> np.ndarray:
    """``calibrated_rom_deg`` of a calibration's curves.csv as (n, 4, m); NaN where absent."""
    out = np.full((len(specimens), len(LOAD_CASES), moments.size), np.nan)
    if not path.is_file():
        logger.warning("%s not found: the surrogate-evaluated error is not reported.", path)
        return out
    df = pd.read_csv(path, dtype={"specimen": str})
    index = {s: i for i, s in enumerate(specimens)}
    lci = {lc: k for k, lc in enumerate(LOAD_CASES)}
    for row in df.itertuples(index=False):
        i = index.get(str(row.specimen))
        k = lci.get(str(row.load_case))
        j = np.flatnonzero(np.isclose(moments, float(row.moment_nm)))
        if i is not None and k is not None and j.size:
            out[i, k, j[0]] = float(row.calibrated_rom_deg)
    return out


def _mae(a: np.ndarray, b: np.ndarray, axis: Any) -> np.ndarray:
    diff = np.abs(a - b)
    count = np.sum(np.isfinite(diff), axis=axis)
    total = np.nansum(diff, axis=axis)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def validate_calibration(
    calibration_dir: str | Path,
    measurements: str | Path,
    fe: FeRuntime,
    out_dir: str | Path,
    options: ValidateOptions | None = None,
    *,
    surrogate: Any = None,
    idp_head: Any = None,
    **overrides: Any,
) -> ValidationResult:
    """Re-simulate a calibration's parameters with the FE model; write the validation tables.

    Parameters
    ----------
    calibration_dir : str or Path
        Output folder of ``femcal calibrate`` (``parameters.csv``, ``curves.csv``).
    measurements : str or Path
        The measurements it was calibrated to (any layout of ``femcal calibrate``).
    fe : FeRuntime
        The FE solver, its settings, the campaign store of the validation runs (resumable)
        and the Dask cluster (as for ``femcal simulate``).
    out_dir : str or Path
        Receives ``validation.csv``, ``validation.json``, ``fe_curves.csv``, ``idp.csv``.
    options : ValidateOptions, optional
        The IDP check's forces and published pressures, and the refinement's budget (default:
        :class:`~femcal.fe.options.ValidateOptions`'s).
    surrogate : object, optional
        A fitted femcal surrogate (the one calibrated with); with ``max_fe_runs > 1`` it steers
        the FE-in-the-loop refinement (:func:`femcal.fe.refine.refine_with_fe`) that comes first,
        and ``refine.csv`` (per specimen: FE error before and after, FE runs, parameters
        before and after) and ``refine_history.csv`` (per FE run) join the tables.
    idp_head : surrogate, optional
        The IDP head (a surrogate of the pressure, ``train.<split>.target: idp_mpa``): its
        pressures at the validated parameters against FE's under the moments go to
        ``idp_head.csv`` and the summary's ``idp_head``.
    **overrides
        Fields of :class:`~femcal.fe.options.ValidateOptions` replacing those of ``options``.

    Returns
    -------
    ValidationResult
        ``table``: one row per specimen (``specimen``, ``fe_mae_deg``,
        ``surrogate_mae_deg``, ``fe_vs_surrogate_mae_deg``, per-load-case columns,
        ``idp_mpa_<F>N`` and ``idp_in_range_<F>N``, ``fe_failed``).

    Raises
    ------
    InputDataError
        The calibration's parameters are missing, or name specimens the measurements lack.
    ConfigError
        Refinement (``max_fe_runs > 1``) without the surrogate that steers it.
    """
    o = dataclasses.replace(options or ValidateOptions(), **overrides)
    calibration_dir, out_dir = Path(calibration_dir), Path(out_dir)
    params, meas, measured = _calibration(calibration_dir, measurements)
    specimens = list(params["specimen"])
    calibrated = _surrogate_curves(calibration_dir / "curves.csv", specimens, meas.moments)
    forces = sorted(float(f) for f in o.forces)
    refined = None
    if o.max_fe_runs > 1:
        refined = _refine(surrogate, meas.moments, measured, params, specimens, fe, o)
        params = params.copy()
        params[list(PARAMETER_NAMES)] = refined.x
        calibrated = np.where(np.isfinite(measured), refined.surrogate_curves, np.nan)

    design_df = params[list(PARAMETER_NAMES)].copy()
    design_df.insert(0, "config_id", np.arange(len(specimens), dtype=np.int64))
    campaign = fe.campaign(
        design_df,
        load_cases=(*LOAD_CASES, COMPRESSION) if forces else LOAD_CASES,
        moments=meas.moments.tolist(),
        forces=forces,
    )
    runs = _FeRuns.of(campaign, len(specimens), meas.moments.size, len(forces))
    ranges = {r.force_n: r for r in o.literature}
    table = _table(specimens, measured, calibrated, runs, forces, ranges)
    curves = _curves(specimens, meas.moments, measured, calibrated, runs.rom_deg)
    idp_df = _idp_table(specimens, forces, ranges, runs.idp)
    published_df, published_summary = published_table(specimens, forces, runs.idp, o.published)
    head_df, head_summary = None, None
    if idp_head is not None:
        head_df, head_summary = idp_head_error(
            idp_head,
            specimens,
            params[list(PARAMETER_NAMES)].to_numpy(float),
            meas.moments,
            runs.moment_idp,
        )
    summary: dict[str, Any] = {
        **_summary(table, refined, forces, ranges, runs.idp),
        "idp_published": published_summary,
        "idp_head": head_summary,
        "n_fe_failed_jobs": int((campaign.records["status"] != STATUS_OK).sum()),
        "fe_failures": campaign.failures().to_dict(orient="records"),
        "fe_cpu_seconds_total": float(campaign.records["cpu_seconds"].sum()),
        "solver": fe.solver,
        "solver_versions": sorted(set(campaign.records["solver_version"].astype(str))),
        "settings": dict(fe.settings),
        "calibration_dir": str(calibration_dir),
        "measurements": str(measurements),
    }
    tables = {VALIDATION_CSV: table, CURVES_CSV: curves, IDP_CSV: idp_df}
    if o.published:
        tables[IDP_PUBLISHED_CSV] = published_df
    if head_df is not None:
        tables[IDP_HEAD_CSV] = head_df
    if refined is not None:
        tables[REFINE_CSV] = refined.table()
        tables[REFINE_HISTORY_CSV] = refined.history
    _write(out_dir, tables, summary)
    return ValidationResult(table, summary, curves, idp_df, campaign, refined)


def _calibration(
    calibration_dir: Path, measurements: str | Path
) -> tuple[pd.DataFrame, Any, np.ndarray]:
    """The calibrated parameters (``parameters.csv``), the measurements they were calibrated
    to, and each calibrated specimen's measured curves (n, 4, m) in degrees."""
    from femcal.measurements import read_measurements

    params = _read_parameters(calibration_dir / "parameters.csv")
    meas = read_measurements(measurements)
    index = {s: i for i, s in enumerate(meas.specimens)}
    unknown = [s for s in params["specimen"] if s not in index]
    if unknown:
        raise InputDataError(
            f"{calibration_dir / 'parameters.csv'}: specimens {unknown[:5]} are not in the "
            f"measurements {measurements}; give the measurements this calibration was run on."
        )
    measured = meas.rom_deg[[index[s] for s in params["specimen"]]]  # (n, 4, m)
    return params, meas, measured


def _write(out_dir: Path, tables: Mapping[str, pd.DataFrame], summary: Mapping[str, Any]) -> None:
    """Write the tables (file name -> table) and ``validation.json`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, table in tables.items():
        table.to_csv(out_dir / name, index=False)
    (out_dir / VALIDATION_JSON).write_text(
        json.dumps(json_safe(summary), indent=2, default=str) + "\n"
    )


def _refine(
    surrogate: Any,
    moments: np.ndarray,
    measured: np.ndarray,
    params: pd.DataFrame,
    specimens: Sequence[str],
    fe: FeRuntime,
    o: ValidateOptions,
) -> Any:
    """The FE-in-the-loop refinement of the calibrated ``params`` (a
    :class:`~femcal.fe.refine.RefineResult`), steered by ``surrogate``."""
    if surrogate is None:
        raise ConfigError(
            f"FE-in-the-loop refinement (max_fe_runs={o.max_fe_runs}) needs the surrogate "
            "that steers it; give validate.refine.model_uri, or max_fe_runs: 1."
        )
    from femcal.calibration import SurrogateCurveModel
    from femcal.fe.refine import refine_with_fe

    return refine_with_fe(
        SurrogateCurveModel(surrogate, moments),
        measured,
        params[list(PARAMETER_NAMES)].to_numpy(dtype=float),
        fe.curves(moments.tolist()),
        specimens=specimens,
        max_fe_runs=o.max_fe_runs,
        tol_deg=o.tol_deg,
    )


@dataclass(frozen=True)
class _FeRuns:
    """A validation campaign's outputs per specimen, NaN where FE gave none.

    Attributes
    ----------
    rom_deg : ndarray, shape (n, 4, m)
        RoM under the moments, degrees.
    moment_idp : ndarray, shape (n, 4, m)
        The intradiscal pressure under the moments, MPa.
    idp : ndarray, shape (n, n_forces)
        The intradiscal pressure under axial compression, MPa.
    failed : list of list of str
        Per specimen, ``"<load case>: <reason>"`` of each failed job.
    """

    rom_deg: np.ndarray
    moment_idp: np.ndarray
    idp: np.ndarray
    failed: list[list[str]]

    @classmethod
    def of(cls, campaign: CampaignResult, n: int, m: int, n_forces: int) -> _FeRuns:
        """Gather the records of ``campaign`` (config_id = specimen position)."""
        fe = np.full((n, len(LOAD_CASES), m), np.nan)
        fe_idp = np.full((n, len(LOAD_CASES), m), np.nan)  # the pressure under the moments
        idp = np.full((n, n_forces), np.nan)
        failed: list[list[str]] = [[] for _ in range(n)]
        for rec in campaign.records.itertuples(index=False):
            i = int(rec.config_id)
            values = np.array([np.nan if v is None else float(v) for v in rec.rom_deg])
            if rec.status != STATUS_OK:
                failed[i].append(f"{rec.load_case}: {rec.reason}")
            if rec.load_case == COMPRESSION:
                idp[i] = [np.nan if v is None else float(v) for v in rec.idp_mpa]
            else:
                fe[i, LOAD_CASES.index(rec.load_case)] = values
                fe_idp[i, LOAD_CASES.index(rec.load_case)] = [
                    np.nan if v is None else float(v) for v in rec.idp_mpa
                ]
        return cls(fe, fe_idp, idp, failed)


def _table(
    specimens: Sequence[str],
    measured: np.ndarray,
    calibrated: np.ndarray,
    runs: _FeRuns,
    forces: Sequence[float],
    ranges: Mapping[float, LiteratureRange],
) -> pd.DataFrame:
    """One row per specimen: FE's and the surrogate's errors, the IDP and its verdicts."""
    fe, idp = runs.rom_deg, runs.idp
    common = np.isfinite(measured) & np.isfinite(fe)
    meas_c = np.where(common, measured, np.nan)
    table = pd.DataFrame({"specimen": specimens})
    table["fe_mae_deg"] = _mae(fe, meas_c, axis=(1, 2))
    table["surrogate_mae_deg"] = _mae(calibrated, meas_c, axis=(1, 2))
    table["surrogate_mae_deg_all_points"] = _mae(calibrated, measured, axis=(1, 2))
    table["fe_vs_surrogate_mae_deg"] = _mae(fe, np.where(common, calibrated, np.nan), axis=(1, 2))
    for k, lc in enumerate(LOAD_CASES):
        table[f"fe_mae_deg_{lc}"] = _mae(fe[:, k], meas_c[:, k], axis=1)
        table[f"surrogate_mae_deg_{lc}"] = _mae(calibrated[:, k], meas_c[:, k], axis=1)
    table["n_points"] = np.isfinite(measured).sum(axis=(1, 2))
    table["n_points_fe"] = common.sum(axis=(1, 2))
    for j, f in enumerate(forces):
        table[f"idp_mpa_{f:g}N"] = idp[:, j]
        if f in ranges:
            inside = ranges[f].contains(idp[:, j])
            table[f"idp_in_range_{f:g}N"] = np.where(np.isfinite(idp[:, j]), inside, False)
    table["fe_failed"] = ["; ".join(x) for x in runs.failed]
    return table


def _curves(
    specimens: Sequence[str],
    moments: np.ndarray,
    measured: np.ndarray,
    calibrated: np.ndarray,
    fe: np.ndarray,
) -> pd.DataFrame:
    """Measured, surrogate and FE RoM at every measured point (``fe_curves.csv``)."""
    n, m = len(specimens), moments.size
    spec, lc_i, mom = np.meshgrid(
        np.arange(n), np.arange(len(LOAD_CASES)), np.arange(m), indexing="ij"
    )
    curves = pd.DataFrame(
        {
            "specimen": np.asarray(specimens, dtype=object)[spec.reshape(-1)],
            "load_case": np.asarray(LOAD_CASES, dtype=object)[lc_i.reshape(-1)],
            "moment_nm": moments[mom.reshape(-1)],
            "measured_rom_deg": measured.reshape(-1),
            "surrogate_rom_deg": calibrated.reshape(-1),
            "fe_rom_deg": fe.reshape(-1),
        }
    )
    return curves[np.isfinite(curves["measured_rom_deg"])].reset_index(drop=True)


def _idp_table(
    specimens: Sequence[str],
    forces: Sequence[float],
    ranges: Mapping[float, LiteratureRange],
    idp: np.ndarray,
) -> pd.DataFrame:
    """One row per force and specimen: FE's IDP and the literature range (``idp.csv``)."""
    idp_rows = []
    for j, f in enumerate(forces):
        r = ranges.get(f)
        for i, s in enumerate(specimens):
            idp_rows.append(
                {
                    "specimen": s,
                    "force_n": f,
                    "idp_mpa": idp[i, j],
                    "literature_low_mpa": r.low_mpa if r else np.nan,
                    "literature_mean_mpa": r.mean_mpa if r else np.nan,
                    "literature_high_mpa": r.high_mpa if r else np.nan,
                    "in_range": bool(r.contains(idp[i, j])) if r else None,
                }
            )
    return pd.DataFrame(idp_rows)


def _summary(
    table: pd.DataFrame,
    refined: Any,
    forces: Sequence[float],
    ranges: Mapping[float, LiteratureRange],
    idp: np.ndarray,
) -> dict[str, Any]:
    """The summary's errors, refinement figures and IDP per force, from the table."""

    def mean(col: str) -> float:
        v = table[col].to_numpy(dtype=float)
        return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")

    return {
        "n_specimens": len(table),
        "fe_mae_deg": mean("fe_mae_deg"),
        # in-sample: FE at the parameters fitted (and refined, when there was refinement) to
        # the very curves scored
        "fe_fit_residual_deg": mean("fe_mae_deg"),
        "fe_fit_residual_deg_before_refine": (
            mean("fe_mae_deg") if refined is None else float(np.nanmean(refined.fe_mae_start))
        ),
        "fe_runs_per_specimen_max": 1 if refined is None else int(refined.fe_runs.max()),
        "fe_runs_per_specimen_mean": 1.0 if refined is None else float(refined.fe_runs.mean()),
        "refine": None if refined is None else refined.summary(),
        "surrogate_mae_deg": mean("surrogate_mae_deg"),
        "fe_vs_surrogate_mae_deg": mean("fe_vs_surrogate_mae_deg"),
        "fe_mae_deg_per_load_case": {lc: mean(f"fe_mae_deg_{lc}") for lc in LOAD_CASES},
        "surrogate_mae_deg_per_load_case": {
            lc: mean(f"surrogate_mae_deg_{lc}") for lc in LOAD_CASES
        },
        "n_points": int(table["n_points"].sum()),
        "n_points_fe": int(table["n_points_fe"].sum()),
        "idp": [_idp_summary(f, idp[:, j], ranges.get(f)) for j, f in enumerate(forces)],
    }


def _idp_summary(force: float, idp: np.ndarray, r: LiteratureRange | None) -> dict[str, Any]:
    """FE's IDP at one force over the specimens (MPa) and its literature range."""
    finite = np.isfinite(idp).any()
    return {
        "force_n": force,
        "idp_mpa_mean": float(np.nanmean(idp)) if finite else float("nan"),
        "idp_mpa_min": float(np.nanmin(idp)) if finite else float("nan"),
        "idp_mpa_max": float(np.nanmax(idp)) if finite else float("nan"),
        "literature": None
        if r is None
        else {"low_mpa": r.low_mpa, "mean_mpa": r.mean_mpa, "high_mpa": r.high_mpa},
        "n_in_range": None if r is None else int(np.sum(r.contains(idp))),
    }


def json_safe(value: Any) -> Any:
    """``value`` with NaN and inf as null (strict JSON), dicts, lists and tuples walked through."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
