"""``pgd``: batched projected Gauss-Newton (Levenberg-Marquardt) on the frozen surrogate.

Every specimen and every start of a batch is one row of one tensor. Each iteration computes the
curves and their exact Jacobian in the network's unit coordinates (forward mode, see
:meth:`~femcal.surrogates.nn.RomNet.curves_jacobian`), solves the damped normal equations with
the variables held at an active bound frozen, and projects the step onto the box exactly
(``clamp`` to [0, 1], the study's ClipBounds in these coordinates). A step is kept only if it
lowers the loss; converged rows leave the batch. The iterate is therefore inside the bounds
at every step, and the returned parameters are clipped in float64.

Starts: the training configurations (``start_bank``) and ``n_bank_uniform`` uniform draws are
evaluated once; each specimen starts from its ``n_starts`` nearest of them (weighted squared
distance of the curves), plus ``n_random_starts`` uniform draws of its own.

Models with physical effects (:class:`~femcal.effects.composite.EffectModel`) are calibrated in
two stages, so that an effect the data do not need stays off: the disc alone first (as above),
then material and effect parameters jointly from that disc solution combined with every
effect at its weak end, and with a grid (``effect_levels``) over each effect's own box while
the other effects stay at their weak end.

Identifiability: around every start that ends near-optimal (MAE within ``noise_deg`` of the
best; each specimen's own error scale where the problem carries one,
:attr:`~femcal.calibration.base.CalibrationProblem.point_sd`), the linearised posterior
``(J^T J / noise^2 + I / prior^2)^-1`` gives a z-sigma interval per parameter; their union,
cut to the box, is the parameter's range. A parameter the curves do not determine gets (nearly)
the whole box.

``optimizer="adam"`` and ``optimizer="lbfgsb"`` run the same starts with projected Adam or
SciPy's L-BFGS-B instead; the docs' page *Benchmarks > Surrogates and calibration* compares
them (stage ``bench_calibration`` of ``experiments/dvc.yaml``).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from typing import Any

import numpy as np
import torch

from femcal.calibration.base import (
    CalibrationProblem,
    Solution,
    chi2_p_value,
    register_calibrator,
)
from femcal.calibration.gauss_newton import gauss_newton, gn_cost, gn_residual
from femcal.calibration.pgd_options import LOSSES as LOSSES
from femcal.calibration.pgd_options import OPTIMIZERS as OPTIMIZERS
from femcal.calibration.pgd_options import SELECT as SELECT
from femcal.calibration.pgd_options import GaussNewtonOptions, PgdOptions
from femcal.calibration.starts import (
    build_bank,
    combination_starts,
    effect_bank,
    effect_starts,
    nearest_starts,
)

logger = logging.getLogger(__name__)


def _has_effects(model) -> bool:
    return hasattr(model, "effects") and model.dim > getattr(model, "n_disc", model.dim)


def _effect_halving(keep_after: int, effect_keep: int, k: int, max_iter: int) -> tuple[int, int]:
    """``(keep_after, keep)`` for ``k`` staged starts of an effect model: the ``effect_keep``
    best go on after at least 3 iterations, or every start runs to the end (0 or >= k)."""
    if effect_keep <= 0 or effect_keep >= k:
        return max_iter, k
    return max(keep_after, 3), effect_keep


def adam(
    problem: CalibrationProblem,
    v: torch.Tensor,
    rows: torch.Tensor,
    *,
    steps: int,
    lr: float,
    loss: str,
) -> torch.Tensor:
    """Projected Adam (clamp to the box after every step) from starts ``v`` (B, d)."""
    v = v.clone().requires_grad_(True)
    opt = torch.optim.Adam([v], lr=lr)
    w = problem.weight[rows].reshape(len(rows), -1)
    for _ in range(steps):
        opt.zero_grad()
        r = gn_residual(problem, rows, problem.model.curves(v))
        gn_cost(r, w, loss).sum().backward()
        opt.step()
        with torch.no_grad():
            v.clamp_(0.0, 1.0)
    return v.detach()


def lbfgsb(
    problem: CalibrationProblem,
    v: torch.Tensor,
    rows: torch.Tensor,
    *,
    max_iter: int,
    loss: str,
) -> torch.Tensor:
    """SciPy's L-BFGS-B (bounds built in) on the sum of the rows' losses."""
    from scipy.optimize import minimize

    shape = v.shape
    w = problem.weight[rows].reshape(len(rows), -1)

    def fun(flat: np.ndarray):
        vt = torch.tensor(flat.reshape(shape), dtype=torch.float32, requires_grad=True)
        total = gn_cost(gn_residual(problem, rows, problem.model.curves(vt)), w, loss).sum()
        total.backward()
        return float(total.detach()), vt.grad.double().numpy().reshape(-1)

    out = minimize(
        fun,
        v.double().numpy().reshape(-1),
        jac=True,
        method="L-BFGS-B",
        bounds=[(0.0, 1.0)] * v.numel(),
        options={"maxiter": max_iter},
    )
    return torch.tensor(out.x.reshape(shape), dtype=torch.float32)


def local_ranges(
    problem: CalibrationProblem,
    v: torch.Tensor,
    rows: torch.Tensor,
    *,
    noise_deg: float | torch.Tensor,
    z: float,
    prior_sd: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor]:
    """z-sigma intervals (B, d) of the linearised posterior around ``v``, cut to [0, 1].

    ``noise_deg`` is one error scale or one per row (B,); a singular row gets the whole box."""
    _, jf = problem.model.curves_jacobian(v)
    b, d = v.shape
    mask = problem.mask[rows].reshape(b, -1, 1)
    jj = jf.reshape(b, -1, d) * mask
    w = problem.weight[rows].reshape(b, -1, 1)
    noise2 = torch.as_tensor(noise_deg, dtype=torch.float32).reshape(-1, 1, 1) ** 2
    precision = (jj * w).transpose(1, 2) @ jj / noise2 + torch.eye(d) / prior_sd**2
    cov, info = torch.linalg.inv_ex(precision)
    half = z * torch.diagonal(cov, dim1=1, dim2=2).clamp_min(0).sqrt()
    half = torch.where((info != 0)[:, None] | ~torch.isfinite(half), 1.0, half)
    return (v - half).clamp(0, 1), (v + half).clamp(0, 1)


def _tolerance_text(fit_tolerance: float, scale: torch.Tensor) -> str:
    """The fit tolerance in words: one value, or the range of the specimens' own."""
    tol = fit_tolerance * scale
    if not len(tol) or float(tol.min()) == float(tol.max()):
        return f"({float(tol[0]) if len(tol) else 0.0:.4f} deg RMS)"
    return f"({float(tol.min()):.4f}-{float(tol.max()):.4f} deg RMS, each specimen's own)"


