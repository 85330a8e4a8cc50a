"""How far can FE prediction at 5.5-10 Nm go? Oracles under ``fe_predictive_mae_deg_noisy``.

The predict stage of ``fe/dvc.yaml`` (:mod:`femcal.fe.predictive`) calibrates 16 held-out Test
specimens of the FE campaign on 1-5 Nm through the surrogate, runs CalculiX at the calibrated
parameters and scores it against the specimens' curves at 5.5-10 Nm. This experiment splits
that error into its causes and measures what a calibrator could reach at best:

* **Decomposition** (no FE run; the predict stage's CalculiX runs are read from its committed
  store): at the calibrated parameters, the surrogate against CalculiX (the surrogate's own
  error where the calibration landed) and the surrogate against the truth, in the fitted
  (1-5 Nm) and the predicted (5.5-10 Nm) band; and the surrogate against the truth at the
  true parameters.
* **Oracle 1, the fit made on CalculiX itself** (``refine``): the predict stage's calibrated
  parameters refined with FE in the loop (:func:`femcal.fe.refine.refine_with_fe`) on the
  same 1-5 Nm points, noise-free and with the stage's 0.05 deg noise (the same draws); the
  CalculiX runs cover 0.5-10 Nm, so the run at the best point FE found is also its
  prediction at 5.5-10 Nm. What is left is the predictive error without the surrogate's error
  in the fit (up to the refinement's own convergence). Its first round is the predict stage's
  runs (``fe/data/predictive-campaign``, read where the parameters agree to 1e-5 of the box),
  the further ones go to this experiment's store (committed, resumed when present), one
  CalculiX job at a time.
* **Oracle 2, identifiability** (no FE run): the surrogate taken as the world, so that its
  error is zero by construction. Each specimen's 1-5 Nm targets are the surrogate's curves at
  its true parameters (plus the same noise draws), calibrated ``--starts`` times each from
  uniform random starts (pgd, Gauss-Newton); among the ends that fit 1-5 Nm as well as the true
  parameters do (MAE at most theirs + :data:`EQUAL_FIT_MARGIN_DEG`), the 5.5-10 Nm error
  against the surrogate at the true parameters is the part of the predictive error that the
  data leave open, whatever the model's accuracy.
* **Oracle 3, the true parameters**: the Test curves are CalculiX at the true parameters, so
  their predictive error is 0 by construction; not re-run.

Usage (from the project root; ``FE`` is the FE pipeline's folder with its DVC outputs, e.g.
/tmp/ferun/fe: ``data/dataset/Test``, ``models/surrogate-large``, ``reports/predictive``)::

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m experiments.fe_predictive_ceiling \\
        --fe-dir FE

It writes ``ceiling.json`` and ``ceiling.md`` into ``--out``
(experiments/results/fe_predictive_ceiling/ by default), beside the store of the refinement's
CalculiX runs; with the store committed, a rerun with the same torch thread count runs no
CalculiX job.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from experiments.common import REPO, RESULTS, reproduce_command
from femcal.errors import InputDataError
from femcal.fe.predictive import ID_OFFSET, bands, fit_targets, predictive_error, split_moment
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

#: The refinement's CalculiX runs are numbered from here (row i: ``REFINE_ID_OFFSET + i``; the
#: noise-free rows first, then the noisy ones).
REFINE_ID_OFFSET = 400_000
#: The variants of the predict stage, in its order.
VARIANTS = ("clean", "noisy")
#: A parameter set "fits 1-5 Nm as well" as the true one when its MAE there is at most the
#: true parameters' MAE plus this, deg (a fifth of the 0.05 deg noise).
EQUAL_FIT_MARGIN_DEG = 0.01
#: A refinement run at the calibrated parameters is served from the predict stage's store when
#: every parameter agrees to this fraction of its box width (float32 unit coordinates round
#: the start by about 1e-7).
SAME_POINT_TOL = 1e-5
#: Oracle 2: uniform random starts behind each end, the best after 4 iterations going on.
TRIES_PER_END = 4
#: Keys of the predictive MAE and of the equally fitting runs' spread in the figures.
PRED = ("predictive", "predict_mae_deg")
SPREAD = "predict_mae_spread_deg_mean"
#: Where the results and the store go.
OUT = RESULTS / "fe_predictive_ceiling"


@dataclass(frozen=True)
class Inputs:
    """The predict stage's specimens, targets and calibrations.

    Attributes
    ----------
    specimens, moments, split_nm : tuple of str (n,), ndarray (m,) in Nm, float in Nm
        The specimens, the moment grid and the highest moment fitted.
    truth : ndarray, shape (n, 4, m)
        Noise-free RoM of the specimens (CalculiX at the true parameters), deg; NaN where the
        run did not reach a level.
    x_true : ndarray, shape (n, d)
        True parameters, physical units.
    targets : dict of str to ndarray, shape (n, 4, m)
        Per variant, the points the calibration saw (1-5 Nm), deg; NaN elsewhere.
    x_cal : dict of str to ndarray, shape (n, d)
        Per variant, the predict stage's calibrated parameters.
    fe_cal : dict of str to ndarray, shape (n, 4, m)
        Per variant, CalculiX at ``x_cal`` (the predict stage's runs), deg.
    """

    specimens: tuple[str, ...]
    moments: np.ndarray
    split_nm: float
    truth: np.ndarray
    x_true: np.ndarray
    targets: dict[str, np.ndarray]
    x_cal: dict[str, np.ndarray]
    fe_cal: dict[str, np.ndarray]


def long_to_array(long: pd.DataFrame, specimens: Sequence[str], moments: np.ndarray) -> np.ndarray:
    """A long table ``specimen, load_case, moment_nm, rom_deg`` as an array (n, 4, m), deg,
    NaN where the table has no point."""
    out = np.full((len(specimens), len(LOAD_CASES), len(moments)), np.nan)
    i = pd.Index(list(specimens)).get_indexer(long["specimen"].astype(str))
    k = pd.Index(list(LOAD_CASES)).get_indexer(long["load_case"])
    j = np.abs(np.asarray(long["moment_nm"], float)[:, None] - moments[None, :]).argmin(axis=1)
    out[i, k, j] = long["rom_deg"].to_numpy(dtype=float)
    return out


def stored_curves(
    records: Sequence[Mapping[str, Any]], x: np.ndarray, config_ids: np.ndarray, m: int
) -> np.ndarray:
    """RoM (n, 4, m) of the store's runs of configurations ``config_ids`` (n,) at exactly the
    parameters ``x`` (n, d); NaN where no such run is stored or a level was not reached."""
    out = np.full((len(x), len(LOAD_CASES), m), np.nan)
    where = {int(c): i for i, c in enumerate(config_ids)}
    for rec in records:
        i = where.get(int(rec["config_id"]))
        if i is None or rec["load_case"] not in LOAD_CASES or len(rec["rom_deg"]) != m:
            continue
        p = np.array([rec["parameters"][name] for name in PARAMETER_NAMES], dtype=float)
        if np.allclose(p, x[i], rtol=1e-12, atol=1e-12):
            rom = [np.nan if v is None else float(v) for v in rec["rom_deg"]]
            out[i, LOAD_CASES.index(rec["load_case"])] = rom
    return out


def read_inputs(fe_dir: Path, predictive_store: Path, n_specimens: int, seed: int) -> Inputs:
    """The predict stage's inputs from its folder ``fe_dir`` (module docstring), its noise
    redrawn as it drew it (seed ``seed``, the stage's noise) and checked against its points.

    Raises
    ------
    InputDataError
        When the redrawn noisy points differ from the stage's ``points.csv``, or the stage's
        store lacks its runs at the calibrated parameters.
    """
    from femcal.fe.store import load_records
    from femcal.measurements import read_measurements

    meas = read_measurements(fe_dir / "data/dataset/Test")
    meas = meas.subset(meas.specimens[:n_specimens])
    moments = np.asarray(meas.moments, dtype=float)
    split_nm = split_moment(moments)
    specimens = tuple(meas.specimens)
    report = json.loads((fe_dir / "reports/predictive.json").read_text())
    rngs = {"clean": None, "noisy": np.random.default_rng([seed, 43])}
    targets, x_cal, fe_cal = {}, {}, {}
    records = load_records(predictive_store)
    for variant in VARIANTS:
        points = fit_targets(meas.to_long(), report["noise_deg"], rngs[variant], split_nm)
        folder = fe_dir / "reports/predictive" / variant
        seen = pd.read_csv(folder / "points.csv", dtype={"specimen": str})
        if len(seen) != len(points) or not np.allclose(seen["rom_deg"], points["rom_deg"]):
            raise InputDataError(
                f"{folder / 'points.csv'} holds other points than the noise redrawn with seed "
                f"{seed}; give --seed of the predict stage that wrote {fe_dir}."
            )
        targets[variant] = long_to_array(points, specimens, moments)
        params = pd.read_csv(folder / "calibration/parameters.csv", dtype={"specimen": str})
        x_cal[variant] = params.set_index("specimen").loc[list(specimens), list(PARAMETER_NAMES)]
        x_cal[variant] = x_cal[variant].to_numpy(dtype=float)
        ids = ID_OFFSET[variant] + np.arange(len(specimens))
        fe_cal[variant] = stored_curves(records, x_cal[variant], ids, len(moments))
        if np.isnan(fe_cal[variant]).all(axis=(1, 2)).any():
            raise InputDataError(
                f"{predictive_store} lacks the predict stage's {variant} runs at the calibrated "
                f"parameters of {folder}; give the store of the run that wrote them."
            )
    x_true = pd.read_csv(next((fe_dir / "data/dataset/Test").glob("MaterialConfigurations_*")))
    x_true = x_true[list(PARAMETER_NAMES)].to_numpy(dtype=float)[[int(s) for s in specimens]]
    return Inputs(specimens, moments, split_nm, meas.rom_deg, x_true, targets, x_cal, fe_cal)


def surrogate_at(model: Any, x: np.ndarray) -> np.ndarray:
    """The surrogate's RoM (n, 4, m) at physical parameters ``x`` (n, d), deg."""
    with torch.no_grad():
        return model.curves(model.from_physical(x).float()).double().numpy()


def band_mae(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> dict[str, Any]:
    """MAE of ``a - b`` (n, 4, m) over the finite points of ``mask`` (m,), overall and per load
    case, deg."""
    err = np.abs(a - b)[:, :, mask]
    return {
        "mae_deg": float(np.nanmean(err)),
        "per_load_case": {lc: float(np.nanmean(err[:, k])) for k, lc in enumerate(LOAD_CASES)},
    }


def decomposition(inp: Inputs, model: Any) -> dict[str, Any]:
    """The predictive error at the predict stage's calibrations split into the surrogate's
    error there and the surrogate's own prediction, per band (``fit_1_5``,
    ``predict_5_10``), over the points where the truth and the stage's CalculiX run exist."""
    fit, pred = bands(inp.moments, inp.split_nm)
    s_true = surrogate_at(model, inp.x_true)
    out: dict[str, Any] = {}
    for variant in VARIANTS:
        fe = inp.fe_cal[variant]
        truth = np.where(np.isfinite(fe), inp.truth, np.nan)
        s_cal = surrogate_at(model, inp.x_cal[variant])
        pairs = {
            "fe_vs_truth": (fe, truth),
            "surrogate_vs_fe_at_calibrated": (s_cal, fe),
            "surrogate_vs_truth_at_calibrated": (s_cal, truth),
            "surrogate_vs_truth_at_true": (s_true, truth),
        }
        out[variant] = {
            name: {"fit_1_5": band_mae(a, b, fit), "predict_5_10": band_mae(a, b, pred)}
            for name, (a, b) in pairs.items()
        }
        out[variant]["predictive"] = predictive_error(inp.truth, fe, inp.moments, inp.split_nm)
    return out


class LoggedFe:
    """The refinement's FE model: CalculiX through a campaign runtime, a row's run at its
    starting parameters served from the predict stage's runs, every answer logged.

    Parameters
    ----------
    runtime : FeRuntime
        Solver, settings, store and cluster of the runs it makes.
    moments : ndarray, shape (m,)
        Levels of every run, Nm.
    x0, fe0 : ndarray, shapes (n, d) and (n, 4, m)
        The rows' starting parameters and CalculiX's RoM there (the predict stage's runs).
    config_ids : ndarray of int, shape (n,)
        The rows' configuration numbers in the store.
    width : ndarray, shape (d,)
        The box's widths, for :data:`SAME_POINT_TOL`.
    """

    def __init__(
        self,
        runtime: Any,
        moments: np.ndarray,
        x0: np.ndarray,
        fe0: np.ndarray,
        config_ids: np.ndarray,
        width: np.ndarray,
    ) -> None:
        self.run = runtime.curves([float(m) for m in moments])
        self.x0, self.fe0, self.config_ids, self.width = x0, fe0, config_ids, width
        self.log: list[tuple[np.ndarray, np.ndarray]] = []

    def __call__(self, x: np.ndarray, ids: np.ndarray) -> np.ndarray:
        x, ids = np.asarray(x, dtype=float), np.asarray(ids, dtype=int)
        same = np.all(np.abs(x - self.x0[ids]) <= SAME_POINT_TOL * self.width, axis=1)
        out = np.empty((len(x), *self.fe0.shape[1:]))
        out[same] = self.fe0[ids[same]]
        if (~same).any():
            out[~same] = self.run(x[~same], self.config_ids[ids[~same]])
        self.log.append((ids.copy(), out.copy()))
        return out


def fe_runtime_of(fe_dir: Path, store: Path) -> Any:
    """``fe_dir``'s FE runtime (its params.yaml's solver, settings) on one worker, to ``store``."""
    import yaml

    from femcal.fe.runtime import fe_runtime

    params = yaml.safe_load((fe_dir / "params.yaml").read_text())
    return replace(fe_runtime(params, {"store": str(store)}, "fe"), n_workers=1)


def refine_oracle(
    inp: Inputs, model: Any, runtime: Any, max_fe_runs: Mapping[str, int], tol_deg: float
) -> dict[str, Any]:
    """Oracle 1: each variant's calibrations refined on CalculiX at 1-5 Nm with
    ``max_fe_runs[variant]`` runs per specimen at most (the first the predict stage's), scored
    at 5.5-10 Nm at the best point FE found; and, among every CalculiX run of a specimen, the
    spread at 5.5-10 Nm of the runs that fit 1-5 Nm within :data:`EQUAL_FIT_MARGIN_DEG` of its
    best. Row i of variant k is configuration ``REFINE_ID_OFFSET + 1000 k + i``."""
    from femcal.fe.refine import refine_with_fe

    fit, _ = bands(inp.moments, inp.split_nm)
    n = len(inp.specimens)
    out: dict[str, Any] = {"tol_deg": tol_deg}
    for variant in ("noisy", "clean"):  # the bar's variant first
        if max_fe_runs.get(variant, 0) < 1:
            continue
        ids = REFINE_ID_OFFSET + 1000 * VARIANTS.index(variant) + np.arange(n)
        x0, measured = inp.x_cal[variant], inp.targets[variant]
        fe = LoggedFe(runtime, inp.moments, x0, inp.fe_cal[variant], ids, model.space.width)
        res = refine_with_fe(
            model,
            measured,
            x0,
            fe,
            specimens=inp.specimens,
            max_fe_runs=max_fe_runs[variant],
            tol_deg=tol_deg,
        )
        out[variant] = {
            "max_fe_runs": max_fe_runs[variant],
            "fe_runs_total": int(res.fe_runs.sum()),
            "fe_fit_mae_deg_start": float(np.nanmean(res.fe_mae_start)),
            "fe_fit_mae_deg_refined": float(np.nanmean(res.fe_mae_deg)),
            "fit_1_5_vs_truth_refined": band_mae(res.fe_curves, inp.truth, fit),
            "predictive": predictive_error(inp.truth, res.fe_curves, inp.moments, inp.split_nm),
            "equal_fit_runs": run_spread(fe.log, measured, inp),
        }
    return out


def run_spread(
    log: Sequence[tuple[np.ndarray, np.ndarray]], measured: np.ndarray, inp: Inputs
) -> dict[str, Any]:
    """Among the logged CalculiX runs ``(ids (k,), RoM (k, 4, m))`` of each specimen, those
    whose 1-5 Nm MAE against its targets ``measured`` (n, 4, m) is within
    :data:`EQUAL_FIT_MARGIN_DEG` of its best: their 5.5-10 Nm MAE against the truth, the spread
    (max - min) averaged over the specimens, deg."""
    _, pred = bands(inp.moments, inp.split_nm)
    spreads, counts = [], []
    for r in range(len(inp.specimens)):
        fits, preds = [], []
        for ids, curves in log:
            for j in np.flatnonzero(ids == r):
                fits.append(np.nanmean(np.abs(curves[j] - measured[r])))
                preds.append(np.nanmean(np.abs(curves[j] - inp.truth[r])[:, pred]))
        fits_a, preds_a = np.array(fits), np.array(preds)
        equal = fits_a <= np.nanmin(fits_a) + EQUAL_FIT_MARGIN_DEG
        counts.append(int(equal.sum()))
        spreads.append(float(np.nanmax(preds_a[equal]) - np.nanmin(preds_a[equal])))
    return {
        "runs_per_specimen_equal_fit_mean": float(np.mean(counts)),
        "predict_mae_spread_deg_mean": float(np.mean(spreads)),
        "predict_mae_spread_deg_max": float(np.max(spreads)),
    }


def world_fits(
    model: Any, world: np.ndarray, target: np.ndarray, pred: np.ndarray, options: Mapping
) -> dict[str, Any]:
    """Calibrate the targets (n, 4, m; NaN where not fitted) ``options["n_starts"]`` times per
    specimen with pgd (each from :data:`TRIES_PER_END` uniform random starts, seeded by
    ``options["rng"]``, ``options["max_iter"]`` Gauss-Newton iterations) and score the ends
    against ``world`` (n, 4, m), the surrogate at the true parameters, in the band ``pred``
    (m,): the best-fit end's and the equally fitting ends' 5.5-10 Nm MAE, averaged over the
    specimens, deg."""
    from femcal.calibration.base import CalibrationProblem
    from femcal.calibration.pgd import calibrate_pgd

    n, k = len(world), int(options["n_starts"])
    problem = CalibrationProblem.from_arrays(model, np.repeat(target, k, axis=0))
    t0 = time.process_time()
    sol = calibrate_pgd(
        problem,
        rng=options["rng"],
        n_starts=0,
        n_random_starts=TRIES_PER_END,
        max_iter=int(options["max_iter"]),
        keep_after=4,
        keep=1,
        ranges=False,
        retry_alpha=0.0,
        fit_tolerance=0.0,
    )
    cpu_s = time.process_time() - t0
    ends = surrogate_at(model, sol.x).reshape(n, k, len(LOAD_CASES), -1)
    fit_mae = np.nanmean(np.abs(ends - target[:, None]), axis=(2, 3))  # (n, k)
    err = np.abs(ends - world[:, None])[..., pred]  # (n, k, 4, p)
    pred_mae = np.nanmean(err, axis=(2, 3))
    truth_fit = np.nanmean(np.abs(world - target), axis=(1, 2))  # (n,): the noise's MAE
    equal = fit_mae <= truth_fit[:, None] + EQUAL_FIT_MARGIN_DEG
    best = np.argmin(fit_mae, axis=1)
    masked = np.where(equal, pred_mae, np.nan)
    lc = np.where(equal[..., None], np.nanmean(err, axis=3), np.nan)  # (n, k, 4)
    # one point estimate from all of them: the equally fitting ends' mean in unit coordinates
    v = model.from_physical(sol.x).double().numpy().reshape(n, k, -1)
    w = np.where(equal | ~equal.any(axis=1, keepdims=True), 1.0, 0.0)[..., None]
    centre = surrogate_at(model, model.to_physical((v * w).sum(1) / w.sum(1)))
    return {
        "predict_mae_deg_equal_fit_centroid": float(
            np.nanmean(np.nanmean(np.abs(centre - world)[..., pred], axis=(1, 2)))
        ),
        "calibration_cpu_s": cpu_s,
        "n_equal_fit_mean": float(equal.sum(axis=1).mean()),
        "n_specimens_without_equal_fit": int((~equal.any(axis=1)).sum()),
        "truth_fit_mae_deg": float(truth_fit.mean()),
        "best_fit_mae_deg": float(fit_mae[np.arange(n), best].mean()),
        "predict_mae_deg_best_fit": float(pred_mae[np.arange(n), best].mean()),
        "predict_mae_deg_equal_fit_mean": float(np.nanmean(np.nanmean(masked, axis=1))),
        "predict_mae_deg_equal_fit_max": float(np.nanmean(np.nanmax(masked, axis=1))),
        "predict_mae_deg_equal_fit_per_load_case": {
            name: float(np.nanmean(np.nanmean(lc[..., j], axis=1)))
            for j, name in enumerate(LOAD_CASES)
        },
    }


def identifiability_oracle(
    inp: Inputs, model: Any, n_starts: int, seed: int, options: Mapping[str, Any]
) -> dict[str, Any]:
    """Oracle 2 (module docstring): the surrogate as the world, each variant's targets fitted
    by :func:`world_fits`; then ``options["noise_draws"]`` further draws of noise of sd
    ``options["noise_deg"]`` (seeds ``[seed, 43, 1..]``), to show how the noisy figure varies
    with the draw. ``options["max_iter"]``: Gauss-Newton iterations."""
    fit, pred = bands(inp.moments, inp.split_nm)
    world = np.where(np.isfinite(inp.truth), surrogate_at(model, inp.x_true), np.nan)
    fitted = np.where(fit, world, np.nan)
    out: dict[str, Any] = {"n_starts": n_starts, "seed": seed, **dict(options)}
    for k, variant in enumerate(VARIANTS):
        target = fitted + (inp.targets[variant] - np.where(fit, inp.truth, np.nan))
        run = {**options, "n_starts": n_starts, "rng": np.random.default_rng([seed, k])}
        out[variant] = world_fits(model, world, target, pred, run)
    draws = []
    for k in range(1, int(options["noise_draws"]) + 1):
        noise = np.random.default_rng([seed, 43, k]).normal(0.0, options["noise_deg"], world.shape)
        run = {**options, "n_starts": n_starts, "rng": np.random.default_rng([seed, 2, k])}
        draws.append(world_fits(model, world, fitted + noise, pred, run))
    if draws:
        best = np.array([d["predict_mae_deg_best_fit"] for d in draws])
        equal = np.array([d["predict_mae_deg_equal_fit_mean"] for d in draws])
        centroid = np.array([d["predict_mae_deg_equal_fit_centroid"] for d in draws])
        out["noise_draws_summary"] = {
            "predict_mae_deg_best_fit": best.tolist(),
            "predict_mae_deg_best_fit_mean": float(best.mean()),
            "predict_mae_deg_equal_fit_mean": equal.tolist(),
            "predict_mae_deg_equal_fit_mean_mean": float(equal.mean()),
            "share_best_fit_within_0_10": float((best <= 0.10).mean()),
            "predict_mae_deg_equal_fit_centroid": centroid.tolist(),
            "predict_mae_deg_equal_fit_centroid_mean": float(centroid.mean()),
        }
    return out


def store_cpu_hours(store: Path) -> dict[str, Any]:
    """CalculiX jobs in ``store`` and their CPU time, h (the solver's ``cpu_seconds``)."""
    from femcal.fe.store import load_records

    records = load_records(store)
    cpu = sum(float(r.get("cpu_seconds") or 0.0) for r in records)
    failed = sum(r["status"] != "ok" for r in records)
    return {"jobs": len(records), "failed": failed, "cpu_h": cpu / 3600}


def _f(value: Any) -> str:
    """A figure in degrees to three decimals, or a list of them."""
    if isinstance(value, Mapping):
        value = list(value.values())
    if isinstance(value, list):
        return ", ".join(f"{v:.3f}" for v in value)
    return f"{value:.3f}"


def markdown(fig: Mapping[str, Any]) -> str:
    """The figures as a markdown table (one column per variant), deg."""
    d, r, o = fig["decomposition"], fig.get("refine") or {}, fig["identifiability"]

    def pair(name: str) -> Any:
        return lambda v: " / ".join(
            _f(d[v][name][band]["mae_deg"]) for band in ("fit_1_5", "predict_5_10")
        )

    def at(src: Mapping[str, Any], *keys: str) -> Any:
        def cell(v: str) -> str:
            if v not in src:
                return "not run"
            value = src[v]
            for key in keys:
                value = value[key]
            return str(value) if isinstance(value, int) else _f(value)

        return cell

    rows = [
        ("predict stage: CalculiX at the surrogate's calibration vs truth", pair("fe_vs_truth")),
        (
            "surrogate vs CalculiX at the calibrated parameters",
            pair("surrogate_vs_fe_at_calibrated"),
        ),
        (
            "surrogate vs truth at the calibrated parameters",
            pair("surrogate_vs_truth_at_calibrated"),
        ),
        ("surrogate vs truth at the true parameters", pair("surrogate_vs_truth_at_true")),
        ("oracle 1: CalculiX runs per specimen at most", at(r, "max_fe_runs")),
        ("oracle 1: CalculiX fit to the 1-5 Nm points, start", at(r, "fe_fit_mae_deg_start")),
        ("oracle 1: the same, FE-refined", at(r, "fe_fit_mae_deg_refined")),
        ("oracle 1: CalculiX at the FE-refined parameters, 5.5-10 Nm", at(r, *PRED)),
        ("oracle 1: per load case (F, E, LB, AR)", at(r, "predictive", f"{PRED[1]}_per_load_case")),
        ("oracle 1: spread among equally fitting runs", at(r, "equal_fit_runs", SPREAD)),
        ("oracle 2 (surrogate as the world): best-fit end", at(o, f"{PRED[1]}_best_fit")),
        ("oracle 2: equally fitting ends, mean", at(o, f"{PRED[1]}_equal_fit_mean")),
        ("oracle 2: equally fitting ends, worst per specimen", at(o, f"{PRED[1]}_equal_fit_max")),
        ("oracle 2: their centroid (unit coordinates)", at(o, f"{PRED[1]}_equal_fit_centroid")),
        (
            "oracle 2: the mean per load case (F, E, LB, AR)",
            at(o, f"{PRED[1]}_equal_fit_per_load_case"),
        ),
        ("oracle 3: the true parameters (the Test curves are CalculiX there)", lambda v: "0"),
    ]
    lines = [
        "| MAE, deg (pairs: 1-5 / 5.5-10 Nm; one figure: 5.5-10 Nm) | noise-free | noise 0.05 |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {name} | {cell('clean')} | {cell('noisy')} |" for name, cell in rows]
    draws = o.get("noise_draws_summary")
    if draws:
        lines += [
            "",
            f"Oracle 2 over {len(draws['predict_mae_deg_best_fit'])} further noise draws: "
            f"best-fit end {_f(draws['predict_mae_deg_best_fit'])} (mean "
            f"{_f(draws['predict_mae_deg_best_fit_mean'])}; within 0.10 deg in "
            f"{draws['share_best_fit_within_0_10']:.0%} of the draws); equally fitting ends "
            f"{_f(draws['predict_mae_deg_equal_fit_mean'])}; their centroid "
            f"{_f(draws['predict_mae_deg_equal_fit_centroid'])} (mean "
            f"{_f(draws['predict_mae_deg_equal_fit_centroid_mean'])}).",
        ]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line (module docstring)."""
    from femcal.calibration.model import SurrogateCurveModel
    from femcal.tracking import load_surrogate

    parser = argparse.ArgumentParser(prog="python -m experiments.fe_predictive_ceiling")
    parser.add_argument("--fe-dir", type=Path, default=REPO / "fe")
    parser.add_argument("--model", default="models/surrogate-large", help="under --fe-dir")
    parser.add_argument(
        "--predictive-store",
        type=Path,
        default=REPO / "fe/data/predictive-campaign/runs.jsonl.gz",
    )
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--store", type=Path, default=OUT / "runs.jsonl.gz")
    parser.add_argument("--n-specimens", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0, help="the predict stage's noise seed")
    parser.add_argument(
        "--max-fe-runs",
        type=int,
        nargs=2,
        default=[2, 3],
        metavar=("CLEAN", "NOISY"),
        help="CalculiX runs per specimen at most, the first included (0: no refinement)",
    )
    parser.add_argument("--tol-deg", type=float, default=0.01)
    parser.add_argument("--starts", type=int, default=32)
    parser.add_argument("--max-iter", type=int, default=40)
    parser.add_argument("--noise-draws", type=int, default=8, help="oracle 2's further noise draws")
    args = parser.parse_args(argv)
    # a band without points (a specimen without an equally fitting end) is NaN, not a warning
    warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
    warnings.filterwarnings("ignore", "All-NaN slice encountered", RuntimeWarning)
    t0, c0 = time.perf_counter(), time.process_time()
    inp = read_inputs(args.fe_dir, args.predictive_store, args.n_specimens, args.seed)
    model = SurrogateCurveModel(load_surrogate(args.fe_dir / args.model), inp.moments)
    noise = json.loads((args.fe_dir / "reports/predictive.json").read_text())["noise_deg"]
    fig: dict[str, Any] = {
        "command": reproduce_command("fe_predictive_ceiling", argv),
        "n_specimens": len(inp.specimens),
        "split_nm": inp.split_nm,
        "equal_fit_margin_deg": EQUAL_FIT_MARGIN_DEG,
        "decomposition": decomposition(inp, model),
        "identifiability": identifiability_oracle(
            inp,
            model,
            args.starts,
            args.seed,
            {"max_iter": args.max_iter, "noise_draws": args.noise_draws, "noise_deg": noise},
        ),
        "refine": None,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    if max(args.max_fe_runs) > 0:
        runtime = fe_runtime_of(args.fe_dir, args.store)
        budget = dict(zip(VARIANTS, args.max_fe_runs))
        fig["refine"] = refine_oracle(inp, model, runtime, budget, args.tol_deg)
        fig["refine"]["store"] = store_cpu_hours(args.store)
    fig["wall_s"] = time.perf_counter() - t0
    fig["cpu_s_this_process"] = time.process_time() - c0
    (args.out / "ceiling.json").write_text(json.dumps(fig, indent=2) + "\n")
    (args.out / "ceiling.md").write_text(markdown(fig))
    print(markdown(fig))
    return fig


if __name__ == "__main__":
    main()
