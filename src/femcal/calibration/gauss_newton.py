"""Projected Levenberg-Marquardt (Gauss-Newton) over a batch of starts, the core of ``pgd``.

Every specimen and every start of a batch is one row of one tensor. Each iteration computes the
curves and their Jacobian (exact, or from fewer ensemble members in the first iterations),
solves the damped normal equations with the variables held at an active bound frozen, and
projects the step onto the box (``clamp`` to [0, 1]). A step is kept only if it lowers the
loss; converged rows leave the batch.
"""

from __future__ import annotations

import torch

from femcal.calibration.base import CalibrationProblem
from femcal.calibration.pgd_options import GaussNewtonOptions
from femcal.calibration.progress import report_step

#: With ``settle_exact``: a row on the cheaper Jacobian goes on with the exact one once a kept
#: step lowers its loss by less than this fraction (the cheaper Jacobian converges only
#: linearly there).
_SETTLE_GAIN = 0.01


def gn_residual(problem, rows, pred):
    """The masked residuals of predicted curves against the targets of specimens ``rows``.

    Parameters
    ----------
    problem : CalibrationProblem
        Holds ``target`` (n, 4, m) in degrees and ``mask`` (n, 4, m).
    rows : Tensor of int, shape (B,)
        The specimen of each row.
    pred : Tensor, shape (B, 4, m)
        Predicted RoM in degrees.

    Returns
    -------
    Tensor, shape (B, 4 * m)
        ``pred - target`` in degrees, 0 where a point is not measured.
    """
    return ((pred - problem.target[rows]) * problem.mask[rows]).reshape(len(rows), -1)


def gn_cost(r, w, loss):
    """The weighted loss of each row: ``sum(w * |r|)`` for ``"l1"``, ``sum(w * r**2)`` else.

    Parameters
    ----------
    r : Tensor, shape (B, 4 * m)
        Residuals in degrees (:func:`gn_residual`).
    w : Tensor, shape (B, 4 * m)
        Point weights (relative inverse noise variances), 0 where not measured.
    loss : {"l2", "l1"}
        The loss.

    Returns
    -------
    Tensor, shape (B,)
        The loss of each row, in degrees (l1) or squared degrees (l2) times weight.
    """
    return (w * r.abs()).sum(1) if loss == "l1" else (w * r**2).sum(1)


def gauss_newton(
    problem: CalibrationProblem,
    v: torch.Tensor,
    rows: torch.Tensor,
    options: GaussNewtonOptions,
) -> tuple[torch.Tensor, int, torch.Tensor]:
    """Projected Levenberg-Marquardt from starts ``v`` (B, d) for specimens ``rows`` (B,).

    A row has converged when a kept step lowers the loss by less than ``options.tol``
    (relative), when its RMS residual falls below ``options.atol_deg``, when the step is below
    1e-6 in unit coordinates, or when the damping has grown past 1e6 (no step lowers the loss).
    Successive halving and the cheaper Jacobian of the first iterations follow ``options``
    (:class:`~femcal.calibration.pgd_options.GaussNewtonOptions`).

    Returns the final ``v`` (B, d), the number of iterations run and a bool (B,) "converged".
    """
    v, nit, converged, _ = gauss_newton_residuals(problem, v, rows, options)
    return v, nit, converged


