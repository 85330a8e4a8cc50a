"""``pgd-study``: the study's PGD with its published settings, for side-by-side comparison.

Atad et al. (Algorithm 1): the search matrix holds one copy of the parameters per measured
row (load case, moment); Adam (lr 0.0971) minimises the L1 loss averaged over the rows; the
projection replaces every row by the rows' mean clipped to the bounds (ClipBounds), in the
study's min-max unit box; M = 500 uniform random starts run in parallel for T = 2250 steps and
the start with the best mean R² over load cases wins.

Because the projection leaves all rows identical, row ``r`` of a start sees the shared point
``p``; its gradient is ``sign(f_r(p) - y_r) / k * grad f_r(p)``. Those per-row gradients are the
rows of the Jacobian at ``p``, computed in one forward-mode pass instead of ``k`` separate
network evaluations; each row keeps its own Adam moments exactly as in the study, so the
iterates are the study's.

Ablations of the study's Table (``projection``, ``bounds_penalty``, ``loss``, ``optimizer``):
``projection="average"`` keeps the row averaging but drops the clipping (the study's "no
projection": the parameters may leave the box); ``bounds_penalty > 0`` adds
``penalty * sum(relu(u - 1) + relu(-u))`` to the loss; ``loss="l2"``; ``optimizer="lbfgs"``
(torch's L-BFGS on the shared point, projected after every step).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from typing import Any

import numpy as np
import torch

from femcal.calibration.base import CalibrationProblem, Solution, register_calibrator
from femcal.calibration.pgd_study_options import PgdStudyOptions

logger = logging.getLogger(__name__)

_BETA1, _BETA2, _EPS = 0.9, 0.999, 1e-8


def _unit_chain(problem: CalibrationProblem, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Network coordinates v(u) and the diagonal derivative dv/du, both (B, d)."""
    uu = u.detach().clone().requires_grad_(True)
    v = problem.model.from_linear_unit(uu)
    (dvdu,) = torch.autograd.grad(v.sum(), uu)
    return v.detach(), dvdu


def _row_loss_grad(r: torch.Tensor, loss: str) -> torch.Tensor:
    return torch.sign(r) if loss == "l1" else 2.0 * r


def _penalty_grad(u: torch.Tensor) -> torch.Tensor:
    return (u > 1).float() - (u < 0).float()


def pgd_study(
    problem: CalibrationProblem,
    options: PgdStudyOptions | None = None,
    *,
    rng: np.random.Generator,
    **overrides: Any,
) -> Solution:
    """The study's projected Adam calibration (see the module docstring).

    Parameters
    ----------
    problem : CalibrationProblem
        Targets of n specimens and the surrogate.
    options : PgdStudyOptions, optional
        Starts, steps, learning rate, loss, projection, penalty, optimiser and selection
        (default: the study's settings).
    rng : numpy.random.Generator
        Source of the uniform starts.
    **overrides
        Fields of :class:`PgdStudyOptions` replacing those of ``options``.

    Returns
    -------
    Solution
        ``x`` in physical units, outside the box only for the unprojected ablations.
    """
    o = dataclasses.replace(options or PgdStudyOptions(), **overrides)
    n_starts, steps = o.n_starts, o.steps
    n, d = problem.n_specimens, problem.dim
    rows = torch.arange(n).repeat_interleave(n_starts)
    u = torch.tensor(rng.random((n * n_starts, d)), dtype=torch.float32)
    mask = problem.mask[rows].reshape(len(rows), -1)  # (B, R)
    w = problem.weight[rows].reshape(len(rows), -1)
    k = mask.sum(1, keepdim=True).float()  # measured rows per start
    y = problem.target[rows].reshape(len(rows), -1)
    clip = o.projection == "clip"
    run = _adam if o.optimizer == "adam" else _lbfgs
    u = run(problem, u, (y, mask, w, k), steps, o.lr, o.loss, o.bounds_penalty, clip)
    with torch.no_grad():
        scores = problem.scores(problem.model.curves(problem.model.from_linear_unit(u)), rows)
    key = -scores["r2"] if o.select == "r2" else scores["mae"]
    key = torch.nan_to_num(key, nan=float("inf")).reshape(n, n_starts)
    best = key.argmin(1)
    u_best = u.reshape(n, n_starts, d)[torch.arange(n), best].double().numpy()
    x = problem.model.linear_unit_to_physical(u_best)
    if clip:
        x = problem.model.space.clip(x)
    return Solution(
        x=x,
        nit=steps,
        success=np.ones(n, dtype=bool),
        message=(
            f"pgd-study ({o.optimizer}, {o.loss}, projection={o.projection}, "
            f"penalty={o.bounds_penalty}): {n_starts} starts x {steps} steps, lr {o.lr}"
        ),
        info={k: v for k, v in dataclasses.asdict(o).items() if k != "select"},
    )


