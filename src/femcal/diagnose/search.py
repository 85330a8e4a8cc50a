"""Compare the model with measurements, show where it fails, find what is missing.

For every specimen, :func:`diagnose` runs these steps over one :class:`DiagnosisState`:

1. **the disc alone**, calibrated with ``pgd``; residuals are weighed against the noise
   ``sigma(M)^2 = noise^2 / w + surrogate_error(M)^2`` (the surrogate's own error counts as
   noise, larger beyond its trained moments; ``w`` the point's weight, e.g. ``k`` for the mean
   of ``k`` repeated measurements);
2. **forward selection** (:mod:`femcal.diagnose.forward`): the disc with each registered effect
   (material and effect parameters jointly, inside all bounds), tied and, for the first
   effect, split per load case too: the form that lowers the criterion ``chi^2 + k ln n``
   most (``k`` the effective number of parameters, the trace of the hat matrix; a split form
   pays ``min_delta_inadequate`` more) is added when it pays ``min_delta``; two effects on
   disjoint load cases (a facet and a ligament) are also fitted together from the start and
   compete with the second level's models; further effects while they pay
   ``min_delta_inadequate`` (the model does not explain the data yet) or
   ``min_delta_adequate``;
3. **tied or split** (:mod:`femcal.diagnose.forms`): each chosen effect's parameters per load
   case where that pays;
4. **backward check**: each effect of a combination must still pay ``backward_delta`` given
   the others;
5. **open world** (:mod:`femcal.diagnose.elimination`): where the chosen effects leave the data
   unexplained, each must pay beyond a smooth discrepancy, unless it removes most of the
   disc-alone misfit;
6. **where each effect acts** (:mod:`femcal.diagnose.where`): one load case its prior leaves
   open added to or left out of each chosen effect, where that pays with the prior's cost
   (forward selection fitted each candidate in every load case its prior allows too); the
   backward check again where that changed a model;
7. **the decision** (:mod:`femcal.diagnose.decide`): the posterior probability of every
   fitted model, of each effect and of something outside the library (a discrepancy on top of
   the model, or in place of its effects: :mod:`femcal.diagnose.probabilities`); each
   specimen's model is the most probable fitted one; the verdict says ``unexplained`` where a
   discrepancy is more probable than the model alone, and names the box where a disc beyond
   the parameter box is the likelier reading (:mod:`femcal.diagnose.outside`). The
   :class:`~femcal.diagnose.decide.Decision` holds each specimen's model, verdict,
   probabilities and out-of-box reading, frozen;
8. **the description** (:mod:`femcal.diagnose.assemble`), which reads the state and the
   decision and changes neither: adequacy tests, the discrepancy described (load cases,
   laxity or stiffening, from which moment, how large), continuous curves, rankings and
   *what to measure next* where the runner-up is close.

Steps 2-7 change the :class:`~femcal.diagnose.state.DiagnosisState` (its fits and chosen
models); each step's docstring says what it reads and what it changes. A model is a
:class:`femcal.effects.terms.Model`, written as a string only in the files and logs.

The measured rates of these choices are in the docs' benchmark pages.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import numpy as np
import torch

from femcal.calibration.base import CalibrationProblem
from femcal.calibration.model import CurveModel
from femcal.calibration.pgd import pgd
from femcal.diagnose.assemble import assemble_result
from femcal.diagnose.decide import decide
from femcal.diagnose.elimination import open_world_elimination
from femcal.diagnose.fits import Fit, chi_square, design_columns, point_weights
from femcal.diagnose.forms import choose_forms
from femcal.diagnose.forward import forward_selection
from femcal.diagnose.options import DiagnoseOptions
from femcal.diagnose.result import Diagnosis
from femcal.diagnose.state import DiagnosisState
from femcal.diagnose.where import choose_cases
from femcal.diagnose.workers import in_workers
from femcal.effects.base import available_effects, get_effect
from femcal.effects.terms import Model, Term
from femcal.errors import ConfigError
from femcal.moments import MomentPolicy

logger = logging.getLogger(__name__)


def _point_weight(point_weight: np.ndarray | None, measured: np.ndarray) -> np.ndarray:
    """The points' weights (n, 4, m), checked: finite and >= 0 (1 everywhere by default)."""
    if point_weight is None:
        return np.ones(measured.shape)
    w = np.asarray(point_weight, dtype=float)
    if w.shape != measured.shape:
        raise ConfigError(
            f"diagnose: point_weight must have the measurements' shape {measured.shape} "
            f"(specimen, load case, moment); got {w.shape}."
        )
    bad = np.isfinite(measured) & ~(np.isfinite(w) & (w >= 0))
    if bad.any():
        raise ConfigError(
            f"diagnose: point_weight must be finite and >= 0 at every measured point; got "
            f"{w[bad][:3].tolist()} at {int(bad.sum())} points. A weight is a relative inverse "
            "noise variance (the mean of k repeated measurements weighs k; 0 leaves a point out)."
        )
    return np.where(np.isfinite(w), w, 1.0)


