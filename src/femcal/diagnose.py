"""Compare the model with measurements, show where it fails, find what is missing.

For every specimen:

1. calibrate the disc alone (``pgd`` through the surrogate); residuals against the noise
   ``sigma(M)^2 = noise^2 + surrogate_error(M)^2`` (the surrogate's own error counts as noise,
   larger beyond its trained moments, otherwise its misfit reads as missing physics);
2. **forward selection** of registered effects: fit the disc with each candidate (material and
   effect parameters jointly, inside all bounds, from the current solution and a grid over the
   new effect's box; a first effect also from the disc-and-effect combinations nearest the
   specimen's curves, because the disc fitted alone has bent towards the missing physics), add
   the one with the lowest BIC (``chi^2 + k ln n`` with the known noise) if it beats the current
   model by ``min_delta`` (10 = "very strong" evidence), and go on while the model does not
   explain the data and another effect pays (a model that holds an effect and still does not
   explain the data takes a further effect at a lower bar, ``min_delta_inadequate``: the data
   already say that something more is missing); a further effect also starts from the
   combination's own bank of disc-and-effect starts, not only from the fit it extends;
2a. **backward check** (stepwise selection): each effect of a combination must still lower the
   BIC given the others, the sub-model refitted from the combination's solution (an effect
   enters at ``min_delta`` and leaves below ``backward_delta``);
2b. **open world**: where the chosen model still does not explain the data, each of its effects
   must also pay beyond a smooth discrepancy: every model (with and without the effect) gets the
   GP discrepancy it needs (type-II maximum likelihood per load case, capped in the dropped
   effect's own load cases at ``elimination_cap`` times what the model with it needed there)
   and the models compare by ``-2 log`` marginal likelihood ``+ k ln n``; an effect that only let
   the disc bend towards physics nobody registered is dropped (backward elimination), one that
   explains its own load cases stays;
3. **adequacy** of the chosen model: is its ``chi^2`` consistent with the noise (p-value with the
   effective degrees of freedom, ``n - trace(hat matrix)``), and are its residuals free of long
   runs of one sign per load case (Wald-Wolfowitz)? If not, the verdict says ``unexplained``
   (alone, or after the effects that helped: ``facet_contact+unexplained``); ``none`` only when
   the disc alone explains the data;
4. **what is missing**: a smooth Gaussian-process discrepancy in rotation per load case, fitted
   jointly with the chosen model (:mod:`femcal.discrepancy`), described in words (load cases,
   laxity or stiffening, from which moment, how large) and compared with each registered
   effect's signature;
5. **what to measure next**: when the runner-up model is within ``min_delta`` of the best, the
   load case and moment where their predictions differ most, in sigma.

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
from femcal.calibration.model import CurveModel, SurrogateCurveModel
from femcal.calibration.pgd import gauss_newton, pgd
from femcal.calibration.starts import effect_bank, nearest_starts, single_effect_starts
from femcal.discrepancy import (
    dense_grid,
    describe,
    discrepancy_posterior,
    fit_discrepancy,
    runs_p_value,
    similarity,
)
from femcal.effects.base import available_effects, get_effect
from femcal.effects.composite import EffectModel
from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)

NONE = "none"
UNEXPLAINED = "unexplained"
#: Similarity (cosine, in sigma units) above which a discrepancy "resembles" an effect.
RESEMBLES = 0.8


def verdict_label(effects: Sequence[str], adequate: bool) -> str:
    """``none``, ``unexplained``, ``a+b`` or ``a+b+unexplained``."""
    parts = list(effects)
    if not adequate:
        parts.append(UNEXPLAINED)
    return "+".join(parts) if parts else NONE


def model_label(effects: Sequence[str]) -> str:
    """A fitted model's name in rankings and plots: ``none`` (the disc alone) or ``a+b``."""
    return "+".join(effects) if effects else NONE


@dataclass
class SpecimenDiagnosis:
    """Diagnosis of one specimen (see :func:`diagnose`).

    Attributes
    ----------
    verdict : str
        ``none``, ``unexplained``, the effects found joined by ``+``, possibly ending in
        ``+unexplained``.
    effects : list of str
        The registered effects found, in the order forward selection added them.
    adequate : bool
        The final model explains the data within the noise.
    ranking : list of dict
        Every model fitted (``effect`` = its label, ``effects``, ``mae_deg``, ``criterion``
        (BIC), ``parameters`` of its effects ± sd), best first.
    residuals : ndarray, shape (4, m)
        Disc-alone residuals, measured - model (deg, NaN where not measured).
    final_residuals : ndarray, shape (4, m)
        The same for the final model.
    curves : dict
        ``moments`` (q,) over the specimen's own measured range and the continuous curves
        (4, q) of the disc alone (``none``) and of the final model (its label).
    discrepancy : dict or None
        ``mean``, ``sd`` (4, q) on ``curves["moments"]``, ``mae_deg`` (model + discrepancy),
        ``amplitude_deg``, ``description`` (sentences), ``similarity`` (effect -> cosine),
        ``resembles`` (an effect name or None), ``model`` (the label it sits on).
    next_measurement : dict or None
        Where the two closest explanations differ most.
    """

    specimen: str
    verdict: str
    baseline_mae_deg: float
    ranking: list[dict[str, Any]]
    residuals: np.ndarray
    failures: dict[str, Any] = field(default_factory=dict)
    effects: list[str] = field(default_factory=list)
    adequate: bool = True
    adequacy: dict[str, Any] = field(default_factory=dict)
    final_mae_deg: float = float("nan")
    final_residuals: np.ndarray | None = None
    curves: dict[str, Any] = field(default_factory=dict)
    discrepancy: dict[str, Any] | None = None
    next_measurement: dict[str, Any] | None = None

    @property
    def discrepancy_mae_deg(self) -> float | None:
        return None if self.discrepancy is None else self.discrepancy["mae_deg"]

    @property
    def final_label(self) -> str:
        return model_label(self.effects)

    def to_dict(self) -> dict[str, Any]:
        disc = None
        if self.discrepancy is not None:
            disc = {
                k: v
                for k, v in self.discrepancy.items()
                if k not in ("mean", "sd") and not isinstance(v, np.ndarray)
            }
        return {
            "specimen": self.specimen,
            "verdict": self.verdict,
            "effects": list(self.effects),
            "adequate": bool(self.adequate),
            "adequacy": self.adequacy,
            "baseline_mae_deg": self.baseline_mae_deg,
            "final_mae_deg": self.final_mae_deg,
            "ranking": self.ranking,
            "discrepancy": disc,
            "next_measurement": self.next_measurement,
            "failures": self.failures,
        }