def pgd(
    problem: CalibrationProblem,
    options: PgdOptions | None = None,
    *,
    rng: np.random.Generator,
    start_bank: np.ndarray | None = None,
    **overrides: Any,
) -> Solution:
    """Projected gradient-based calibration of a batch (see the module docstring).

    Parameters
    ----------
    problem : CalibrationProblem
        Targets of n specimens and the surrogate.
    options : PgdOptions, optional
        How it starts, iterates, selects and bounds (default: :class:`PgdOptions`'s).
    rng : numpy.random.Generator
        Source of the uniform draws.
    start_bank : ndarray, shape (N, d), optional
        Candidate starts in physical units (the surrogate's training configurations).
    **overrides
        Fields of :class:`PgdOptions` replacing those of ``options``.

    Returns
    -------
    Solution
    """
    o = dataclasses.replace(options or PgdOptions(), **overrides)
    max_iter, keep_after, keep = o.max_iter, o.keep_after, o.keep
    loss, optimizer, n_random_starts = o.loss, o.optimizer, o.n_random_starts
    n, d = problem.n_specimens, problem.dim
    model = problem.model
    # The error scale of each specimen (n,): its own where the problem carries one.
    scale = (
        problem.point_sd.double()
        if problem.point_sd is not None
        else torch.full((n,), float(o.noise_deg), dtype=torch.float64)
    )
    if _has_effects(model):
        if o.effect_max_iter is not None:
            max_iter = o.effect_max_iter
        starts, k_bank = _effect_model_starts(problem, o, rng, start_bank), 0
        # The first start (the disc-alone solution, every effect weak) always goes on
        # (keep_first): an effect the data do not need then never leaves a specimen worse off.
        halving_after = keep_after
        keep_after, keep = _effect_halving(
            halving_after, o.effect_keep, sum(s.shape[1] for s in starts), max_iter
        )
    else:
        bank_v, bank_pred = build_bank(problem, start_bank, o.n_bank_uniform, rng)
        idx = nearest_starts(problem, bank_v, bank_pred, o.n_starts)
        k_bank = idx.shape[1]
        starts = [bank_v[idx]] if k_bank else []
    if n_random_starts:
        starts.append(torch.tensor(rng.random((n, n_random_starts, d)), dtype=torch.float32))
    v0 = torch.cat(starts, dim=1)  # (n, k, d)
    k = v0.shape[1]
    rows = torch.arange(n).repeat_interleave(k)
    v0 = v0.reshape(n * k, d)
    converged = torch.ones(n * k, dtype=torch.bool)

    def newton(v0, rows, keep_after, keep):
        return gauss_newton(
            problem,
            v0,
            rows,
            GaussNewtonOptions(
                max_iter=max_iter,
                loss=loss,
                tol=o.tol,
                keep_after=keep_after,
                keep=keep,
                jacobian_members=o.jacobian_members,
                exact_final=o.exact_final,
                atol_deg=(o.fit_tolerance * scale).clamp_min(1e-4).float(),
                keep_first=_has_effects(model),
            ),
        )

    if optimizer == "gauss-newton":
        v, nit, converged = newton(v0, rows, keep_after, keep)
    elif optimizer == "adam":
        v, nit = adam(problem, v0, rows, steps=o.steps, lr=o.lr, loss=loss), o.steps
    else:
        v, nit = lbfgsb(problem, v0, rows, max_iter=max_iter, loss=loss), max_iter
    if _has_effects(model):
        # The disc-alone solution with every effect weak is a point of the effect model: where
        # the steps from it lowered the weighted squared error but not the MAE, keep it as it
        # was, so that an effect model never ends worse than the disc alone.
        first = torch.arange(n) * k
        with torch.no_grad():
            before = problem.scores(model.curves(v0[first]), rows[first])["mae"]
            after = problem.scores(model.curves(v[first]), rows[first])["mae"]
        back = first[before < after]
        v[back] = v0[back]
        if optimizer == "gauss-newton" and len(model.effects) > 1:
            for _ in range(o.effect_rounds - 1):
                v, rows, k, nit2, converged = _combination_round(
                    problem,
                    v,
                    rows,
                    k,
                    o,
                    lambda v0, rows, k: newton(
                        v0, rows, *_effect_halving(halving_after, o.effect_keep, k, max_iter)
                    ),
                )
                nit += nit2
    sol = _solution(problem, o, v, rows, k, converged, scale, nit, k_bank)
    if o.retry_alpha > 0 and problem.point_sd is not None and n:
        sol = _retry_unexplained(problem, sol, rng, o, start_bank)
    return sol


