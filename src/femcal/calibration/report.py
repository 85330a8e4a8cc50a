"""Calibration outputs: tables, per-specimen figures, a summary page, an MLflow run.

:func:`write_outputs` writes into one directory

* ``parameters.csv``: ``specimen`` + the d parameters in physical units;
* ``metrics.csv``: specimen, method, mae_deg, r2_mean, MAE and R² per load case, exceedance,
  success, missing load cases, ``holdout_mae_deg`` when a
  held-out surrogate re-evaluated the parameters, ``reachability`` (why a specimen's points lie
  outside every curve the model can produce, :mod:`femcal.reachability`; "" when they do not)
  and ``flag`` (:func:`fit_flags`: "R2<0" for a fit worse than the specimen's mean, "outside
  envelope"; "" for a plain fit);
* ``ranges.csv``: the identifiability range of every parameter of every specimen;
* ``curves.csv``: measured and calibrated RoM of every point (long format);
* ``plots/<specimen>.png``: measured vs calibrated RoM per load case (the study's figure 4),
  with the noise band when the noise is known (:mod:`femcal.calibration.plots`);
  ``plots="summary"`` or ``"none"`` leaves them out;
* ``summary.png`` (not with ``plots="none"``) and ``summary.md``, ``summary.json`` (aggregate
  figures, DVC metrics).

The files hold what was computed, so a rerun on the same inputs writes the same bytes; the
batch's wall time goes to the returned figures (``seconds``: the console, MLflow, the
folder's marker), not to the files.
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.calibration.model import CurveModel
from femcal.calibration.plots import FigureCurves, plot_specimens, plot_summary
from femcal.calibration.result import CalibrationResult
from femcal.dvc_metrics import split_run
from femcal.metrics import curve_metrics
from femcal.schema import LOAD_CASES
from femcal.settings.keywords import PLOT_CHOICES  # all, summary, none

logger = logging.getLogger(__name__)

#: A specimen's residuals are "beyond noise" (flag, ``n_beyond_noise``) below this chi-square
#: p-value (the diagnosis' ``alpha``).
BEYOND_NOISE_P = 0.01

#: A parameter counts as determined by the data for a specimen when its identifiability range
#: spans less than this fraction of its bounds.
DETERMINED_WIDTH = 0.5


def holdout_scores(result: CalibrationResult, holdout: CurveModel) -> dict[str, np.ndarray]:
    """Re-evaluate calibrated parameters with an independently trained surrogate.

    Returns
    -------
    dict
        ``mae`` (n,), ``r2_mean`` (n,) of the held-out surrogate's curves at ``result.x``
        against the measurements, and ``prediction`` (n, 4, m).
    """
    pred = holdout.predict(result.x, clip=False)
    m = curve_metrics(result.measured, pred)
    return {"mae": m["mae"], "r2_mean": m["r2_mean"], "prediction": pred}


def identifiability(result: CalibrationResult) -> pd.DataFrame | None:
    """Per parameter: mean normalised range width and the fraction of specimens it is
    determined for (width < :data:`DETERMINED_WIDTH`); None without ranges."""
    ranges = result.ranges_frame()
    if ranges is None:
        return None
    ranges["determined"] = ranges["width_normalised"] < DETERMINED_WIDTH
    out = ranges.groupby("parameter", sort=False).agg(
        mean_width=("width_normalised", "mean"), determined=("determined", "mean")
    )
    return out.reset_index()


def coverage(result: CalibrationResult, x_true: np.ndarray, *, atol: float = 1e-9) -> np.ndarray:
    """Per parameter, the fraction of specimens whose true value lies in its range, shape (d,)."""
    if result.x_low is None or result.x_high is None:
        return np.full(len(result.parameter_names), np.nan)
    inside = (x_true >= result.x_low - atol) & (x_true <= result.x_high + atol)
    return inside.mean(axis=0)


def curves_frame(result: CalibrationResult, holdout_pred: np.ndarray | None = None) -> pd.DataFrame:
    """Measured and calibrated RoM of every measured point, long format."""
    n, n_lc, m = result.measured.shape
    spec, lc, mom = np.meshgrid(np.arange(n), np.arange(n_lc), np.arange(m), indexing="ij")
    df = pd.DataFrame(
        {
            "specimen": np.asarray(result.specimens, dtype=object)[spec.reshape(-1)],
            "load_case": np.asarray(LOAD_CASES, dtype=object)[lc.reshape(-1)],
            "moment_nm": result.moments[mom.reshape(-1)],
            "measured_rom_deg": result.measured.reshape(-1),
            "calibrated_rom_deg": result.prediction.reshape(-1),
        }
    )
    if holdout_pred is not None:
        df["holdout_rom_deg"] = holdout_pred.reshape(-1)
    return df[np.isfinite(df["measured_rom_deg"])].reset_index(drop=True)


def fit_flags(metrics: pd.DataFrame) -> pd.Series:
    """What a reader must not take for a plain success, per specimen.

    Parameters
    ----------
    metrics : pandas.DataFrame, shape (n, k)
        Per-specimen metrics with ``r2_mean`` and, optionally, ``reachability`` (text, "" when
        the specimen lies within the model's envelope) and ``p_value``
        (:attr:`~femcal.calibration.result.CalibrationResult.p_value`).

    Returns
    -------
    pandas.Series of str, shape (n,)
        "; "-joined flags: ``R2<0`` (the calibrated curves explain less than the specimen's
        mean: a fit worse than a flat line), ``outside envelope``, ``beyond noise`` (with a
        ``p_value`` column: its residuals exceed the noise, p < :data:`BEYOND_NOISE_P`); ""
        when none applies.
    """
    r2 = pd.to_numeric(metrics["r2_mean"], errors="coerce").to_numpy(dtype=float)
    notes = metrics["reachability"] if "reachability" in metrics else pd.Series([""] * len(r2))
    p = (
        pd.to_numeric(metrics["p_value"], errors="coerce").to_numpy(dtype=float)
        if "p_value" in metrics
        else np.full(len(r2), np.nan)
    )
    flags = [
        "; ".join(
            f
            for f, on in (
                ("R2<0", r < 0),
                ("outside envelope", bool(note)),
                ("beyond noise", pv < BEYOND_NOISE_P),
            )
            if on
        )
        for r, note, pv in zip(r2, notes.fillna("").astype(str), p)
    ]
    return pd.Series(flags, index=metrics.index, dtype=object)


def summary(result: CalibrationResult, holdout: Mapping[str, np.ndarray] | None = None) -> dict:
    """Aggregate figures of a batch (what the DVC metrics file and MLflow record).

    ``n_r2_negative`` counts the specimens whose fit is worse than their mean (R² < 0). With
    an error scale (``femcal calibrate --noise-deg``): ``rms_z_median`` and ``rms_z_max``, the
    residuals in units of the noise, and ``n_beyond_noise``, the specimens whose residuals the
    noise does not explain (p < :data:`BEYOND_NOISE_P`).
    """
    out: dict[str, Any] = {
        "method": result.method,
        "n_specimens": len(result.specimens),
        "mae_deg": float(np.nanmean(result.mae_deg)),
        "mae_deg_median": float(np.nanmedian(result.mae_deg)),
        "mae_deg_max": float(np.nanmax(result.mae_deg)),
        "r2_mean": float(np.nanmean(result.r2_mean)),
        "exceedance_max": float(np.max(result.exceedance)),
        "n_outside_bounds": int(np.sum(result.exceedance > 0)),
        "seconds": float(result.seconds),
        "n_success": int(np.sum(result.success)),
        "n_r2_negative": int(np.sum(np.asarray(result.r2_mean, dtype=float) < 0)),
        "nit": int(result.nit),
    }
    for j, lc in enumerate(LOAD_CASES):
        col = result.mae_per_load_case[:, j]
        if np.isfinite(col).any():
            out[f"mae_deg_{lc}"] = float(np.nanmean(col))
    if holdout is not None:
        out["holdout_mae_deg"] = float(np.nanmean(holdout["mae"]))
        out["holdout_r2_mean"] = float(np.nanmean(holdout["r2_mean"]))
    rms_z, p = result.rms_z, result.p_value
    if rms_z is not None and p is not None:
        out["rms_z_median"] = float(np.median(rms_z))
        out["rms_z_max"] = float(np.max(rms_z))
        out["n_beyond_noise"] = int(np.sum(p < BEYOND_NOISE_P))
    ident = identifiability(result)
    if ident is not None:
        out["range_width_mean"] = float(ident["mean_width"].mean())
        out["determined"] = {
            row.parameter: round(float(row.determined), 4) for row in ident.itertuples()
        }
    return out


def safe_file_name(name: str) -> str:
    """A specimen name made safe as a file name (other characters become "_")."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "specimen"


def figure_names(specimens: Sequence[str]) -> list[str]:
    """Distinct file names (without suffix) for the specimens' figures, in their order: each
    specimen's :func:`safe_file_name`, with "_" appended until no earlier specimen's name is
    the same (``["a b", "a_b"]`` gives ``["a_b", "a_b_"]``)."""
    used: set[str] = set()
    names = []
    for specimen in specimens:
        name = safe_file_name(str(specimen))
        while name in used:
            name += "_"
        used.add(name)
        names.append(name)
    return names


def plot_mode(plots: bool | str) -> str:
    """``plots`` as one of ``PLOT_CHOICES`` (True is "all", False is "none").

    "all": every per-specimen PNG and the summary page; "summary": the summary page only;
    "none": no figure (the tables, curves.csv and summary.md/json are always written).

    Raises
    ------
    ValueError
        Another value.
    """
    if plots is True or plots is False:
        return "all" if plots else "none"
    if plots not in PLOT_CHOICES:
        raise ValueError(
            f"plots must be one of {', '.join(PLOT_CHOICES)} (or a bool); got {plots!r}"
        )
    return str(plots)


def _markdown(result: CalibrationResult, figures: dict, ident: pd.DataFrame | None) -> str:
    lines = [
        f"# Calibration: {result.method}",
        "",
        f"{result.message}.",
        "",
        *_warnings(figures),
        "| figure | value |",
        "|---|---|",
    ]
    for key, value in figures.items():
        if isinstance(value, dict):
            continue
        lines.append(
            f"| {key} | {value:.6g} |" if isinstance(value, float) else f"| {key} | {value} |"
        )
    missing = result.metrics_frame()["missing_load_cases"]
    if (missing != "").any():
        lines += ["", "Specimens calibrated without some load cases:", ""]
        for spec, miss in zip(result.specimens, missing):
            if miss:
                lines.append(f"- {spec}: no {miss.replace(';', ', ')}")
    if ident is not None:
        lines += [
            "",
            "## Identifiability",
            "",
            "Range of the near-optimal solutions per parameter (fraction of its bounds); "
            f"'determined' = share of specimens whose range is narrower than {DETERMINED_WIDTH}.",
            "",
            "| parameter | mean range | determined |",
            "|---|---|---|",
        ]
        for row in ident.itertuples():
            lines.append(f"| {row.parameter} | {row.mean_width:.3f} | {row.determined:.2f} |")
    return "\n".join(lines) + "\n"


def _warnings(figures: Mapping[str, Any]) -> list[str]:
    """Markdown lines (each followed by a blank line) flagging fits that are no success."""
    lines = []
    n_neg, n_out = figures.get("n_r2_negative", 0), figures.get("n_outside_envelope", 0)
    if n_neg:
        lines += [
            f"**Warning: {n_neg} of {figures['n_specimens']} specimens fit worse than their mean "
            "(R² < 0): see metrics.csv (column flag).** Their calibrated curves explain less than "
            "a flat line at the measured mean; check the units and load cases of those "
            "specimens.",
            "",
        ]
    n_beyond = figures.get("n_beyond_noise", 0)
    if n_beyond:
        lines += [
            f"**{n_beyond} of {figures['n_specimens']} specimens are not explained within the "
            "noise (chi-square p < "
            f"{BEYOND_NOISE_P:g}): see metrics.csv (columns flag, rms_z, p_value).** The model "
            "misses something there, or the noise given is too small: `femcal diagnose` asks "
            "which physical effect is missing.",
            "",
        ]
    if n_out:
        lines += [
            f"**Warning: {n_out} of {figures['n_specimens']} specimens have measured points "
            "outside every curve the model can produce: see metrics.csv (columns flag, "
            "reachability).**",
            "",
        ]
    return lines


def write_outputs(
    result: CalibrationResult,
    out_dir: Path,
    *,
    holdout: CurveModel | None = None,
    plots: bool | str = True,
    max_plots: int | None = None,
    reachability: Sequence[str] | None = None,
    progress: bool = False,
    curves: FigureCurves | None = None,
    before_figures: Callable[[dict], Any] | None = None,
) -> dict:
    """Write the tables, figures and summary of a calibration; returns the summary figures.

    Parameters
    ----------
    result : CalibrationResult
    out_dir : Path
        Created if needed; existing files of the same names are replaced.
    holdout : CurveModel, optional
        An independently trained surrogate on the same moment grid: its MAE at the calibrated
        parameters is reported as ``holdout_mae_deg``.
    plots : {"all", "summary", "none"} or bool
        "all" (True): the per-specimen PNGs (``plots/``) and the summary page (``summary.png``);
        "summary": the summary page only; "none" (False): no figure. The tables and
        ``summary.md``/``summary.json`` are written in every case.
    max_plots : int, optional
        Write per-specimen PNGs for the first ``max_plots`` specimens only (the tables always
        hold every specimen; the summary says how many were plotted).
    reachability : sequence of str, shape (n,), optional
        Per specimen, why its points lie outside the model's envelope ("" when they do not;
        :meth:`femcal.reachability.ReachabilityReport.notes`): the ``reachability`` column of
        metrics.csv, flagged in ``flag`` and counted as ``n_outside_envelope``.
    progress : bool
        Show a progress bar (stderr) over the per-specimen plots.
    curves : FigureCurves, optional
        What the per-specimen figures draw: continuous curves of the calibrated (and held-out)
        model and the sd of one measurement (:func:`femcal.calibration.plots.dense_curves`);
        default: the curves at the measured moments, with the result's error scale.
    before_figures : callable, optional
        Called with the summary figures once the tables, ``summary.json`` and ``summary.md``
        are written, before the figures are drawn (e.g. to log them meanwhile).
    """
    mode = plot_mode(plots)  # a wrong value before any file is written
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    held = holdout_scores(result, holdout) if holdout is not None else None
    metrics = result.metrics_frame()
    if held is not None:
        metrics["holdout_mae_deg"] = held["mae"]
        metrics["holdout_r2_mean"] = held["r2_mean"]
    if reachability is not None:
        metrics["reachability"] = [str(note) for note in reachability]
    metrics["flag"] = fit_flags(metrics)
    result.parameters_frame().to_csv(out_dir / "parameters.csv", index=False)
    metrics.to_csv(out_dir / "metrics.csv", index=False)
    ranges = result.ranges_frame()
    if ranges is not None:
        ranges.to_csv(out_dir / "ranges.csv", index=False)
    curves_frame(result, None if held is None else held["prediction"]).to_csv(
        out_dir / "curves.csv", index=False
    )
    figures = summary(result, held)
    if reachability is not None:
        figures["n_outside_envelope"] = int(sum(bool(note) for note in reachability))
    if figures["n_r2_negative"]:
        logger.warning(
            "%d of %d specimens fit worse than their mean (R² < 0): see metrics.csv (column flag).",
            figures["n_r2_negative"],
            figures["n_specimens"],
        )
    n = len(result.specimens)
    n_plot = n if max_plots is None else min(n, int(max_plots))
    figures["n_plotted"] = n_plot if mode == "all" else 0
    ident = identifiability(result)
    # the wall time is the run's, not the calibration's: the marker and MLflow hold it
    computed = split_run(figures)[0]
    (out_dir / "summary.json").write_text(json.dumps(computed, indent=2) + "\n")
    (out_dir / "summary.md").write_text(_markdown(result, computed, ident))
    if before_figures is not None:
        before_figures(figures)
    page = None
    if mode != "none":
        page = partial(plot_summary, result, out_dir / "summary.png", held, ident, DETERMINED_WIDTH)
    if mode == "all":
        plot_dir = out_dir / "plots"
        plot_dir.mkdir(exist_ok=True)
        paths = [plot_dir / f"{name}.png" for name in figure_names(result.specimens[:n_plot])]
        start = time.perf_counter()
        if curves is None:
            curves = FigureCurves.at_measured(result, None if held is None else held["prediction"])
        # the summary page drawn beside the specimens' figures
        plot_specimens(result, paths, curves, progress=progress, beside=page)
        logger.debug("%d specimen plots in %.2f s", n_plot, time.perf_counter() - start)
        if n_plot < n:
            logger.warning(
                "Plotted %d of %d specimens (max_plots); the tables hold all of them.", n_plot, n
            )
    elif page is not None:
        page()
    return figures
