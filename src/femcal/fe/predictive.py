"""Predictive FE validation: calibrate on 1-5 Nm, let FE predict 5.5-10 Nm, never seen.

The FE validation of :mod:`femcal.fe.validate` scores the calibrated parameters against the
very curves they were fitted to (an in-sample residual). Here the held-out specimens' curves
are split by moment at ``split_nm`` (:func:`split_moment`: 5 Nm when the curves go beyond
it, else the grid's middle moment, so that a 1-5 Nm campaign fits 1-3 Nm and predicts 4-5):

1. the calibration sees only the points from :data:`FIT_FROM_NM` up to the split, noise-free
   or with Gaussian noise of ``noise_deg`` added (seeded);
2. CalculiX runs the four load cases at the calibrated parameters, one FE run per specimen
   and load case (no refinement, no adaptive sampling aimed at the specimens), with
   ``fe.settings`` but the wall-clock limit of
   :data:`~femcal.fe.runtime.SHARED_MACHINE_TIMEOUT_S`;
3. the FE curves are compared with the specimens' noise-free curves above the split, which
   the calibration never saw.

``python -m femcal.fe.predictive`` (from ``fe/``) calibrates with the surrogate given and
``fe/params.yaml``'s ``calibrate`` settings (:func:`femcal.jobs.calibrate.run_calibration`, in
this process), and writes ``predictive.json``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.dvc_metrics import write as write_dvc_metrics
from femcal.errors import InputDataError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

#: Lowest moment the calibration sees, Nm (the study's protocol starts at 1 Nm).
FIT_FROM_NM = 1.0
#: Highest moment the calibration sees when the curves go beyond it, Nm.
SPLIT_NM = 5.0
#: First config_id of each variant's FE runs (apart from the campaign's).
ID_OFFSET = {"clean": 200_000, "noisy": 300_000}

#: ``(x (n, 13), ids (n,)) -> (RoM deg, IDP MPa)``, each (n, 4, m): the FE model at the
#: truth's moments.
Curves = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
#: ``(long table of the points to fit, variant) -> parameters (specimen + 13 columns)``.
Calibrate = Callable[[pd.DataFrame, str], pd.DataFrame]


def split_moment(moments: Sequence[float]) -> float:
    """The highest moment the calibration sees, Nm.

    :data:`SPLIT_NM` when the grid has moments above it; otherwise the middle moment of the
    grid's points from :data:`FIT_FROM_NM` on, so that points remain on both sides.

    Raises
    ------
    InputDataError
        When fewer than two moments are at or above :data:`FIT_FROM_NM`.
    """
    grid = np.sort(np.asarray(moments, dtype=float))
    usable = grid[grid >= FIT_FROM_NM - 1e-9]
    if len(usable) < 2:
        raise InputDataError(
            f"The held-out curves have moments {grid.tolist()} Nm; predictive validation "
            f"needs at least two moments from {FIT_FROM_NM:g} Nm on (the lower ones to fit, "
            f"the upper ones to predict). Validate on curves with more load levels."
        )
    if usable[-1] > SPLIT_NM + 1e-9 and usable[0] <= SPLIT_NM + 1e-9:
        return SPLIT_NM
    return float(usable[(len(usable) - 1) // 2])


def bands(moments: Sequence[float], split_nm: float) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the fitted (``FIT_FROM_NM..split_nm``) and the predicted (``> split_nm``)
    moments, each shape (m,); disjoint."""
    moments = np.asarray(moments, dtype=float)
    fit = (moments >= FIT_FROM_NM - 1e-9) & (moments <= split_nm + 1e-9)
    return fit, moments > split_nm + 1e-9


def fit_targets(
    long: pd.DataFrame, noise_deg: float, rng: np.random.Generator | None, split_nm: float
) -> pd.DataFrame:
    """The points the calibration sees, with noise when ``rng`` is given.

    Parameters
    ----------
    long : pandas.DataFrame
        ``specimen, load_case, moment_nm, rom_deg, ...`` (:meth:`Measurements.to_long`).
    noise_deg : float
        Sd of the Gaussian noise added to ``rom_deg``, deg.
    rng : numpy.random.Generator or None
        None: noise-free.
    split_nm : float
        Highest moment seen, Nm (:func:`split_moment`).

    Returns
    -------
    pandas.DataFrame
        The rows from :data:`FIT_FROM_NM` to ``split_nm`` (``idp_mpa`` dropped).
    """
    out = long[bands(long["moment_nm"].to_numpy(), split_nm)[0]].drop(
        columns=["idp_mpa"], errors="ignore"
    )
    out = out.reset_index(drop=True)
    if rng is not None:
        out["rom_deg"] = out["rom_deg"] + rng.normal(0.0, noise_deg, len(out))
    return out