@dataclass
class Diagnosis:
    """Diagnosis of a cohort.

    ``sigma_deg`` is the noise sd inside the surrogate's trained moments; ``sigma_by_moment``
    (m,) the sd at each moment of the grid (larger where the surrogate extrapolates).
    """

    specimens: list[SpecimenDiagnosis]
    sigma_deg: float
    noise_deg: float
    noise_sd_deg: float
    surrogate_error_deg: float
    moments: np.ndarray
    seconds: float
    sigma_by_moment: np.ndarray | None = None
    alpha: float = 0.01

    def verdicts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in self.specimens:
            out[s.verdict] = out.get(s.verdict, 0) + 1
        return out

    def effect_counts(self) -> dict[str, int]:
        """How many specimens name each registered effect, and ``unexplained``."""
        out: dict[str, int] = {}
        for s in self.specimens:
            for e in [*s.effects, *([] if s.adequate else [UNEXPLAINED])]:
                out[e] = out.get(e, 0) + 1
        return out

    def found_effects(self) -> list[str]:
        """Registered effects named for at least one specimen, most frequent first."""
        counts = {k: v for k, v in self.effect_counts().items() if k != UNEXPLAINED}
        return sorted(counts, key=lambda k: (-counts[k], k))

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
            "sigma_by_moment": None
            if self.sigma_by_moment is None
            else [float(s) for s in self.sigma_by_moment],
            "noise_deg": self.noise_deg,
            "noise_sd_deg": self.noise_sd_deg,
            "surrogate_error_deg": self.surrogate_error_deg,
            "alpha": self.alpha,
            "cohort_verdict": self.cohort_verdict(),
            "verdicts": self.verdicts(),
            "effects": self.effect_counts(),
            "seconds": self.seconds,
            "specimens": [s.to_dict() for s in self.specimens],
        }