def _solution(problem, o, v, rows, k, converged, scale, nit, k_bank) -> Solution:
    """Each specimen's best start (by ``o.select``), its ranges, and the message."""
    n = problem.n_specimens
    with torch.no_grad():
        scores = problem.scores(problem.model.curves(v), rows)
    mae = scores["mae"].reshape(n, k)
    key = mae if o.select == "mae" else -scores["r2"].reshape(n, k)
    # A start whose curves are NaN (an effect's moment balance left unsolved) is never chosen.
    key = torch.nan_to_num(key, nan=float("inf"))
    best = key.argmin(1)
    flat_best = torch.arange(n) * k + best
    x = problem.model.to_physical(v[flat_best].double().numpy())
    x_low = x_high = None
    if o.ranges:
        x_low, x_high = _ranges(problem, v, rows, mae, best, scale, o.range_z)
    conv = converged.reshape(n, k).gather(1, best[:, None])[:, 0].numpy()
    sol = Solution(
        x=x,
        nit=int(nit),
        success=conv,
        message=(
            f"pgd ({o.optimizer}, {o.loss} loss): {k} starts per specimen "
            + (
                f"(the disc-alone solution with {k - o.n_random_starts} effect starts, "
                if _has_effects(problem.model)
                else f"({k_bank} nearest, "
            )
            + f"{o.n_random_starts} random), {nit} iterations, "
            f"{int(conv.sum())}/{n} converged or fitted within {o.fit_tolerance:g} x noise "
            + _tolerance_text(o.fit_tolerance, scale)
        ),
        x_low=x_low,
        x_high=x_high,
        info={
            "optimizer": o.optimizer,
            "loss": o.loss,
            "select": o.select,
            "starts_per_specimen": k,
            "nit": int(nit),
            "error_scale_deg": float(scale.median()) if n else float(o.noise_deg),
        },
    )
    return sol