def predictive_error(
    truth: np.ndarray, fe: np.ndarray, moments: np.ndarray, split_nm: float
) -> dict[str, Any]:
    """FE-vs-truth MAE in the fitted and in the predicted band.

    Parameters
    ----------
    truth, fe : ndarray, shape (n, 4, m)
        Noise-free RoM of the specimens and FE RoM at their calibrated parameters, deg (NaN:
        not reached).
    moments : ndarray, shape (m,)
        Nm.
    split_nm : float
        Highest moment the calibration saw, Nm.

    Returns
    -------
    dict
        ``predict_mae_deg`` (above ``split_nm``), ``fit_band_mae_deg`` (up to it), per load
        case and per specimen in the predicted band, and the number of points compared.
    """
    err = np.abs(np.asarray(fe, float) - np.asarray(truth, float))
    fit, pred = bands(moments, split_nm)
    per_specimen = np.nanmean(err[:, :, pred], axis=(1, 2))
    return {
        "predict_mae_deg": float(np.nanmean(err[:, :, pred])),
        "fit_band_mae_deg": float(np.nanmean(err[:, :, fit])),
        "predict_mae_deg_per_load_case": {
            lc: float(np.nanmean(err[:, k][:, pred])) for k, lc in enumerate(LOAD_CASES)
        },
        "predict_mae_deg_max_specimen": float(np.nanmax(per_specimen)),
        "n_points_predicted": int(np.sum(np.isfinite(err[:, :, pred]))),
    }


def run_predictive(
    truth: Any,
    curves: Curves,
    calibrate: Calibrate,
    noise_deg: float,
    seed: int,
    variants: Sequence[str] = ("clean", "noisy"),
) -> dict[str, Any]:
    """Calibrate on the lower moments (noise-free and noisy), FE-predict the upper ones.

    Parameters
    ----------
    truth : Measurements
        The held-out specimens' noise-free curves at 0.5-10 Nm.
    curves : callable
        The FE model: RoM and IDP at ``truth.moments`` (:func:`fe_outputs`).
    calibrate : callable
        ``(points, variant) -> parameters``.
    noise_deg : float
        Measurement noise of the noisy variant, deg.
    seed : int
        Seed of the noise.
    variants : sequence of {"clean", "noisy"}, optional
        The variants run (both by default).

    Returns
    -------
    dict
        ``fe_predictive_mae_deg``, ``fe_predictive_mae_deg_noisy``, each variant's details
        (with ``idp_mae_mpa``: FE's IDP at the calibrated parameters against the specimens'
        under all the moments, when the truth has IDP), ``split_nm``, ``n_specimens`` and
        ``fe_runs_per_specimen_max`` (1).

    Raises
    ------
    InputDataError
        When the truth has too few moments to split (:func:`split_moment`).
    """
    moments = np.asarray(truth.moments, dtype=float)
    split_nm = split_moment(moments)
    long = truth.to_long()
    out: dict[str, Any] = {
        "n_specimens": len(truth.specimens),
        "noise_deg": float(noise_deg),
        "split_nm": split_nm,
    }
    rngs = {"clean": None, "noisy": np.random.default_rng([seed, 43])}
    for variant, rng in ((v, rngs[v]) for v in variants):
        params = calibrate(fit_targets(long, noise_deg, rng, split_nm), variant)
        params = params.set_index(params["specimen"].astype(str)).loc[list(truth.specimens)]
        x = params[list(PARAMETER_NAMES)].to_numpy(dtype=float)
        ids = ID_OFFSET[variant] + np.arange(len(x))
        fe, idp = curves(x, ids)
        out[variant] = predictive_error(truth.rom_deg, fe, moments, split_nm)
        if truth.idp_mpa is not None:
            out[variant]["idp_mae_mpa"] = float(np.nanmean(np.abs(idp - truth.idp_mpa)))
            out[variant]["idp_mean_abs_mpa"] = float(np.nanmean(np.abs(truth.idp_mpa)))
    keys = {"clean": "fe_predictive_mae_deg", "noisy": "fe_predictive_mae_deg_noisy"}
    for variant in variants:
        out[keys[variant]] = out[variant]["predict_mae_deg"]
    out["fe_runs_per_specimen_max"] = 1
    return out