@register_calibrator("pgd-study")
def calibrate_pgd_study(
    problem: CalibrationProblem, *, rng: np.random.Generator, **options: Any
) -> Solution:
    """The registered ``pgd-study`` calibrator: :func:`pgd_study` with the keywords of
    :class:`PgdStudyOptions`."""
    return pgd_study(problem, PgdStudyOptions(**options), rng=rng)


calibrate_pgd_study.__signature__ = inspect.Signature(
    [
        *list(inspect.signature(pgd_study).parameters.values())[:1],
        list(inspect.signature(pgd_study).parameters.values())[2],
        *(
            inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default)
            for f in dataclasses.fields(PgdStudyOptions)
        ),
    ],
    return_annotation=Solution,
)


def _adam(
    problem: CalibrationProblem,
    u: torch.Tensor,
    rows_data: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    steps: int,
    lr: float,
    loss: str,
    bounds_penalty: float,
    clip: bool,
) -> torch.Tensor:
    """The study's projected Adam from the starts ``u`` (B, d) in the linear unit box.

    ``rows_data`` holds the targets ``y`` (B, R), the measured-row ``mask`` (B, R), the weights
    ``w`` (B, R) and the measured rows per start ``k`` (B, 1). Each load-case row takes its own
    Adam step; the start moves to their mean over the measured rows (clipped to the box with
    ``clip``). Returns the final starts (B, d).
    """
    y, mask, w, k = rows_data
    b, d = u.shape
    m1 = torch.zeros((b, y.shape[1], d))
    m2 = torch.zeros_like(m1)
    for t in range(1, steps + 1):
        v, dvdu = _unit_chain(problem, u)
        f, jac = problem.model.curves_jacobian(v)
        r = (f.reshape(b, -1) - y) * mask
        jac_u = jac.reshape(b, -1, d) * dvdu[:, None, :]
        g = (w * _row_loss_grad(r, loss) / k)[..., None] * jac_u  # (B, R, d)
        if bounds_penalty:
            g = g + bounds_penalty * _penalty_grad(u)[:, None, :]
        g = g * mask[..., None]
        m1.mul_(_BETA1).add_(g, alpha=1 - _BETA1)
        m2.mul_(_BETA2).addcmul_(g, g, value=1 - _BETA2)
        step = lr * (m1 / (1 - _BETA1**t)) / ((m2 / (1 - _BETA2**t)).sqrt() + _EPS)
        rows_x = u[:, None, :] - step  # every row's own update
        u = (rows_x * mask[..., None]).sum(1) / k  # the mean over the measured rows
        if clip:
            u = u.clamp(0.0, 1.0)
    return u


def _lbfgs(
    problem: CalibrationProblem,
    u: torch.Tensor,
    rows_data: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    steps: int,
    lr: float,
    loss: str,
    bounds_penalty: float,
    clip: bool,
) -> torch.Tensor:
    """torch's L-BFGS (one iteration per step) on the summed row losses from the starts ``u``
    (B, d) in the linear unit box, clipped to the box after every step with ``clip``.

    ``rows_data`` as in :func:`_adam`. Returns the final starts (B, d).
    """
    y, mask, w, k = rows_data
    b = len(u)
    p = u.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([p], lr=lr, max_iter=1, history_size=10)

    def closure() -> torch.Tensor:
        opt.zero_grad()
        f = problem.model.curves(problem.model.from_linear_unit(p))
        r = (f.reshape(b, -1) - y) * mask
        per = (w * (r.abs() if loss == "l1" else r**2)).sum(1) / k[:, 0]
        total = per.sum()
        if bounds_penalty:
            total = total + bounds_penalty * (torch.relu(p - 1).sum() + torch.relu(-p).sum())
        total.backward()
        return total

    for _ in range(steps):
        opt.step(closure)
        with torch.no_grad():
            if clip:
                p.clamp_(0.0, 1.0)
    return p.detach()