def _effect_model_starts(
    problem: CalibrationProblem,
    o: PgdOptions,
    rng: np.random.Generator,
    start_bank: np.ndarray | None,
) -> list[torch.Tensor]:
    """The first round's starts of an effect model, (n, k_i, d) each: the disc calibrated
    alone combined with each effect's grid and design, and the disc-and-effect combinations
    of the bank nearest each specimen's curves."""
    model, n = problem.model, problem.n_specimens
    disc = pgd(
        dataclasses.replace(problem, model=model.base),
        dataclasses.replace(o, ranges=False, retry_alpha=0.0),  # the effects explain the rest
        rng=rng,
        start_bank=None if start_bank is None else np.asarray(start_bank)[:, : model.n_disc],
    )
    grid = effect_starts(model, o.effect_levels, o.effect_shape_starts)  # (g, d - n_disc)
    v_disc = model.base.from_physical(disc.x)  # (n, n_disc)
    starts = [
        torch.cat([v_disc[:, None, :].expand(-1, len(grid), -1), grid.expand(n, -1, -1)], dim=2)
    ]
    if start_bank is not None and len(start_bank) and o.effect_bank_starts > 0:
        # The disc fitted alone bends towards the missing physics; these starts do not.
        bank_v, bank_pred = effect_bank(model, start_bank, rng, o.effect_bank_samples)
        nearest = nearest_starts(problem, bank_v, bank_pred, o.effect_bank_starts)
        starts.append(bank_v[nearest])
    return starts


def _combination_round(problem, v, rows, k, o, newton):
    """A further round of an effect model with several effects: from each specimen's best
    solution, each effect again from its grid and design with the others as found, so that
    a second effect joins the first (the first round's starts have one effect on at a time).
    The first round's best is the first start: it always goes on. Returns the iterates, their
    rows, the starts per specimen, the iterations and the convergence flags."""
    model, n, d = problem.model, problem.n_specimens, problem.dim
    with torch.no_grad():
        mae = problem.scores(model.curves(v), rows)["mae"].reshape(n, k)
    mae = torch.nan_to_num(mae, nan=float("inf"))
    best = v.reshape(n, k, d)[torch.arange(n), mae.argmin(1)]
    v0 = combination_starts(model, best, o.effect_levels, o.effect_shape_starts)
    k = v0.shape[1]
    rows = torch.arange(n).repeat_interleave(k)
    v, nit, converged = newton(v0.reshape(n * k, d), rows, k)
    return v, rows, k, nit, converged