# ------------------------------------------------------------------------ fitting helpers
def _weights(sigma: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Relative weights 1/sigma^2 of every point (the optimiser normalises them)."""
    return np.broadcast_to((sigma.min() / sigma) ** 2, shape)


def _chi2(pred: torch.Tensor, measured: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    r = (measured - pred.double().numpy()) / sigma
    return np.nansum(r**2, axis=(1, 2))


def _grid(
    model: EffectModel,
    new: str,
    levels: Sequence[float],
    shape_starts: int = 0,
    grid_shapes: bool = False,
) -> tuple[slice, torch.Tensor]:
    """Starts (g, p) for effect ``new`` of ``model`` and its slice
    (:func:`femcal.calibration.starts.single_effect_starts`)."""
    k = model.effect_names.index(new)
    return model._slices[k], single_effect_starts(
        model.effects[k], levels, shape_starts, grid_shapes
    )


def _starts(
    model: EffectModel,
    prev: Sequence[str],
    v_prev: torch.Tensor,
    new: str,
    levels,
    shape_starts: int = 0,
    grid_shapes: bool = False,
) -> torch.Tensor:
    """Starts (n * g, dim): the previous solution (disc + its effects) and a grid for ``new``."""
    n = v_prev.shape[0]
    sl_new, grid = _grid(model, new, levels, shape_starts, grid_shapes)
    g = len(grid)
    v0 = torch.empty((n, g, model.dim))
    v0[:, :, : model.n_disc] = v_prev[:, None, : model.n_disc]
    prev_model_slices = _slices_of(prev)
    for name, sl in zip(model.effect_names, model._slices):
        if name == new:
            v0[:, :, sl] = grid[None]
        else:
            a, b = prev_model_slices[name]
            v0[:, :, sl] = v_prev[:, None, model.n_disc + a : model.n_disc + b]
    return v0.reshape(n * g, model.dim)


def _slices_of(effects: Sequence[str]) -> dict[str, tuple[int, int]]:
    """Offsets of each effect's parameters after the disc's, in an EffectModel of ``effects``."""
    out, start = {}, 0
    for name in effects:
        p = len(get_effect(name).parameters)
        out[name] = (start, start + p)
        start += p
    return out


def _solutions(per_spec: list[dict], rows, effects: tuple[str, ...]) -> torch.Tensor:
    """Unit coordinates (len(rows), dim) of model ``effects`` fitted to specimens ``rows``."""
    return torch.stack([per_spec[i][effects][0].v[per_spec[i][effects][1]] for i in rows])


def _columns(n_disc: int, effects: Sequence[str], rest: Sequence[str]) -> list[int]:
    """Columns of an EffectModel of ``effects`` that an EffectModel of ``rest`` keeps."""
    offsets = _slices_of(effects)
    return list(range(n_disc)) + [n_disc + c for e in rest for c in range(*offsets[e])]


def _hat_trace_and_cov(jac: torch.Tensor, mask: np.ndarray, sigma: np.ndarray):
    """Effective number of parameters and the parameter covariance (unit box prior).

    ``jac`` (n, 4, m, d); returns trace (n,) and covariance (n, d, d) in unit coordinates.
    """
    n = jac.shape[0]
    d = jac.shape[-1]
    j = jac.double().numpy() / np.broadcast_to(sigma, mask.shape)[..., None]
    j = np.where(mask[..., None], np.nan_to_num(j, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    j = j.reshape(n, -1, d)
    info = np.einsum("npi,npj->nij", j, j)
    cov = np.linalg.inv(info + np.eye(d))
    trace = np.einsum("nij,nji->n", info, cov)
    return trace, cov


def _chi2_sf(x: float, k: float) -> float:
    """Survival function of the chi-square distribution (SciPy)."""
    from scipy.stats import chi2

    return float(chi2.sf(x, max(k, 1.0)))


@dataclass
class _Fit:
    effects: tuple[str, ...]
    model: Any
    v: torch.Tensor  # (r, dim) for the specimens ``rows``
    rows: np.ndarray  # specimen indices
    pred: torch.Tensor  # (r, 4, m)
    chi2: np.ndarray  # (r,)
    k: int
    trace: np.ndarray | None = None  # (r,) effective number of parameters
    cov: np.ndarray | None = None  # (r, dim, dim) parameter covariance, unit coordinates
    finite: np.ndarray | None = None  # (r,) the Jacobian is finite


def _fit_from(
    model, measured, weight, sigma, rows: np.ndarray, v0: torch.Tensor, g: int, max_iter: int
):
    """Gauss-Newton from ``g`` starts per specimen of ``rows``; the best start per specimen."""
    problem = CalibrationProblem.from_arrays(model, measured[rows], weight[rows])
    r = len(rows)
    idx = torch.arange(r).repeat_interleave(g)
    keep = {"keep_after": 3, "keep": 2} if g > 2 else {}
    v, _, _ = gauss_newton(problem, v0, idx, max_iter=max_iter, loss="l2", tol=1e-6, **keep)
    with torch.no_grad():
        pred = model.curves(v)
    chi2 = _chi2(pred, np.repeat(measured[rows], g, 0), sigma)
    chi2 = np.nan_to_num(chi2, nan=np.inf, posinf=np.inf).reshape(r, g)
    best = chi2.argmin(1)
    flat = torch.as_tensor(np.arange(r) * g + best)
    return v[flat], pred[flat], chi2[np.arange(r), best]


# ------------------------------------------------------------------------------ diagnose
def diagnose(
    base: CurveModel,
    rom_deg: np.ndarray,
    *,
    specimens: Sequence[str],
    noise_deg: float | None = None,
    surrogate_error_deg: float | np.ndarray = 0.0,
    candidates: Sequence[str] | None = None,
    start_bank: np.ndarray | None = None,
    min_delta: float = 10.0,
    alpha: float = 0.01,
    max_effects: int = 3,
    max_iter: int = 25,
    effect_levels: Sequence[float] = (0.15, 0.5, 0.85),
    discrepancy: bool = True,
    curve_points: int = 48,
    bank_starts: int = 4,
    bank_samples: int = 1024,
    bank_every_level: bool = True,
    backward: bool = True,
    backward_delta: float = 0.0,
    gp_amplitude: str = "ml",
    stop_when_adequate: bool = True,
    elimination_cap: float = 2.0,
    min_delta_inadequate: float = 2.0,
    grid_shapes: bool = True,
    shape_starts: int = 0,
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
        Measurement noise (sd, deg). Estimated from the cohort's residuals when omitted
        (pooled chi-square of the best model per specimen).
    surrogate_error_deg : float or ndarray, shape (m,)
        The surrogate's own error (sd, deg) at each moment of the grid (or one value),
        added in quadrature to the noise: larger beyond the trained moments
        (:meth:`femcal.moments.MomentPolicy.sigma_surrogate`).
    candidates : sequence of str, optional
        Effects to try (default: every registered effect).
    start_bank : ndarray, shape (N, 13), optional
        Training configurations for the disc-alone starts.
    min_delta : float
        BIC improvement an effect needs over the model without it.
    alpha : float
        Significance level of the adequacy tests (chi-square and runs): below it, the model
        does not explain the data.
    max_effects : int
        At most this many effects per specimen.
    max_iter : int
        Gauss-Newton iterations per fit.
    effect_levels : sequence of float
        Unit-box levels of the start grid over a new effect's parameters.
    grid_shapes : bool
        The start grid of a new effect also spans its shape parameters (``effect_levels`` over
        every parameter: 81 starts for facet contact, 27 for the others), not only the classic
        member: a law far from it (a soft contact onset, say) was not reached from there
        (measured in reports/bench_diagnose.md).
    shape_starts : int
        A new effect also starts from this many points of a Sobol design over all of its
        parameters (:func:`femcal.calibration.starts.shape_design`); measured: 16 of them found
        less than ``grid_shapes``.
    discrepancy : bool
        Fit the GP discrepancy and describe what is missing.
    curve_points : int
        Points of the continuous curves (log-spaced over the measured moments).
    bank_starts : int
        A single effect's fit also starts from the ``bank_starts`` disc-and-effect combinations
        (of ``bank_samples`` drawn from ``start_bank``,
        :func:`femcal.calibration.starts.effect_bank`)
        nearest each specimen's curves.
    bank_samples : int
    backward : bool
        After forward selection, each effect of a combination must still pay its criterion
        given the others (the sub-model refitted from the combination's solution); one that
        does not is dropped (stepwise selection).
    backward_delta : float
        What an effect of a combination must still gain (BIC) given the others to stay. An
        effect enters at ``min_delta`` (or ``min_delta_inadequate``) and leaves below this
        (stepwise selection's hysteresis: 0 = the criterion no longer improves).
    bank_every_level : bool
        Also for a further effect (the combination's bank): the disc fitted with one effect
        has bent towards the other, and the start from that fit missed combinations that a
        fresh calibration finds (hidden cohorts: facet + laxity fitted at MAE 0.10 deg instead
        of 0.036 deg; reports/bench_diagnose.md).
    gp_amplitude : {"ml", "misfit"}
        The discrepancy of the open-world elimination: each model's own type-II maximum
        likelihood amplitude, compared by marginal likelihood ("ml"), or one amplitude sized to
        the larger model's misfit, compared by generalised least squares ("misfit").
    min_delta_inadequate : float
        BIC improvement a further effect needs over a model that already holds an effect but
        does not explain the data (the adequacy test said something more is missing; the
        open-world elimination still checks that it pays beyond a smooth discrepancy).
    elimination_cap : float
        Open-world elimination: when an effect is dropped, the discrepancy in that effect's own
        load cases may be at most this factor times what the model with the effect needed
        there (0: no cap). Without a cap the smooth discrepancy takes over whatever an effect
        explained and real effects are dropped; elsewhere it stays free, so an effect that only
        compensated a disc bent towards unregistered physics is still dropped
        (reports/bench_diagnose.md).
    stop_when_adequate : bool
        Stop adding effects once the model explains the data (default; measured in
        reports/bench_diagnose.md: going on while an effect pays ``min_delta`` doubled the time
        and named one more combination in 16), or keep adding while an effect pays.
    seed : int

    Returns
    -------
    Diagnosis
    """
    t0 = time.perf_counter()
    candidates = list(available_effects() if candidates is None else candidates)
    for name in candidates:
        get_effect(name)  # unknown names fail before any work
    if not 0 < alpha < 1:
        raise ConfigError(f"diagnose: alpha must be in (0, 1); got {alpha}.")
    if not (elimination_cap == 0 or elimination_cap >= 1) or not np.isfinite(elimination_cap):
        raise ConfigError(
            "diagnose: elimination_cap must be >= 1 or 0 (no cap), a factor on the discrepancy "
            f"the larger model needed in the dropped effect's load cases; got {elimination_cap}."
        )
    if shape_starts < 0:
        raise ConfigError(f"diagnose: shape_starts must be >= 0; got {shape_starts}.")
    if not min_delta_inadequate >= 0:
        raise ConfigError(
            f"diagnose: min_delta_inadequate must be >= 0; got {min_delta_inadequate}."
        )
    if not 0 <= backward_delta <= min_delta:
        raise ConfigError(
            f"diagnose: backward_delta must be in [0, min_delta={min_delta}] (an effect leaves "
            f"a combination below what it needed to enter); got {backward_delta}."
        )
    if gp_amplitude not in ("ml", "misfit"):
        raise ConfigError(f"diagnose: gp_amplitude must be 'ml' or 'misfit'; got {gp_amplitude!r}.")
    rng = np.random.default_rng(seed)
    measured = np.where(np.isfinite(rom_deg), np.asarray(rom_deg, dtype=float), np.nan)
    n, _, m = measured.shape
    mask = np.isfinite(measured)
    n_points = mask.reshape(n, -1).sum(1).astype(float)
    log_n = np.log(np.maximum(n_points, 2.0))
    sur = np.broadcast_to(np.asarray(surrogate_error_deg, dtype=float), (m,)).copy()
    if np.any(~np.isfinite(sur)) or np.any(sur < 0):
        raise ConfigError(f"surrogate_error_deg must be finite and >= 0; got {sur.tolist()}.")
    moments = base.moments.double().numpy()

    # 1. The disc alone (its weights: 1/sigma^2 once the noise is known; flat before).
    def disc_fit(weight: np.ndarray):
        problem = CalibrationProblem.from_arrays(base, measured, weight)
        sol = pgd(
            problem,
            rng=rng,
            start_bank=start_bank,
            max_iter=max_iter,
            fit_tolerance=0.0,
            ranges=False,
            n_starts=8,
            keep_after=3,
            keep=2,
        )
        v = base.from_physical(sol.x)
        with torch.no_grad():
            return v, base.curves(v)

    if noise_deg is None:
        v_disc, pred0 = disc_fit(_weights(np.sqrt(0.05**2 + sur**2), measured.shape))
        r0 = np.where(mask, measured - pred0.double().numpy(), 0.0)
        dof = float(np.clip(n_points - base.dim / 2, 1, None).sum())
        total = float((r0**2).sum()) / dof
        noise_used = float(np.sqrt(max(total - float(np.mean(sur**2)), 1e-12)))
        noise_sd = noise_used / np.sqrt(2 * dof)
        logger.info("noise estimated from the disc-alone residuals: %.4f deg", noise_used)
    else:
        if not noise_deg > 0:
            raise ConfigError(f"noise_deg must be > 0; got {noise_deg}.")
        noise_used, noise_sd = float(noise_deg), 0.0
    sigma_m = np.sqrt(noise_used**2 + sur**2)  # (m,)
    sigma = np.broadcast_to(sigma_m, (len(LOAD_CASES), m))
    weight = np.ascontiguousarray(_weights(sigma_m, measured.shape))
    v_disc, pred0 = disc_fit(weight)
    all_rows = np.arange(n)
    fits: dict[tuple[str, ...], _Fit] = {
        (): _Fit((), base, v_disc, all_rows, pred0, _chi2(pred0, measured, sigma), base.dim)
    }
    models: dict[tuple[str, ...], EffectModel] = {}
    banks: dict[tuple[str, ...], tuple[torch.Tensor, torch.Tensor]] = {}

    def effect_model(effects: tuple[str, ...]) -> EffectModel:
        if effects not in models:
            models[effects] = EffectModel(base, list(effects))
        return models[effects]

    # 2. Forward selection, batched over the specimens that share a current model.
    chosen: list[tuple[str, ...]] = [() for _ in range(n)]
    per_spec: list[dict[tuple[str, ...], tuple[_Fit, int]]] = [
        {(): (fits[()], i)} for i in range(n)
    ]

    def bic_of(fit: _Fit, pos: int, i: int) -> float:
        return float(fit.chi2[pos] + fit.k * log_n[i])

    active = all_rows.copy()
    for _level in range(max_effects):
        if active.size == 0:
            break
        groups: dict[tuple[str, ...], list[int]] = {}
        for i in active:
            groups.setdefault(chosen[i], []).append(int(i))
        improved: list[int] = []
        for current, members in groups.items():
            rows = np.asarray(members)
            prev_fit, _ = per_spec[rows[0]][current]
            v_prev = _solutions(per_spec, rows, current)
            trials: dict[tuple[str, ...], _Fit] = {}
            for new in candidates:
                if new in current:
                    continue
                effects = tuple(sorted((*current, new)))
                model = effect_model(effects)
                _, grid = _grid(model, new, effect_levels, shape_starts, grid_shapes)
                v0 = _starts(model, current, v_prev, new, effect_levels, shape_starts, grid_shapes)
                g = len(grid)
                if start_bank is not None and bank_starts > 0 and (bank_every_level or not current):
                    # The disc fitted alone (or with one effect) has bent towards the missing
                    # physics: also start from the disc-and-effect combinations nearest each
                    # specimen's curves.
                    if effects not in banks:
                        banks[effects] = effect_bank(model, start_bank, rng, bank_samples)
                    problem = CalibrationProblem.from_arrays(model, measured[rows], weight[rows])
                    near = nearest_starts(problem, *banks[effects], bank_starts)  # (r, K)
                    v_near = banks[effects][0][near]  # (r, K, d)
                    v0 = torch.cat([v0.reshape(len(rows), g, -1), v_near], dim=1)
                    g = v0.shape[1]
                    v0 = v0.reshape(len(rows) * g, -1)
                v, pred, chi2 = _fit_from(model, measured, weight, sigma, rows, v0, g, max_iter)
                fit = _Fit(effects, model, v, rows, pred, chi2, model.dim)
                trials[effects] = fit
                for pos, i in enumerate(rows):
                    per_spec[i][effects] = (fit, pos)
            for i in rows:
                cur_fit, cur_pos = per_spec[i][current]
                cur_bic = bic_of(cur_fit, cur_pos, i)
                best_eff, best_bic = None, np.inf
                for effects in trials:
                    f, pos = per_spec[i][effects]
                    b = bic_of(f, pos, i)
                    if b < best_bic:
                        best_eff, best_bic = effects, b
                logger.debug(
                    "%s: forward from %s: BIC gains %s",
                    specimens[i],
                    current,
                    {e: round(cur_bic - bic_of(*per_spec[i][e], i), 1) for e in trials},
                )
                # A model shown not to explain the data needs something more: the next effect
                # only has to beat it by ``min_delta_inadequate`` (the elimination below keeps
                # an effect only if it pays beyond a smooth discrepancy).
                need = min_delta
                if current and not _adequate_quick(
                    cur_fit, cur_pos, i, measured, sigma, n_points, alpha
                ):
                    need = min_delta_inadequate
                if best_eff is not None and cur_bic - best_bic >= need:
                    chosen[i] = best_eff
                    improved.append(int(i))
        # Keep adding while it pays (or, with ``stop_when_adequate``, only where the chosen
        # model still does not explain the data).
        still = []
        for i in improved:
            f, pos = per_spec[i][chosen[i]]
            if not stop_when_adequate or not _adequate_quick(
                f, pos, i, measured, sigma, n_points, alpha
            ):
                still.append(i)
        active = np.asarray(still, dtype=int)

    # 2a. Backward check (stepwise selection): each effect of a combination must still pay
    # given the others. The sub-model, refitted from the combination's solution without that
    # effect, often fits far better than forward selection's fit of it did (there the disc had
    # bent towards the effect added first): a third effect that only made up for a poor fit
    # of the other two is dropped again.
    if backward:
        for _round in range(max_effects):
            groups = {}
            for i in range(n):
                if len(chosen[i]) >= 2:
                    groups.setdefault(chosen[i], []).append(i)
            dropped = 0
            for current, members in groups.items():
                rows = np.asarray(members)
                v_cur = _solutions(per_spec, rows, current)
                for drop in current:
                    rest = tuple(e for e in current if e != drop)
                    cols = _columns(base.dim, current, rest)
                    model = effect_model(rest)
                    v, pred, chi2 = _fit_from(
                        model, measured, weight, sigma, rows, v_cur[:, cols], 1, max_iter
                    )
                    fit = _Fit(rest, model, v, rows, pred, chi2, model.dim)
                    for pos, i in enumerate(rows):
                        old = per_spec[i].get(rest)
                        if old is None or chi2[pos] < old[0].chi2[old[1]]:
                            per_spec[i][rest] = (fit, pos)
                for i in members:
                    here = bic_of(*per_spec[i][current], i)
                    losses = {}
                    for drop in current:
                        rest = tuple(e for e in current if e != drop)
                        losses[rest] = bic_of(*per_spec[i][rest], i) - here
                    rest = min(losses, key=losses.get)
                    loss = losses[rest]
                    if loss < backward_delta:
                        logger.info(
                            "%s: %s does not pay given %s (%.1f < %.1f); dropped",
                            specimens[i],
                            set(current) - set(rest),
                            rest,
                            loss,
                            backward_delta,
                        )
                        chosen[i] = rest
                        dropped += 1
            if not dropped:
                break

    # 2b. Open world: where the chosen effects still leave the data unexplained, keep an effect
    # only if it pays beyond a smooth discrepancy (the GP of step 4) sized to what the chosen
    # model leaves unexplained: effects that merely let the disc bend towards physics nobody
    # registered are dropped (backward elimination, BIC of the GLS fit with that GP).
    pending = [
        i
        for i in range(n)
        if chosen[i]
        and not _adequate_quick(*per_spec[i][chosen[i]], i, measured, sigma, n_points, alpha)
    ]
    gls: dict[tuple[int, tuple[str, ...]], tuple[float, torch.Tensor]] = {}
    gls_amp: dict[tuple[int, tuple[str, ...]], np.ndarray] = {}  # (4,) GP amplitude per LC
    reached: dict[int, torch.Tensor] = {}  # where elimination left a specimen (unit coords)

    def misfit_amplitude(i: int, effects: tuple[str, ...]) -> np.ndarray:
        """Per load case (4,): the RMS misfit ``effects`` leave beyond the noise."""
        f, pos = per_spec[i][effects]
        r = np.where(mask[i], measured[i] - f.pred[pos].double().numpy(), 0.0)
        noise = np.where(mask[i], sigma**2, 0.0).sum(1)
        excess = ((r**2).sum(1) - noise) / np.maximum(mask[i].sum(1), 1)
        return np.clip(np.sqrt(np.clip(excess, 0.0, None)), sigma_m.min(), 5.0)

    def gls_fit(
        effects: tuple[str, ...],
        rows: list[int],
        v: torch.Tensor,
        amp,
        again: bool = False,
        cap: np.ndarray | None = None,
    ) -> None:
        """The GLS fit of ``effects`` with the GP from ``v`` (keeps the better with ``again``).

        ``cap`` (len(rows), 4): the largest GP amplitude per load case (``inf``: free).
        """
        todo = [(k, i) for k, i in enumerate(rows) if again or (i, effects) not in gls]
        if not todo:
            return
        idx = [k for k, _ in todo]
        ids = np.asarray([i for _, i in todo])
        model = base if not effects else effect_model(effects)
        if gp_amplitude == "ml":
            # Each model gets the discrepancy it needs (type-II maximum likelihood per load
            # case) and pays for it in log det C: -2 log marginal likelihood.
            fit = fit_discrepancy(
                model,
                v[idx],
                measured[ids],
                sigma_m,
                amplitude_deg="ml",
                amplitude_cap=None if cap is None else cap[idx],
            )
            score = fit.neg2_log_ml
        else:
            fit = fit_discrepancy(model, v[idx], measured[ids], sigma_m, amplitude_deg=amp[idx])
            score = fit.cost
        for pos, i in enumerate(ids):
            key = (int(i), effects)
            if key not in gls or float(score[pos]) < gls[key][0]:
                gls[key] = (float(score[pos]), fit.v[pos])
                gls_amp[key] = fit.amplitude_deg[pos]

    def ensure_fitted() -> None:
        """Fit (without the GP) the models elimination reached that were never fitted."""
        missing: dict[tuple[str, ...], list[int]] = {}
        for i in range(n):
            if chosen[i] not in per_spec[i]:
                missing.setdefault(chosen[i], []).append(i)
        for effects, members in missing.items():
            rows = np.asarray(members)
            model = effect_model(effects)
            v0 = torch.stack([reached[i] for i in members])
            v, pred, chi2 = _fit_from(model, measured, weight, sigma, rows, v0, 1, max_iter)
            fit = _Fit(effects, model, v, rows, pred, chi2, model.dim)
            for pos, i in enumerate(rows):
                per_spec[i][effects] = (fit, pos)

    for _round in range(max_effects):
        if not pending:
            break
        groups = {}
        for i in pending:
            groups.setdefault(chosen[i], []).append(i)
        still = []
        gls.clear()  # the GP's size changes with the model under test
        for current, members in groups.items():
            v_cur = _solutions(per_spec, members, current)
            amp = np.array([misfit_amplitude(i, current) for i in members])
            gls_fit(current, members, v_cur, amp)
            v_gls = torch.stack([gls[(i, current)][1] for i in members])
            for drop in current:
                rest = tuple(e for e in current if e != drop)
                cols = _columns(base.dim, current, rest)
                # In the dropped effect's own load cases the discrepancy may be no larger than
                # the model with the effect needed there: it may not take over what the effect
                # explained; elsewhere it is free, so the disc can stop bending towards physics
                # nobody registered (which is what a compensating effect was doing).
                cap = None
                if elimination_cap:
                    own_lc = get_effect(drop).load_case_mask().numpy()
                    cap = np.stack(
                        [
                            np.where(own_lc, elimination_cap * gls_amp[(i, current)], np.inf)
                            for i in members
                        ]
                    )
                gls_fit(rest, members, v_gls[:, cols], amp, cap=cap)
                # The reduced model's own fit is a second start: from the larger model's
                # parameters the disc may stay bent towards what the dropped effect did.
                own = [i for i in members if rest in per_spec[i]]
                if own:
                    v_own = _solutions(per_spec, own, rest)
                    sel = [members.index(i) for i in own]
                    gls_fit(
                        rest,
                        own,
                        v_own,
                        amp[sel],
                        again=True,
                        cap=None if cap is None else cap[sel],
                    )
            k_cur = base.dim + sum(len(get_effect(e).parameters) for e in current)
            for i in members:
                here = gls[(i, current)][0] + k_cur * log_n[i]
                losses = {}
                for drop in current:
                    rest = tuple(e for e in current if e != drop)
                    k_rest = k_cur - len(get_effect(drop).parameters)
                    losses[rest] = gls[(i, rest)][0] + k_rest * log_n[i] - here
                rest = min(losses, key=losses.get)
                logger.debug(
                    "%s: GP-BIC loss of dropping from %s: %s", specimens[i], current, losses
                )
                if losses[rest] < min_delta:
                    logger.info(
                        "%s: %s does not pay beyond a smooth discrepancy (%.1f); dropped",
                        specimens[i],
                        set(current) - set(rest),
                        losses[rest],
                    )
                    chosen[i] = rest
                    reached[i] = gls[(i, rest)][1]
                    if rest:
                        still.append(i)
        ensure_fitted()
        pending = still

    # 3. Adequacy of the final models (and of the disc alone), with the exact Jacobian.
    out: list[SpecimenDiagnosis] = []
    finals: dict[tuple[str, ...], list[int]] = {}
    for i in range(n):
        finals.setdefault(chosen[i], []).append(i)
    # One Jacobian per fitted batch (all its specimens at once): effective parameters and
    # the parameter covariance of every model in every ranking.
    done: set[int] = set()
    for i in range(n):
        for f, _ in per_spec[i].values():
            if id(f) not in done:
                done.add(id(f))
                _, jac = f.model.curves_jacobian(f.v)
                f.trace, f.cov = _hat_trace_and_cov(jac, mask[f.rows], sigma)
                f.finite = torch.isfinite(jac).reshape(len(f.rows), -1).all(1).numpy()

    adequacy: list[dict[str, Any]] = []
    f0 = fits[()]
    for i in range(n):
        f, pos = per_spec[i][chosen[i]]
        res = measured[i] - f.pred[pos].double().numpy()
        adequacy.append(
            {
                "final": _adequacy(res, sigma, float(n_points[i] - f.trace[pos]), alpha),
                "disc_alone": _adequacy(
                    measured[i] - pred0[i].double().numpy(),
                    sigma,
                    float(n_points[i] - f0.trace[i]),
                    alpha,
                ),
            }
        )

    # 4. The discrepancy on top of each final model.
    dense = dense_grid(moments, curve_points)
    disc_info: list[dict[str, Any] | None] = [None] * n
    if discrepancy:
        signatures = _signatures(per_spec, candidates, pred0, n)
        for effects, members in finals.items():
            rows = np.asarray(members)
            model = base if not effects else effect_model(effects)
            v = _solutions(per_spec, rows, effects)
            dfit = fit_discrepancy(model, v, measured[rows], sigma_m)
            mean, sd = discrepancy_posterior(dfit, moments, dense, mask[rows])
            for pos, i in enumerate(rows):
                own = _own_range(dense, moments, mask[i])
                mu = np.where(own, mean[pos], np.nan)
                sdev = np.where(own, sd[pos], np.nan)
                sim = similarity(dfit.delta_at_points[pos], signatures[i], sigma)
                best_sim = max(sim, key=sim.get) if sim else None
                resembles = best_sim if best_sim and sim[best_sim] >= RESEMBLES else None
                text = describe(dense, mu, sdev, float(sigma_m.min()))
                disc_info[i] = {
                    "model": model_label(effects),
                    "mean": mu,
                    "sd": sdev,
                    "mae_deg": float(dfit.mae_deg[pos]),
                    "amplitude_deg": [float(a) for a in dfit.amplitude_deg[pos]],
                    "description": text,
                    "summary": _summary(text, resembles, sim),
                    "similarity": sim,
                    "resembles": resembles,
                }

    # 5. Continuous curves, rankings, what to measure next.
    dense_base = _dense_base(base, dense)
    curves0 = _dense_curves(dense_base, (), v_disc)
    final_curves: dict[int, np.ndarray] = {}
    for effects, members in finals.items():
        if not effects:
            for i in members:
                final_curves[i] = curves0[i]
            continue
        v = _solutions(per_spec, members, effects)
        cv = _dense_curves(dense_base, effects, v)
        for pos, i in enumerate(members):
            final_curves[i] = cv[pos]
    sigma_dense = np.interp(np.log(dense), np.log(moments), sigma_m)
    mae0 = np.nanmean(np.abs(measured - pred0.double().numpy()).reshape(n, -1), axis=1)
    unit_disc = base.space.to_unit(base.to_physical(v_disc.double().numpy()))
    for i, spec in enumerate(specimens):
        ranking = _ranking(per_spec[i], i, measured, sigma, log_n, base)
        effects = list(chosen[i])
        adequate = bool(adequacy[i]["final"]["adequate"])
        f, pos = per_spec[i][chosen[i]]
        final_res = measured[i] - f.pred[pos].double().numpy()
        own = _own_range(dense, moments, mask[i])
        curves = {
            "moments": dense,
            NONE: np.where(own, curves0[i], np.nan),
        }
        if effects:
            curves[model_label(effects)] = np.where(own, final_curves[i], np.nan)
        nxt = _next_measurement(
            ranking, per_spec[i], dense_base, dense, sigma_dense, min_delta, chosen[i]
        )
        resid = measured[i] - pred0[i].double().numpy()
        out.append(
            SpecimenDiagnosis(
                specimen=str(spec),
                verdict=verdict_label(effects, adequate),
                baseline_mae_deg=float(mae0[i]),
                ranking=ranking,
                residuals=resid,
                failures=_failures(resid, sigma, moments, unit_disc[i], base.space.names),
                effects=effects,
                adequate=adequate,
                adequacy=adequacy[i],
                final_mae_deg=float(np.nanmean(np.abs(final_res))),
                final_residuals=final_res,
                curves=curves,
                discrepancy=disc_info[i],
                next_measurement=nxt,
            )
        )
    return Diagnosis(
        specimens=out,
        sigma_deg=float(sigma_m.min()),
        noise_deg=noise_used,
        noise_sd_deg=float(noise_sd),
        surrogate_error_deg=float(sur.min()),
        moments=moments,
        seconds=time.perf_counter() - t0,
        sigma_by_moment=sigma_m,
        alpha=alpha,
    )


# ------------------------------------------------------------------------- adequacy
def _adequacy(res: np.ndarray, sigma: np.ndarray, dof: float, alpha: float) -> dict[str, Any]:
    """Chi-square and runs tests of residuals (4, m) against the noise."""
    z = res / sigma
    chi2 = float(np.nansum(z**2))
    dof = max(dof, 1.0)
    p_chi2 = _chi2_sf(chi2, dof)
    p_runs = runs_p_value(res)
    # Runs of one sign only matter where the residuals are not small against the noise: a
    # smooth surrogate error well inside sigma makes runs, not missing physics.
    runs_bad = p_runs < alpha and chi2 > dof
    return {
        "chi2": chi2,
        "dof": dof,
        "p_chi2": p_chi2,
        "p_runs": p_runs,
        "adequate": bool(p_chi2 >= alpha and not runs_bad),
    }


def _adequate_quick(fit: _Fit, pos: int, i: int, measured, sigma, n_points, alpha) -> bool:
    """Adequacy during forward selection (degrees of freedom: n - k/2, no Jacobian)."""
    res = measured[i] - fit.pred[pos].double().numpy()
    return bool(_adequacy(res, sigma, float(n_points[i] - fit.k / 2), alpha)["adequate"])


# ------------------------------------------------------------------------ reporting
def _ranking(
    fits: dict, i: int, measured: np.ndarray, sigma: np.ndarray, log_n: np.ndarray, base
) -> list[dict[str, Any]]:
    """Every model fitted for specimen ``i``: MAE, BIC and effect parameters ± sd."""
    rows = []
    for effects, (f, pos) in fits.items():
        pred = f.pred[pos].double().numpy()
        mae = float(np.nanmean(np.abs(measured[i] - pred)))
        entry = {
            "effect": model_label(effects),
            "effects": list(effects),
            "mae_deg": mae,
            "criterion": float(f.chi2[pos] + f.k * log_n[i]),
            "parameters": {},
        }
        if effects:
            model = f.model
            vi = f.v[pos : pos + 1]
            finite = bool(f.finite[pos])
            cov = f.cov[pos : pos + 1]
            x = model.to_physical(vi.double().numpy())[0]
            col = base.dim
            for e in model.effects:
                for par in e.parameters:
                    sd_u = float(np.sqrt(max(cov[0, col, col], 0.0))) if finite else float("nan")
                    if par.log:
                        scale = x[col] * np.log(par.upper / par.lower)
                    else:
                        scale = par.upper - par.lower
                    entry["parameters"][par.name] = {
                        "value": float(x[col]),
                        "sd": sd_u * scale,
                        "unit": par.unit,
                    }
                    col += 1
        rows.append(entry)
    rows.sort(key=lambda r: r["criterion"])
    return rows


def _signatures(per_spec, candidates, pred0: torch.Tensor, n: int) -> list[dict[str, np.ndarray]]:
    """What each single effect adds to the disc-alone fit, per specimen (4, m)."""
    out = []
    for i in range(n):
        sig = {}
        for name in candidates:
            if (name,) in per_spec[i]:
                f, pos = per_spec[i][(name,)]
                sig[name] = (f.pred[pos] - pred0[i]).double().numpy()
        out.append(sig)
    return out


def _summary(text: list[str], resembles: str | None, sim: dict[str, float]) -> str:
    if not text:
        return "nothing missing beyond the noise"
    lcs = [t.split(":")[0] for t in text]
    what = "; ".join(text)
    if resembles:
        tail = f"resembles the signature of {resembles} (similarity {sim[resembles]:.2f})"
    elif sim:
        best = max(sim, key=sim.get)
        tail = (
            f"resembles no registered effect (closest: {best}, similarity {sim[best]:.2f}): "
            "a candidate for a new effect"
        )
    else:
        tail = "no registered effect to compare with"
    return f"missing in {', '.join(lcs)}: {what}. It {tail}."


def _own_range(dense: np.ndarray, moments: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Bool (4, q): the dense moments within each load case's own measured range."""
    out = np.zeros((len(LOAD_CASES), len(dense)), dtype=bool)
    for j in range(len(LOAD_CASES)):
        got = moments[mask[j]]
        if got.size:
            out[j] = (dense >= got.min() * (1 - 1e-9)) & (dense <= got.max() * (1 + 1e-9))
    return out


def _dense_base(base, dense: np.ndarray):
    surrogate = getattr(base, "surrogate", None)
    if surrogate is None:
        return None
    return SurrogateCurveModel(surrogate, dense, space=base.space)


def _dense_curves(dense_base, effects: tuple[str, ...], v: torch.Tensor) -> np.ndarray:
    if dense_base is None:
        return np.full((v.shape[0], len(LOAD_CASES), 1), np.nan)
    model = dense_base if not effects else EffectModel(dense_base, list(effects))
    with torch.no_grad():
        return model.curves(v).double().numpy()


def _next_measurement(ranking, fits, dense_base, dense, sigma_dense, min_delta, chosen):
    """Where the chosen model and its closest rival (BIC within ``min_delta``) differ most."""
    if len(ranking) < 2 or dense_base is None:
        return None
    best = next(r for r in ranking if tuple(r["effects"]) == tuple(chosen))
    rivals = [r for r in ranking if r is not best]
    second = min(rivals, key=lambda r: abs(r["criterion"] - best["criterion"]))
    gap = abs(second["criterion"] - best["criterion"])
    if gap >= min_delta:
        return None
    curves = []
    for r in (best, second):
        f, pos = fits[tuple(r["effects"])]
        curves.append(_dense_curves(dense_base, tuple(r["effects"]), f.v[pos : pos + 1])[0])
    diff = (curves[0] - curves[1]) / sigma_dense[None, :]
    if not np.isfinite(diff).any():
        return None
    j, k = np.unravel_index(np.nanargmax(np.abs(diff)), diff.shape)
    return {
        "between": [best["effect"], second["effect"]],
        "criterion_gap": float(gap),
        "load_case": LOAD_CASES[j],
        "moment_nm": float(dense[k]),
        "difference_deg": float(curves[0][j, k] - curves[1][j, k]),
        "difference_sigma": float(abs(diff[j, k])),
    }


def _failures(
    resid: np.ndarray, sigma: np.ndarray, moments: np.ndarray, x_unit: np.ndarray, names
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
        out["sign_pattern"][lc] = "".join("+" if v > 0 else "-" for v in resid[j][ok])
    out["on_bounds"] = [n for n, u in zip(names, x_unit) if u < 1e-3 or u > 1 - 1e-3]
    return out


__all__ = [
    "NONE",
    "UNEXPLAINED",
    "Diagnosis",
    "SpecimenDiagnosis",
    "diagnose",
    "verdict_label",
]
