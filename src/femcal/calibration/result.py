"""The front function :func:`calibrate` and what it returns, a :class:`CalibrationResult`.

:func:`calibrate` runs a registered calibrator (:mod:`femcal.calibration.base`) on a batch of
specimens, times it, and evaluates the solution through the surrogate.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from femcal.calibration.base import (
    CalibrationProblem,
    Solution,
    chi2_p_value,
    get_calibrator,
)
from femcal.calibration.model import CurveModel
from femcal.calibration.progress import specimen_bar
from femcal.errors import InputDataError
from femcal.metrics import curve_metrics
from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)


@dataclass
class CalibrationResult:
    """Calibrated parameters of a batch of specimens, with their fit through the surrogate.

    Attributes
    ----------
    x : ndarray, shape (n, d)
        Calibrated parameters in physical units.
    fun : ndarray, shape (n,)
        Surrogate-evaluated MAE in degrees (the same as ``mae_deg``).
    success : ndarray of bool, shape (n,)
    message : str
    nit : int
    method : str
    specimens : tuple of str, length n
    parameter_names : tuple of str, length d
    moments : ndarray, shape (m,)
    measured, prediction : ndarray, shape (n, 4, m)
        Measured RoM (NaN = not measured) and the surrogate's RoM at ``x``.
    mae_deg, r2_mean : ndarray, shape (n,)
    mae_per_load_case, r2_per_load_case : ndarray, shape (n, 4)
        NaN for a load case without measurements.
    exceedance : ndarray, shape (n,)
        The study's sum of values beyond the bounds in normalised units (0 = feasible).
    seconds : float
        Wall time of the whole batch (model loading excluded).
    x_low, x_high : ndarray, shape (n, d), optional
        Identifiability ranges of the near-optimal solutions.
    info : dict
    error_scale_deg : ndarray, shape (n,), optional
        Each specimen's error sd (deg) of a point of average weight, where the weights were
        inverse variances (:func:`calibrate`'s ``weight_sd``, e.g. ``femcal calibrate
        --noise-deg``: the noise and the surrogate's error); None otherwise.
    chi2 : ndarray, shape (n,), optional
        With ``error_scale_deg``: the sum over each specimen's measured points of its squared
        residuals in units of the point's own sd, ``sum_k ((measured - prediction) / sd_k)^2``
        with ``sd_k = error_scale_deg / sqrt(normalised weight_k)``.
    n_points : ndarray of int, shape (n,), optional
        With ``chi2``: each specimen's measured points (those of weight > 0).
    n_effective : ndarray, shape (n,), optional
        With ``chi2``: each specimen's effective number of fitted parameters at ``x``
        (:meth:`CalibrationProblem.effective_parameters`), which the residuals' degrees of
        freedom lose (``n_points - n_effective``, :attr:`p_value`).
    """

    x: np.ndarray
    fun: np.ndarray
    success: np.ndarray
    message: str
    nit: int
    method: str
    specimens: tuple[str, ...]
    parameter_names: tuple[str, ...]
    moments: np.ndarray
    measured: np.ndarray
    prediction: np.ndarray
    mae_deg: np.ndarray
    r2_mean: np.ndarray
    mae_per_load_case: np.ndarray
    r2_per_load_case: np.ndarray
    exceedance: np.ndarray
    seconds: float
    x_low: np.ndarray | None = None
    x_high: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)
    error_scale_deg: np.ndarray | None = None
    chi2: np.ndarray | None = None
    n_points: np.ndarray | None = None
    n_effective: np.ndarray | None = None

    @property
    def rms_z(self) -> np.ndarray | None:
        """Each specimen's RMS residual in units of its points' sd, ``sqrt(chi2 / n_points)``,
        shape (n,); about 1 where the model explains the data within the noise (a little less,
        as the fit absorbs some of it); None without an error scale."""
        if self.chi2 is None or self.n_points is None:
            return None
        return np.sqrt(self.chi2 / np.maximum(self.n_points, 1))

    @property
    def p_value(self) -> np.ndarray | None:
        """Each specimen's chi-square p-value, shape (n,): small where its residuals exceed
        what the noise explains. The degrees of freedom are the points less the fit's
        effective parameters (:attr:`n_effective`, as ``femcal diagnose`` counts them), or the
        points where those are not known (conservative). None without an error scale."""
        if self.chi2 is None or self.n_points is None:
            return None
        return chi2_p_value(self.chi2, self.dof)

    @property
    def dof(self) -> np.ndarray | None:
        """The residuals' degrees of freedom, shape (n,): ``n_points - n_effective`` (or
        ``n_points`` without :attr:`n_effective`), at least 1; None without an error scale."""
        if self.n_points is None:
            return None
        used = 0.0 if self.n_effective is None else self.n_effective
        return np.maximum(self.n_points - used, 1.0)

    def parameters_frame(self) -> pd.DataFrame:
        """``specimen`` + the d parameters in physical units, one row per specimen."""
        df = pd.DataFrame(self.x, columns=list(self.parameter_names))
        df.insert(0, "specimen", list(self.specimens))
        return df

    def metrics_frame(self) -> pd.DataFrame:
        """Per-specimen metrics: specimen, method, mae_deg, r2_mean, per load case, exceedance,
        success, missing_load_cases; with an error scale also ``error_scale_deg``,
        ``rms_z``, ``dof`` and ``p_value`` (:attr:`rms_z`, :attr:`dof`, :attr:`p_value`)."""
        df = pd.DataFrame(
            {
                "specimen": list(self.specimens),
                "method": self.method,
                "mae_deg": self.mae_deg,
                "r2_mean": self.r2_mean,
            }
        )
        for j, lc in enumerate(LOAD_CASES):
            df[f"mae_{lc}"] = self.mae_per_load_case[:, j]
            df[f"r2_{lc}"] = self.r2_per_load_case[:, j]
        df["exceedance"] = self.exceedance
        df["success"] = self.success
        measured = np.isfinite(self.measured).any(axis=2)
        df["missing_load_cases"] = [
            ";".join(lc for j, lc in enumerate(LOAD_CASES) if not measured[i, j])
            for i in range(len(self.specimens))
        ]
        if self.error_scale_deg is not None and self.chi2 is not None:
            df["error_scale_deg"] = self.error_scale_deg
            df["rms_z"] = self.rms_z
            df["dof"] = self.dof
            df["p_value"] = self.p_value
        return df

    def ranges_frame(self) -> pd.DataFrame | None:
        """Identifiability ranges, long format: specimen, parameter, value, low, high, and the
        range width in normalised units; None when the calibrator gives no ranges."""
        if self.x_low is None or self.x_high is None:
            return None
        n, d = self.x.shape
        width = np.asarray(self.info.get("space_width", np.ones(d)), dtype=float)
        return pd.DataFrame(
            {
                "specimen": np.repeat(list(self.specimens), d),
                "parameter": np.tile(list(self.parameter_names), n),
                "value": self.x.reshape(-1),
                "low": self.x_low.reshape(-1),
                "high": self.x_high.reshape(-1),
                "width_normalised": ((self.x_high - self.x_low) / width).reshape(-1),
            }
        )


def calibrate(
    model: CurveModel,
    rom_deg: np.ndarray,
    *,
    specimens: Sequence[str] | None = None,
    weight: np.ndarray | None = None,
    method: str = "pgd",
    seed: int | np.random.Generator = 0,
    chunk_size: int | None = None,
    progress: bool = False,
    options: Mapping[str, Any] | None = None,
    weight_sd: float | None = None,
) -> CalibrationResult:
    """Calibrate a batch of specimens against the surrogate.

    Parameters
    ----------
    model : CurveModel
        The surrogate on the measurement's moment grid.
    rom_deg : ndarray, shape (n, 4, m)
        Measured RoM in degrees, NaN where not measured.
    specimens : sequence of str, length n, optional
        Names (default "0", "1", ...).
    weight : ndarray, shape (n, 4, m), optional
        Weights of the points (default 1).
    method : str
        A registered calibrator (:func:`available_calibrators`).
    seed : int or numpy.random.Generator
        Seeds every random draw; the same seed gives the same result.
    chunk_size : int, optional
        Specimens per call of the calibrator (bounds memory; the progress bar advances per
        chunk). Default: the whole batch.
    progress : bool
        Show a progress bar over the specimens (:func:`~femcal.calibration.progress.
        specimen_bar`: from 2 s on, with the step a chunk is at).
    options : mapping, optional
        Keyword options of the calibrator.
    weight_sd : float, optional
        ``weight`` are inverse variances relative to a point of this sd (deg): each specimen
        then has its own error scale (:attr:`CalibrationProblem.point_sd`), which ``pgd``
        counts in its ranges and fit tolerance instead of its ``noise_deg`` option.

    Returns
    -------
    CalibrationResult
    """
    fn = get_calibrator(method)
    problem = CalibrationProblem.from_arrays(model, rom_deg, weight, weight_sd=weight_sd)
    n = problem.n_specimens
    names = tuple(str(i) for i in range(n)) if specimens is None else tuple(map(str, specimens))
    if len(names) != n:
        raise InputDataError(f"Got {len(names)} specimen names for {n} specimens.")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    chunk = n if not chunk_size else max(1, int(chunk_size))
    model.n_evaluations = 0
    start = time.perf_counter()
    parts: list[Solution] = []
    with specimen_bar(n, f"calibrate ({method})", enabled=progress and n > 1) as bar:
        for lo in range(0, n, chunk):
            part = problem.subset(slice(lo, lo + chunk))
            parts.append(fn(part, rng=rng, **dict(options or {})))
            if bar is not None:
                bar.update(min(chunk, n - lo))
    seconds = time.perf_counter() - start
    sol = _concat(parts)
    return evaluate_solution(model, problem, sol, names, method=method, seconds=seconds)


def _concat(parts: list[Solution]) -> Solution:
    if len(parts) == 1:
        return parts[0]
    ranges = all(p.x_low is not None for p in parts)
    return Solution(
        x=np.concatenate([p.x for p in parts]),
        nit=max(p.nit for p in parts),
        success=np.concatenate([p.success for p in parts]),
        message=parts[0].message,
        x_low=np.concatenate([p.x_low for p in parts]) if ranges else None,
        x_high=np.concatenate([p.x_high for p in parts]) if ranges else None,
        info={
            **parts[0].info,
            "n_chunks": len(parts),
            # counts of specimens (pgd's refits) add up over the chunks
            **{
                key: sum(int(p.info.get(key, 0)) for p in parts)
                for key in ("n_refitted", "n_refit_improved")
                if key in parts[0].info
            },
        },
    )


def evaluate_solution(
    model: CurveModel,
    problem: CalibrationProblem,
    sol: Solution,
    specimens: tuple[str, ...],
    *,
    method: str,
    seconds: float,
) -> CalibrationResult:
    """Evaluate calibrated parameters through the surrogate into a :class:`CalibrationResult`."""
    space = model.space
    x = np.asarray(sol.x, dtype=float)
    # An unprojected ablation may leave the box: it is evaluated where it stands.
    pred = model.predict(x, clip=False)
    measured = problem.measured
    m = curve_metrics(measured, pred)
    info = dict(sol.info)
    info["space_width"] = space.width.tolist()
    info["n_evaluations"] = int(model.n_evaluations)
    scale = chi2 = n_points = n_effective = None
    if problem.point_sd is not None:  # residuals in units of each point's own sd
        scale = problem.point_sd.double().numpy()
        chi2, n_points = problem.chi2(pred)
        n_effective = problem.effective_parameters(x)
    return CalibrationResult(
        x=x,
        fun=m["mae"],
        success=np.asarray(sol.success, dtype=bool),
        message=sol.message,
        nit=int(sol.nit),
        method=method,
        specimens=specimens,
        parameter_names=tuple(space.names),
        moments=model.moments.double().numpy(),
        measured=measured,
        prediction=pred,
        mae_deg=m["mae"],
        r2_mean=m["r2_mean"],
        mae_per_load_case=m["mae_per_load_case"],
        r2_per_load_case=m["r2_per_load_case"],
        exceedance=space.exceedance(x),
        seconds=float(seconds),
        x_low=sol.x_low,
        x_high=sol.x_high,
        info=info,
        error_scale_deg=scale,
        chi2=chi2,
        n_points=n_points,
        n_effective=n_effective,
    )