def _ranges(problem, v, rows, mae, best, scale, z):
    """Physical ``(x_low, x_high)``, (n, d) each: the union of the linearised ranges of every
    start within its specimen's error scale of the best (:func:`local_ranges`)."""
    n, d = problem.n_specimens, problem.dim
    near = mae <= mae.gather(1, best[:, None]) + scale.float()[:, None]  # (n, k)
    near_flat = torch.nonzero(near.reshape(-1)).reshape(-1)
    lo, hi = local_ranges(
        problem, v[near_flat], rows[near_flat], noise_deg=scale[rows[near_flat]], z=z
    )
    index = rows[near_flat, None].expand(-1, d)
    v_low = torch.ones((n, d)).scatter_reduce(0, index, lo, reduce="amin")
    v_high = torch.zeros((n, d)).scatter_reduce(0, index, hi, reduce="amax")
    return (
        problem.model.to_physical(v_low.double().numpy()),
        problem.model.to_physical(v_high.double().numpy()),
    )


def _retry_unexplained(
    problem: CalibrationProblem,
    sol: Solution,
    rng: np.random.Generator,
    options: PgdOptions,
    start_bank: np.ndarray | None,
) -> Solution:
    """Calibrate again, from more starts, the specimens whose fit the noise does not explain
    (``options.retry_alpha``; see :func:`pgd`); keep the better fit of each."""
    model = problem.model
    chi2, n_points = problem.chi2(model.predict(sol.x))
    dof = n_points - problem.effective_parameters(sol.x)
    bad = np.flatnonzero(chi2_p_value(chi2, dof) < options.retry_alpha)
    sol.info["n_refitted"] = int(bad.size)
    sol.info["n_refit_improved"] = 0
    if bad.size == 0:
        return sol
    thorough = dataclasses.replace(
        options,
        n_starts=4 * options.n_starts,
        keep_after=max(options.keep_after, 4),
        keep=max(options.keep, 4),
        max_iter=max(options.max_iter, 40),
        retry_alpha=0.0,
    )
    sub = problem.subset(bad)
    again = pgd(sub, thorough, rng=rng, start_bank=start_bank)
    chi2_again, _ = sub.chi2(model.predict(again.x))
    better = chi2_again < chi2[bad]
    rows = bad[better]
    x = sol.x.copy()
    x[rows] = again.x[better]
    success = np.asarray(sol.success).copy()
    success[rows] = np.asarray(again.success)[better]
    x_low, x_high = sol.x_low, sol.x_high
    if x_low is not None and x_high is not None and again.x_low is not None:
        x_low, x_high = x_low.copy(), x_high.copy()
        x_low[rows] = again.x_low[better]
        x_high[rows] = again.x_high[better]
    logger.info(
        "pgd: %d of %d specimens were not explained within the noise (p < %g); refitted from "
        "%d starts each, %d fit better",
        bad.size,
        problem.n_specimens,
        options.retry_alpha,
        thorough.n_starts,
        int(better.sum()),
    )
    return dataclasses.replace(
        sol,
        x=x,
        success=success,
        x_low=x_low,
        x_high=x_high,
        nit=max(sol.nit, again.nit),
        message=f"{sol.message}; {bad.size} not explained within the noise refitted from "
        f"{thorough.n_starts} starts, {int(better.sum())} better",
        info={**sol.info, "n_refitted": int(bad.size), "n_refit_improved": int(better.sum())},
    )


@register_calibrator("pgd")
def calibrate_pgd(
    problem: CalibrationProblem,
    *,
    rng: np.random.Generator,
    start_bank: np.ndarray | None = None,
    **options: Any,
) -> Solution:
    """The registered ``pgd`` calibrator: :func:`pgd` with the keywords of :class:`PgdOptions`."""
    return pgd(problem, PgdOptions(**options), rng=rng, start_bank=start_bank)


calibrate_pgd.__signature__ = inspect.Signature(
    [
        *list(inspect.signature(pgd).parameters.values())[:1],
        *list(inspect.signature(pgd).parameters.values())[2:4],
        *(
            inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default)
            for f in dataclasses.fields(PgdOptions)
        ),
    ],
    return_annotation=Solution,
)