def diagnose(
    base: CurveModel,
    rom_deg: np.ndarray,
    *,
    specimens: Sequence[str],
    noise_deg: float | None = None,
    surrogate_error_deg: float | np.ndarray = 0.0,
    point_weight: np.ndarray | None = None,
    candidates: Sequence[str] | None = None,
    start_bank: np.ndarray | None = None,
    moment_policy: MomentPolicy | None = None,
    options: DiagnoseOptions | None = None,
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
        Measurement noise (sd, deg). Estimated from the disc-alone residuals when omitted.
    surrogate_error_deg : float or ndarray, shape (m,) or (n, 4, m)
        The surrogate's own error (sd, deg): one value, one per moment, or one per point (at
        the specimen's own curves), added in quadrature to the noise
        (:meth:`femcal.moments.MomentPolicy.sigma_surrogate`).
    point_weight : ndarray, shape (n, 4, m), optional
        Each point's weight, a relative inverse noise variance (the mean of ``k`` repeated
        measurements weighs ``k``; 0 leaves a point out). Default: 1.
    candidates : sequence of str, optional
        Effects to try (default: every registered effect).
    start_bank : ndarray, shape (N, 13), optional
        Disc configurations (physical units) to start from.
    moment_policy : MomentPolicy, optional
        Where a next measurement may be taken: *what to measure next* then searches every
        moment the policy accepts, with the surrogate's error there; without it, the
        measured range.
    options : DiagnoseOptions, optional
        How to search, decide and describe (the defaults of :class:`DiagnoseOptions`).

    Returns
    -------
    Diagnosis
    """
    t0 = time.perf_counter()
    options = DiagnoseOptions() if options is None else options
    names = list(available_effects() if candidates is None else candidates)
    for name in names:
        get_effect(name)  # unknown names fail before any work
    measured = np.where(np.isfinite(rom_deg), np.asarray(rom_deg, dtype=float), np.nan)
    m = measured.shape[2]
    w = _point_weight(point_weight, measured)
    if np.any((w == 0) & np.isfinite(measured)):
        logger.info(
            "%d measured points of weight 0 are left out of the diagnosis",
            int(np.sum((w == 0) & np.isfinite(measured))),
        )
    measured = np.where(w > 0, measured, np.nan)  # weight 0: left out
    w = np.where(w > 0, w, 1.0)  # where not measured it does not count
    sur = np.asarray(surrogate_error_deg, dtype=float)
    sur = np.broadcast_to(sur, measured.shape if sur.ndim == 3 else (m,)).copy()
    if np.any(~np.isfinite(sur)) or np.any(sur < 0):
        raise ConfigError(
            "surrogate_error_deg must be finite and >= 0 (one value, one per moment, or one "
            f"per point); got {np.unique(sur[~(np.isfinite(sur) & (sur >= 0))])[:3].tolist()}."
        )
    rng = np.random.default_rng(options.seed)
    state = DiagnosisState(
        base=base,
        specimens=list(specimens),
        measured=measured,
        weight=np.ones(measured.shape),
        sigma=np.ones(measured.shape),
        sigma_m=np.ones(m),
        surrogate_sd=np.broadcast_to(sur, measured.shape).copy(),
        options=options,
        candidates=[Term.parse(name) for name in names],
        start_bank=start_bank,
        rng=rng,
    )
    noise_used, noise_sd = _noise(state, w, sur, noise_deg)
    state.sigma_m = np.sqrt(noise_used**2 + _per_moment(sur**2, state.mask))  # (m,): weight 1
    state.sigma = np.sqrt(noise_used**2 / w + sur**2)  # (n, 4, m): every point's own
    state.weight = np.ascontiguousarray(point_weights(state.sigma, measured.shape))
    v_disc, pred0 = disc_fit(state, state.weight)
    all_rows = np.arange(state.n)
    chi2 = chi_square(pred0, measured, state.sigma)
    disc = Fit(Model(), base, v_disc, all_rows, pred0, chi2, base.dim)
    state.per_spec = [{} for _ in range(state.n)]
    state.record(disc)
    state.chosen = [Model() for _ in range(state.n)]
    keywords = dict(sur=sur, noise_used=noise_used, noise_sd=noise_sd, moment_policy=moment_policy)
    diag = in_workers(state, _diagnose_group, options.workers, t0=t0, **keywords)
    if diag is None:
        diag = _diagnose_group(state, disc=disc, t0=t0, **keywords)
    diag.seconds = time.perf_counter() - t0
    return diag


def _diagnose_group(state: DiagnosisState, *, disc: Fit, **keywords) -> Diagnosis:
    """Steps 2-8 for the specimens of ``state`` (``disc``: their disc-alone fit; ``keywords``
    those of :func:`femcal.diagnose.assemble.assemble_result`): the search and the decision change
    ``state``; the description reads it and the decision."""
    forward_selection(state)
    choose_forms(state)
    if state.options.backward:
        _backward(state)
    open_world_elimination(state)
    if choose_cases(state) and state.options.backward:
        _backward(state)
    decision = decide(state, disc)
    return assemble_result(state, decision, disc=disc, **keywords)


def disc_fit(state: DiagnosisState, weight: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The disc alone calibrated with ``pgd`` under ``weight`` (n, 4, m): unit coordinates
    (n, 13) and curves (n, 4, m).

    Reads ``state.base``, ``state.measured``, ``state.start_bank`` and ``state.options``;
    changes ``state.rng`` (pgd's draws) and nothing else."""
    base = state.base
    problem = CalibrationProblem.from_arrays(base, state.measured, weight)
    sol = pgd(
        problem,
        rng=state.rng,
        start_bank=state.start_bank,
        max_iter=state.options.max_iter,
        fit_tolerance=0.0,
        ranges=False,
        n_starts=8,
        keep_after=3,
        keep=2,
    )
    v = base.from_physical(sol.x)
    with torch.no_grad():
        return v, base.curves(v)


