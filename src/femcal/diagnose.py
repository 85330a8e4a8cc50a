"""Compare the model with measurements, show where it fails, find the missing effect.

For every specimen:

1. calibrate the disc alone (``pgd`` through the surrogate);
2. residuals per load case x moment against the noise level ``sigma``, where
   ``sigma^2 = noise_deg^2 + surrogate_error_deg^2``: the surrogate's own error counts as noise
   too, otherwise its misfit reads as missing physics;
3. calibrate the disc with each candidate effect (material and effect parameters jointly,
   inside all bounds), starting from the disc-alone solution and a grid over the effect's box;
4. rank the models by BIC with the known noise, ``chi^2 / sigma^2 + k ln n``: an extra
   parameter must buy ``ln n`` of chi-square, so flexibility alone does not win;
5. verdict: the best effect if it beats the disc alone by at least ``min_delta`` (BIC units;
   10 = "very strong" evidence), otherwise ``none``.

The effect parameters come with linearised standard deviations from the Jacobian at the optimum.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from femcal.calibration.base import CalibrationProblem
from femcal.calibration.model import CurveModel
from femcal.calibration.pgd import gauss_newton, pgd
from femcal.effects.base import available_effects
from femcal.effects.composite import EffectModel
from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)

NONE = "none"


@dataclass
class SpecimenDiagnosis:
    """Diagnosis of one specimen (see :func:`diagnose`)."""

    specimen: str
    verdict: str
    baseline_mae_deg: float
    ranking: list[dict[str, Any]]
    residuals: np.ndarray  # (4, m) disc-alone residual, measured - model, deg (NaN: missing)
    failures: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "specimen": self.specimen,
            "verdict": self.verdict,
            "baseline_mae_deg": self.baseline_mae_deg,
            "ranking": self.ranking,
            "failures": self.failures,
        }


@dataclass
class Diagnosis:
    """Diagnosis of a cohort."""

    specimens: list[SpecimenDiagnosis]
    sigma_deg: float
    noise_deg: float
    noise_sd_deg: float
    surrogate_error_deg: float
    moments: np.ndarray
    seconds: float

    def verdicts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in self.specimens:
            out[s.verdict] = out.get(s.verdict, 0) + 1
        return out

    def cohort_verdict(self) -> str:
        """The most frequent verdict other than ``none`` if it covers at least a quarter of
        the cohort, else ``none``."""
        counts = {k: v for k, v in self.verdicts().items() if k != NONE}
        if not counts:
            return NONE
        best = max(counts, key=counts.get)
        return best if counts[best] >= 0.25 * len(self.specimens) else NONE

    def to_dict(self) -> dict[str, Any]:
        return {
            "sigma_deg": self.sigma_deg,
            "noise_deg": self.noise_deg,
            "noise_sd_deg": self.noise_sd_deg,
            "surrogate_error_deg": self.surrogate_error_deg,
            "cohort_verdict": self.cohort_verdict(),
            "verdicts": self.verdicts(),
            "seconds": self.seconds,
            "specimens": [s.to_dict() for s in self.specimens],
        }


def _fit(problem: CalibrationProblem, v0: torch.Tensor, rows: torch.Tensor, max_iter: int):
    v, _, _ = gauss_newton(problem, v0, rows, max_iter=max_iter, loss="l2", tol=1e-6)
    with torch.no_grad():
        pred = problem.model.curves(v)
    r = ((pred - problem.target[rows]) * problem.mask[rows]).reshape(len(rows), -1)
    rss = (problem.weight[rows].reshape(len(rows), -1) * r**2).sum(1)
    # A fit that left the surrogate's valid range (non-finite curves) cannot win.
    return v, pred, torch.nan_to_num(rss, nan=float("inf"), posinf=float("inf"))


def _effect_grid(n_params: int, levels: Sequence[float]) -> torch.Tensor:
    grids = np.meshgrid(*[levels] * n_params, indexing="ij")
    return torch.tensor(np.stack([g.reshape(-1) for g in grids], 1), dtype=torch.float32)


def _failures(
    resid: np.ndarray, sigma: float, moments: np.ndarray, x_unit: np.ndarray, names: Sequence[str]
) -> dict[str, Any]:
    """Where the disc alone fails: points beyond 2 sigma, sign runs, parameters on bounds."""
    z = resid / sigma
    out: dict[str, Any] = {"beyond_2_sigma": [], "sign_pattern": {}, "on_bounds": []}
    for j, lc in enumerate(LOAD_CASES):
        ok = np.isfinite(z[j])
        if not ok.any():
            continue
        bad = ok & (np.abs(z[j]) > 2)
        if bad.any():
            out["beyond_2_sigma"].append(
                {
                    "load_case": lc,
                    "moments_nm": moments[bad].tolist(),
                    "max_abs_z": float(np.max(np.abs(z[j][ok]))),
                }
            )
        signs = "".join("+" if v > 0 else "-" for v in resid[j][ok])
        out["sign_pattern"][lc] = signs
    out["on_bounds"] = [n for n, u in zip(names, x_unit) if u < 1e-3 or u > 1 - 1e-3]
    return out


def diagnose(
    base: CurveModel,
    rom_deg: np.ndarray,
    *,
    specimens: Sequence[str],
    noise_deg: float | None = None,
    surrogate_error_deg: float = 0.0,
    candidates: Sequence[str] | None = None,
    start_bank: np.ndarray | None = None,
    min_delta: float = 10.0,
    max_iter: int = 25,
    effect_levels: Sequence[float] = (0.15, 0.5, 0.85),
    seed: int = 0,
) -> Diagnosis:
    """Diagnose every specimen (see the module docstring).

    Parameters
    ----------
    base : CurveModel
        The disc surrogate on the measurement's moment grid.
    rom_deg : ndarray, shape (n, 4, m)
        Measured RoM, NaN where not measured.
    specimens : sequence of str, length n
    noise_deg : float, optional
        Measurement noise (sd, deg). Estimated from the cohort's disc-alone residuals when
        omitted (pooled chi-square of the best model per specimen).
    surrogate_error_deg : float
        The surrogate's own error (sd, deg), added in quadrature to the noise.
    candidates : sequence of str, optional
        Effects to try (default: every registered effect).
    start_bank : ndarray, shape (N, 13), optional
        Training configurations for the disc-alone starts.
    min_delta : float
        BIC improvement an effect needs over the disc alone.
    max_iter : int
        Gauss-Newton iterations per fit.
    effect_levels : sequence of float
        Unit-box levels of the effect parameters' start grid.
    seed : int

    Returns
    -------
    Diagnosis
    """
    t0 = time.perf_counter()
    candidates = list(available_effects() if candidates is None else candidates)
    rng = np.random.default_rng(seed)
    n = len(specimens)
    disc_problem = CalibrationProblem.from_arrays(base, rom_deg)
    n_points = disc_problem.mask.reshape(n, -1).sum(1).double()
    disc = pgd(
        disc_problem,
        rng=rng,
        start_bank=start_bank,
        max_iter=max_iter,
        fit_tolerance=0.0,
        ranges=False,
        n_starts=8,
        keep_after=3,
        keep=2,
    )
    x_disc = disc.x
    v_disc = base.from_physical(x_disc)
    with torch.no_grad():
        pred0 = base.curves(v_disc)
    r0 = ((pred0 - disc_problem.target) * disc_problem.mask).reshape(n, -1)
    rss0 = (r0**2).sum(1).double()
    k0 = base.dim
    fits: dict[str, dict[str, Any]] = {}
    for name in candidates:
        model = EffectModel(base, [name])
        problem = CalibrationProblem.from_arrays(model, rom_deg)
        grid = _effect_grid(model.dim - base.dim, effect_levels)
        g = len(grid)
        v0 = torch.cat([v_disc.repeat_interleave(g, 0), grid.repeat(n, 1)], 1)
        rows = torch.arange(n).repeat_interleave(g)
        v, _, rss = _fit(problem, v0, rows, max_iter)
        best = rss.reshape(n, g).argmin(1)
        flat = torch.arange(n) * g + best
        fits[name] = {
            "model": model,
            "problem": problem,
            "v": v[flat],
            "rss": rss.reshape(n, g).gather(1, best[:, None])[:, 0].double(),
        }
    # Noise: given, or the pooled reduced chi-square of the best model per specimen.
    if noise_deg is None:
        best_rss = torch.stack([rss0] + [f["rss"] for f in fits.values()]).min(0).values
        dof = float((n_points - k0 - 2).clamp_min(1).sum())
        total_var = float(best_rss.sum()) / dof
        noise_var = max(total_var - surrogate_error_deg**2, 1e-12)
        noise_deg_used = float(np.sqrt(noise_var))
        noise_sd = noise_deg_used / np.sqrt(2 * dof)
    else:
        if noise_deg <= 0:
            raise ConfigError(f"noise_deg must be > 0; got {noise_deg}.")
        noise_deg_used, noise_sd = float(noise_deg), 0.0
    sigma = float(np.sqrt(noise_deg_used**2 + surrogate_error_deg**2))
    log_n = torch.log(n_points)
    bic0 = rss0 / sigma**2 + k0 * log_n
    out = []
    measured = disc_problem.measured
    moments = base.moments.double().numpy()
    mae0 = (r0.abs().sum(1) / n_points).numpy()
    unit_disc = base.space.to_unit(x_disc)
    for i, spec in enumerate(specimens):
        ranking = [
            {
                "effect": NONE,
                "mae_deg": float(mae0[i]),
                "criterion": float(bic0[i]),
                "parameters": {},
            }
        ]
        for name, f in fits.items():
            model = f["model"]
            vi = f["v"][i : i + 1]
            k = model.dim
            bic = float(f["rss"][i] / sigma**2 + k * log_n[i])
            with torch.no_grad():
                pred = model.curves(vi)
            mask = f["problem"].mask[i : i + 1]
            mae = float(((pred - f["problem"].target[i : i + 1]).abs() * mask).sum() / mask.sum())
            x = model.to_physical(vi.double().numpy())[0]
            _, jac = model.curves_jacobian(vi)
            jj = (jac.reshape(1, -1, k) * mask.reshape(1, -1, 1))[0].double()
            finite = bool(torch.isfinite(jj).all())
            jj = torch.nan_to_num(jj, nan=0.0, posinf=0.0, neginf=0.0)
            cov_u = torch.linalg.pinv(jj.T @ jj / sigma**2 + torch.eye(k, dtype=torch.float64))
            params = {}
            eff = model.effects[0]
            for j, par in enumerate(eff.parameters):
                col = base.dim + j
                sd_u = float(cov_u[col, col].clamp_min(0).sqrt()) if finite else float("nan")
                # d physical / d unit at the estimate (log or linear scale)
                if par.log:
                    scale = x[col] * np.log(par.upper / par.lower)
                else:
                    scale = par.upper - par.lower
                params[par.name] = {"value": float(x[col]), "sd": sd_u * scale, "unit": par.unit}
            ranking.append({"effect": name, "mae_deg": mae, "criterion": bic, "parameters": params})
        ranking.sort(key=lambda r: r["criterion"])
        best = ranking[0]
        verdict = best["effect"]
        if verdict != NONE and float(bic0[i]) - best["criterion"] < min_delta:
            verdict = NONE
        resid = measured[i] - pred0[i].double().numpy()
        out.append(
            SpecimenDiagnosis(
                specimen=str(spec),
                verdict=verdict,
                baseline_mae_deg=float(mae0[i]),
                ranking=ranking,
                residuals=np.where(np.isfinite(measured[i]), resid, np.nan),
                failures=_failures(resid, sigma, moments, unit_disc[i], base.space.names),
            )
        )
    return Diagnosis(
        specimens=out,
        sigma_deg=sigma,
        noise_deg=noise_deg_used,
        noise_sd_deg=float(noise_sd),
        surrogate_error_deg=float(surrogate_error_deg),
        moments=moments,
        seconds=time.perf_counter() - t0,
    )