def gauss_newton_residuals(
    problem: CalibrationProblem,
    v: torch.Tensor,
    rows: torch.Tensor,
    options: GaussNewtonOptions,
) -> tuple[torch.Tensor, int, torch.Tensor, torch.Tensor]:
    """:func:`gauss_newton`, and the residuals (B, 4 * m) at the final ``v``: the curves less
    the targets, 0 where not measured (no further evaluation of the curves)."""
    o = options
    max_iter, loss, tol, atol_deg, l1_delta = o.max_iter, o.loss, o.tol, o.atol_deg, o.l1_delta
    keep_after, keep, keep_first = o.keep_after, o.keep, o.keep_first
    jacobian_members, exact_final = o.jacobian_members, o.exact_final
    model = problem.model
    v = v.clone()
    b, d = v.shape
    w = problem.weight[rows].reshape(b, -1)
    lam = torch.full((b,), 1e-3)
    converged = torch.zeros(b, dtype=torch.bool)
    need_jac = torch.ones(b, dtype=torch.bool)
    # Rows on the exact Jacobian: all without jacobian_members; with settle_exact, the rows
    # that converged on the cheaper one.
    exact = torch.full((b,), not jacobian_members, dtype=torch.bool)
    jac = torch.zeros((b, w.shape[1], d))
    res = torch.zeros_like(w)  # at the current v of every row evaluated so far
    active = torch.arange(b)
    eye = torch.eye(d)
    nit = 0
    n_specimens = int(torch.unique(rows).numel())
    for nit in range(1, max_iter + 1):
        if keep_after and keep and nit == keep_after + 1:
            active = _keep_best(problem, rows, active, keep, w, loss, keep_first, res)
        if active.numel() == 0:
            nit -= 1
            break
        report_step(
            f"Gauss-Newton iteration {nit}/{max_iter}",
            settled=n_specimens - int(torch.unique(rows[active]).numel()),
            of=n_specimens,
        )
        if jacobian_members and nit == max_iter - exact_final + 1:
            need_jac[~exact] = True  # switch to the exact Jacobian for the final iterations
            exact[:] = True
        fresh = active[need_jac[active]]
        for on_exact in (False, True):
            part = fresh[exact[fresh] == on_exact]
            if not part.numel():
                continue
            f, jf = model.curves_jacobian(
                v[part], jacobian_members=None if on_exact else jacobian_members
            )
            res[part] = gn_residual(problem, rows[part], f)
            mask = problem.mask[rows[part]].reshape(part.numel(), -1, 1)
            jac[part] = jf.reshape(part.numel(), -1, d) * mask
        need_jac[fresh] = False
        a_idx = active
        r, jj, wa = res[a_idx], jac[a_idx], w[a_idx]
        cost = gn_cost(r, wa, loss)
        wk = wa / r.abs().clamp_min(l1_delta) if loss == "l1" else wa
        jtw = jj.transpose(1, 2) * wk[:, None, :]
        hess = jtw @ jj
        grad = (jtw @ r[..., None])[..., 0]
        va = v[a_idx]
        # Variables at a bound whose gradient points outward are frozen (projected Newton).
        blocked = ((va <= 0) & (grad > 0)) | ((va >= 1) & (grad < 0))
        free = (~blocked).float()
        hf = hess * free[:, :, None] * free[:, None, :]
        diag = torch.diagonal(hf, dim1=1, dim2=2)
        damp = lam[a_idx, None] * (diag + 1e-6) + 1e-9
        system = hf + torch.diag_embed(damp) + eye * (1 - free)[:, None, :] * eye
        step = torch.linalg.solve(system, -(grad * free)[..., None])[..., 0]
        v_new = (va + step).clamp(0.0, 1.0)
        with torch.no_grad():
            r_new = gn_residual(problem, rows[a_idx], model.curves(v_new))
        cost_new = gn_cost(r_new, wa, loss)
        ok = cost_new < cost
        gain = (cost - cost_new) / cost.clamp_min(1e-30)
        v[a_idx[ok]] = v_new[ok]
        res[a_idx[ok]] = r_new[ok]
        need_jac[a_idx[ok]] = True
        lam[a_idx] = torch.where(ok, lam[a_idx] / 3, lam[a_idx] * 4)
        tiny_step = step.abs().amax(1) < 1e-6
        rms2 = (wa * r_new**2).sum(1) / wa.sum(1)
        atol = atol_deg[rows[a_idx]] if torch.is_tensor(atol_deg) else atol_deg
        fitted = rms2 < atol**2  # RMS residual below atol_deg
        done = (ok & ((gain < tol) | fitted)) | tiny_step | (lam[a_idx] > 1e6)
        if o.settle_exact:  # near convergence on the cheaper Jacobian: on with the exact one
            cheap = (done | (ok & (gain < _SETTLE_GAIN))) & ~exact[a_idx]
            exact[a_idx[cheap]] = need_jac[a_idx[cheap]] = True
            lam[a_idx[cheap]] = 1e-3
            done &= ~cheap
        converged[a_idx[done]] = True
        active = a_idx[~done]
    return v, nit, converged, res


def _keep_best(problem, rows, active, keep, w, loss, keep_first: bool, res) -> torch.Tensor:
    """The active rows among the ``keep`` lowest-loss starts of each specimen (and its first
    start with ``keep_first``), by the residuals ``res`` (B, 4 * m) at the rows' current
    parameters."""
    cost = torch.nan_to_num(gn_cost(res, w, loss), nan=float("inf"))
    n = problem.n_specimens
    k = len(rows) // n
    if k <= keep:
        return active
    ranked = cost.reshape(n, k).argsort(1)[:, :keep]
    chosen = torch.zeros(len(rows), dtype=torch.bool)
    chosen[(torch.arange(n)[:, None] * k + ranked).reshape(-1)] = True
    if keep_first:
        chosen[torch.arange(n) * k] = True
    return active[chosen[active]]