def _per_moment(value: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``value`` (m,) as is, or (n, 4, m) averaged over the measured points at each moment
    (over every point where a moment has none)."""
    if value.ndim == 1:
        return value
    count = mask.sum(axis=(0, 1))
    mean = np.where(mask, value, 0.0).sum(axis=(0, 1)) / np.maximum(count, 1)
    return np.where(count > 0, mean, value.mean(axis=(0, 1)))


def _noise(
    state: DiagnosisState, w: np.ndarray, sur: np.ndarray, noise_deg: float | None
) -> tuple[float, float]:
    """The measurement noise (sd, deg) and its uncertainty: given, or estimated from the
    residuals of the disc alone (pooled, the surrogate's share taken out)."""
    if noise_deg is not None:
        if not noise_deg > 0:
            raise ConfigError(f"noise_deg must be > 0; got {noise_deg}.")
        return float(noise_deg), 0.0
    measured, mask = state.measured, state.mask
    _, pred0 = disc_fit(state, point_weights(np.sqrt(0.05**2 / w + sur**2), measured.shape))
    r0 = np.where(mask, measured - pred0.double().numpy(), 0.0)
    dof = float(np.clip(state.n_points - state.base.dim / 2, 1, None).sum())
    # w r^2 estimates noise^2 + w surrogate_error^2 at a point (up to its leverage)
    total = float((w * r0**2).sum()) / dof
    sur_part = float(np.mean((w * sur**2)[mask])) if mask.any() else 0.0
    noise_used = float(np.sqrt(max(total - sur_part, 1e-12)))
    logger.info("noise estimated from the disc-alone residuals: %.4f deg", noise_used)
    return noise_used, noise_used / np.sqrt(2 * dof)


def _backward(state: DiagnosisState) -> None:
    """Stepwise selection's backward check: each effect of a combination must still gain
    ``backward_delta`` given the others, the sub-model refitted from the combination's
    solution (forward selection's fit of it had the disc bent towards the effect added
    first); one that does not is dropped.

    Reads ``state.chosen`` and their fits in ``state.per_spec``; changes ``state.per_spec``
    (each sub-model one effect smaller, refitted; an earlier fit of it kept where better) and
    ``state.chosen`` (where an effect is dropped). A batch an earlier round fitted (the same
    sub-model, specimens and starts: a group no drop changed) is not fitted again: its
    specimens hold that fit, or a better one."""
    options = state.options
    fitted: set[tuple[Model, bytes, bytes]] = set()  # (sub-model, specimens, starts) fitted
    for _round in range(options.max_effects):
        groups: dict[Model, list[int]] = {}
        for i in range(state.n):
            if len(state.chosen[i]) >= 2:
                groups.setdefault(state.chosen[i], []).append(i)
        dropped = 0
        for current, members in groups.items():
            rows = np.asarray(members)
            v_cur = state.solutions(rows, current)
            for drop in current:
                rest = current.without(drop)
                v0 = v_cur[:, None, design_columns(state.base.dim, current, rest)]
                batch = (rest, rows.tobytes(), v0.numpy().tobytes())
                if batch in fitted:
                    continue
                fitted.add(batch)
                kept = {i: state.per_spec[i].get(rest) for i in rows}
                fit = state.fit(rest, rows, v0)
                for pos, i in enumerate(rows):  # the better of this fit and an earlier one
                    old = kept[i]
                    if old is not None and old[0].chi2[old[1]] <= fit.chi2[pos]:
                        state.per_spec[i][rest] = old
            for i in members:
                here = state.criterion(current, i)
                losses = {}
                for drop in current:
                    rest = current.without(drop)
                    losses[rest] = state.criterion(rest, i) - here
                rest = min(losses, key=losses.get)
                if losses[rest] < options.backward_delta:
                    logger.info(
                        "%s: %s does not pay given %s (%.1f < %.1f); dropped",
                        state.specimens[i],
                        sorted(set(current.key) - set(rest.key)),
                        rest,
                        losses[rest],
                        options.backward_delta,
                    )
                    state.chosen[i] = rest
                    dropped += 1
        if not dropped:
            return