def fe_outputs(fe: Any, moments: Sequence[float]) -> Curves:
    """A :data:`Curves` that runs ``fe`` (a :class:`~femcal.fe.runtime.FeRuntime`) as a
    campaign of the four load cases at ``moments``; NaN where a run did not reach a level."""
    levels = [float(m) for m in moments]

    def outputs(x: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        design = pd.DataFrame(np.asarray(x, dtype=float), columns=list(PARAMETER_NAMES))
        design.insert(0, "config_id", np.asarray(ids, dtype=np.int64))
        result = fe.campaign(design, load_cases=LOAD_CASES, moments=levels)
        where = {int(c): j for j, c in enumerate(design["config_id"])}
        rom = np.full((len(design), len(LOAD_CASES), len(levels)), np.nan)
        idp = rom.copy()
        for rec in result.records.itertuples(index=False):
            i, k = where[int(rec.config_id)], LOAD_CASES.index(rec.load_case)
            rom[i, k] = [np.nan if v is None else float(v) for v in rec.rom_deg]
            idp[i, k] = [np.nan if v is None else float(v) for v in rec.idp_mpa]
        return rom, idp

    return outputs


def job_calibrate(
    params: Mapping[str, Any], model_uri: str, out_dir: Path, noise_deg: float
) -> Calibrate:
    """A :data:`Calibrate` that calibrates the disc alone with ``params``' ``calibrate``
    settings and the surrogate ``model_uri`` (no held-out surrogate, no figures), into
    ``out_dir/<variant>/calibration``; the ``noisy`` variant counts ``noise_deg``.

    The MLflow run goes to the store MLflow is pointed at (:func:`main`:
    :func:`femcal.jobs.common.use_project`).
    """
    from femcal.jobs.calibrate import CalibrationJob, run_calibration

    def calibrate(points: pd.DataFrame, variant: str) -> pd.DataFrame:
        folder = out_dir / variant
        folder.mkdir(parents=True, exist_ok=True)
        points.to_csv(folder / "points.csv", index=False)
        noisy = variant == "noisy"
        job = CalibrationJob.from_params(
            params,
            measurements=folder / "points.csv",
            out_dir=folder / "calibration",
            model_uri=model_uri,
            holdout_uri=None,
            plots="none",
            noise_deg=float(noise_deg) if noisy else None,
            noise_source="python -m femcal.fe.predictive --noise-deg" if noisy else "",
        )
        run_calibration(job)
        return pd.read_csv(folder / "calibration" / "parameters.csv", dtype={"specimen": str})

    return calibrate


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line of :func:`run_predictive`, run from ``fe/`` (module docstring)."""
    from femcal.config import load_params
    from femcal.fe.runtime import SHARED_MACHINE_TIMEOUT_S, fe_runtime
    from femcal.jobs.common import use_project
    from femcal.measurements import read_measurements
    from femcal.threads import limit_threads

    parser = argparse.ArgumentParser(prog="python -m femcal.fe.predictive")
    parser.add_argument("--measurements", type=Path, default=Path("data/dataset/Test"))
    parser.add_argument("--model-uri", default="models/surrogate-large")
    parser.add_argument("--out", type=Path, default=Path("reports/predictive"))
    parser.add_argument("--store", default="data/predictive-campaign/runs.jsonl.gz")
    parser.add_argument("--noise-deg", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--variants", nargs="+", choices=["clean", "noisy"], default=["clean", "noisy"]
    )
    parser.add_argument(
        "--n-specimens", type=int, default=16, help="the first n held-out specimens (0: all)"
    )
    parser.add_argument(
        "--timeout-s",
        type=int,
        default=SHARED_MACHINE_TIMEOUT_S,
        help="wall-clock limit of one attempt of an FE job, s (part of the job's hash)",
    )
    parser.add_argument(
        "--metrics-file", type=Path, default=Path("reports/metrics/predictive.json")
    )
    args = parser.parse_args(argv)
    limit_threads()  # as femcal's command line: the cores free now, before torch starts
    params = load_params("params.yaml")
    use_project(params)
    fe = fe_runtime(params, {"store": args.store}, "fe")
    fe = replace(fe, settings={**fe.settings, "timeout_s": args.timeout_s})
    truth = read_measurements(args.measurements)
    if args.n_specimens:
        truth = truth.subset(truth.specimens[: args.n_specimens])
    curves = fe_outputs(fe, truth.moments)
    calibrate = job_calibrate(params, args.model_uri, args.out, args.noise_deg)
    figures = run_predictive(truth, curves, calibrate, args.noise_deg, args.seed, args.variants)
    figures.update(model_uri=args.model_uri, measurements=str(args.measurements))
    write_dvc_metrics(args.metrics_file, "predictive", figures, details=True)
    print(json.dumps({k: v for k, v in figures.items() if k.startswith("fe_predictive")}))
    return figures


if __name__ == "__main__":
    main()
