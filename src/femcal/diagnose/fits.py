"""Fitting a model to many specimens at once: starts, Gauss-Newton from them, the chi-square,
the hat trace and the parameter covariance.

*Starts* have one shape throughout the search: a tensor (r, g, dim), ``g`` starts of unit
coordinates for each of ``r`` specimens (``g = 1`` for one start each). Only
:func:`fit_from` lays them out as Gauss-Newton takes them, through :class:`Starts`, which
holds every conversion between the two layouts.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from femcal.calibration.base import CalibrationProblem, hat_trace_and_cov
from femcal.calibration.gauss_newton import gauss_newton_residuals
from femcal.calibration.pgd_options import GaussNewtonOptions
from femcal.calibration.starts import single_effect_starts
from femcal.effects.base import get_effect
from femcal.effects.composite import EffectModel
from femcal.effects.split import is_split_effect
from femcal.effects.terms import Model, Term

if TYPE_CHECKING:
    from femcal.diagnose.options import DiagnoseOptions

#: A fit has converged when a step lowers its chi-square by less than this fraction.
_GN_TOL = 1e-6
#: Successive halving of a fit's starts: after ``keep_after`` iterations only the ``keep``
#: best go on. A model with a split form keeps more starts for longer: its per-load-case
#: parameters leave the tied compromise slowly, and the start that wins is often not among the
#: best two after three iterations.
_KEEP = {"keep_after": 3, "keep": 2}
_KEEP_SPLIT = {"keep_after": 5, "keep": 4}


@dataclass(frozen=True)
class Starts:
    """A batch's starts and their layout for Gauss-Newton, which takes them flat: (r * g, dim),
    each specimen's ``g`` starts together.

    Attributes
    ----------
    values : Tensor, shape (r, g, dim)
        ``g`` starts of unit coordinates for each of ``r`` specimens.
    """

    values: torch.Tensor

    @property
    def g(self) -> int:
        """Starts per specimen."""
        return int(self.values.shape[1])

    @property
    def flat(self) -> torch.Tensor:
        """The starts (r * g, dim), each specimen's ``g`` together."""
        r, g, dim = self.values.shape
        return self.values.reshape(r * g, dim)

    @property
    def owner(self) -> torch.Tensor:
        """Each flat start's specimen, its position in the batch (r * g,)."""
        return torch.arange(self.values.shape[0]).repeat_interleave(self.g)

    def per_specimen(self, flat: np.ndarray, *shape: int) -> np.ndarray:
        """A value of each flat start (r * g, prod(shape)) as (r, g, *shape)."""
        return flat.reshape(self.values.shape[0], self.g, *shape)

    def pick(self, flat: torch.Tensor, best: np.ndarray) -> torch.Tensor:
        """Rows (r, ...) of ``flat`` (r * g, ...): each specimen's start ``best`` (r,)."""
        return flat[torch.as_tensor(np.arange(self.values.shape[0]) * self.g + best)]


# ------------------------------------------------------------------------ fitting helpers
def point_weights(sigma: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Relative weights 1/sigma^2 of every point (the optimiser normalises them).

    Parameters
    ----------
    sigma : ndarray, shape broadcastable to ``shape``
        Noise sd in degrees, for example (n, 4, m) or (n, 1, 1).
    shape : tuple of int
        The weights' shape, for example (n, 4, m).

    Returns
    -------
    ndarray, shape ``shape``
        ``(min(sigma) / sigma) ** 2``: 1 at the smallest noise, dimensionless (a read-only
        broadcast view).
    """
    return np.broadcast_to((sigma.min() / sigma) ** 2, shape)


def chi_square(pred: torch.Tensor, measured: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Chi-square over the measured points, shape (n,): ``pred`` (n, 4, m), ``measured``
    (n, 4, m) NaN where not measured, ``sigma`` (n, 4, m). A prediction that is not finite at a
    measured point makes it inf (that model cannot be chosen), not a skipped point."""
    z = np.where(np.isfinite(measured), (measured - pred.double().numpy()) / sigma, 0.0)
    chi2 = (z**2).sum(axis=(1, 2))
    return np.where(np.isfinite(chi2), chi2, np.inf)


def fit_starts(
    model: EffectModel,
    effects: Model,
    prev: Model,
    v_prev: torch.Tensor,
    new: Term,
    options: DiagnoseOptions,
) -> torch.Tensor:
    """Starts (n, g, dim) of ``model`` (the EffectModel of ``effects``, ``prev`` and ``new``):
    the previous solution ``v_prev`` (n, dim of ``prev``: disc + its effects) and a grid over
    ``new``'s box (:func:`femcal.calibration.starts.single_effect_starts` with the options'
    ``effect_levels``, ``shape_starts`` and ``grid_shapes``)."""
    n = v_prev.shape[0]
    grid = single_effect_starts(
        model.effects[effects.terms.index(new)],
        options.effect_levels,
        options.shape_starts,
        options.grid_shapes,
    )
    v0 = torch.empty((n, len(grid), model.dim))
    v0[:, :, : model.n_disc] = v_prev[:, None, : model.n_disc]
    prev_model_slices = _slices_of(prev)
    for term, sl in zip(effects, model._slices):
        if term == new:
            v0[:, :, sl] = grid[None]
        else:
            a, b = prev_model_slices[term]
            v0[:, :, sl] = v_prev[:, None, model.n_disc + a : model.n_disc + b]
    return v0


def _slices_of(effects: Model) -> dict[Term, tuple[int, int]]:
    """Offsets of each term's parameters after the disc's, in an EffectModel of ``effects``."""
    out, start = {}, 0
    for term in effects:
        p = len(get_effect(term).parameters)
        out[term] = (start, start + p)
        start += p
    return out


def _split_start(v: torch.Tensor, effects: Model, split: Model) -> torch.Tensor:
    """A fit of ``effects`` (r, dim) as a start (r, dim') of ``split``, the same effects with
    some in their split form (:mod:`femcal.effects.split`): each tied value copied into every
    load case, so the split form starts where the tied fit is."""
    n_disc = v.shape[1] - sum(len(get_effect(e).parameters) for e in effects)
    offsets = _slices_of(effects)
    parts = [v[:, :n_disc]]
    for term in split:
        tied = term.as_tied() if term.split else None
        a, b = offsets[tied if tied is not None and tied in offsets else term]
        block = v[:, n_disc + a : n_disc + b]
        expand = term.split and term not in offsets
        parts.append(get_effect(term).expand_tied(block) if expand else block)
    return torch.cat(parts, dim=1)


def split_starts(
    v: torch.Tensor, effects: Model, split: Model, levels: Sequence[float]
) -> torch.Tensor:
    """Starts (r, g, dim') of ``split`` from a fit of ``effects`` (r, dim): the tied values
    copied into every load case (:func:`_split_start`), then, one at a time, each per-load-case
    copy of a newly split effect at each unit level of ``levels`` (a load case whose contact
    or slack lies far from the tied compromise is not reached from it)."""
    first = _split_start(v, effects, split)
    n_disc = v.shape[1] - sum(len(get_effect(e).parameters) for e in effects)
    offsets = _slices_of(split)
    columns = []
    for term in split:
        if term in effects or not term.split:
            continue
        cls = get_effect(term)
        tied = {q.name for q in cls.tied.parameters if q.per_load_case}
        a = offsets[term][0]
        columns += [n_disc + a + j for j, q in enumerate(cls.parameters) if q.name not in tied]
    starts = [first]
    for col in columns:
        for level in levels:
            start = first.clone()
            start[:, col] = float(level)
            starts.append(start)
    return torch.stack(starts, dim=1)


def fit_solutions(per_spec: list[dict], rows, effects: Model) -> torch.Tensor:
    """Unit coordinates (len(rows), dim) of model ``effects`` fitted to specimens ``rows``."""
    return torch.stack([per_spec[i][effects][0].v[per_spec[i][effects][1]] for i in rows])


def design_columns(n_disc: int, effects: Model, rest: Model) -> list[int]:
    """Columns of an EffectModel of ``effects`` that an EffectModel of ``rest`` keeps."""
    offsets = _slices_of(effects)
    return list(range(n_disc)) + [n_disc + c for e in rest for c in range(*offsets[e])]


@dataclass
class Fit:
    """One model fitted to a set of specimens: its parameters, curves and goodness of fit.

    Attributes
    ----------
    effects : Model
        The effects added to the disc (none: the disc alone).
    model : CurveModel
        The fitted curve model.
    v : Tensor, shape (r, dim)
        Best parameters in unit coordinates, one row per specimen of ``rows``.
    rows : ndarray of int, shape (r,)
        Specimen indices.
    pred : Tensor, shape (r, 4, m)
        Fitted RoM in degrees.
    chi2 : ndarray, shape (r,)
        Chi-square of each specimen's fit (residuals over the stated noise).
    k : int
        Number of model parameters.
    trace, cov, finite, occam : ndarray or None
        Effective number of parameters (r,), parameter covariance (r, dim, dim) in unit
        coordinates, whether the Jacobian is finite (r,), and ln det(I + J^T J / 2 pi) (r,).
    """

    effects: Model
    model: Any
    v: torch.Tensor  # (r, dim) for the specimens ``rows``
    rows: np.ndarray  # specimen indices
    pred: torch.Tensor  # (r, 4, m)
    chi2: np.ndarray  # (r,)
    k: int
    trace: np.ndarray | None = None  # (r,) effective number of parameters
    cov: np.ndarray | None = None  # (r, dim, dim) parameter covariance, unit coordinates
    finite: np.ndarray | None = None  # (r,) the Jacobian is finite
    occam: np.ndarray | None = None  # (r,) ln det(I + J^T J / 2 pi), unit coordinates

    def take(self, positions: Sequence[int], rows: Sequence[int]) -> Fit:
        """The fit of the batch members at ``positions``, renumbered as specimens ``rows``."""
        pos = list(positions)
        sel = torch.as_tensor(pos, dtype=torch.long)

        def part(x):
            return None if x is None else x[pos]

        return Fit(
            self.effects,
            self.model,
            self.v[sel],
            np.asarray(rows, dtype=int),
            None if self.pred is None else self.pred[sel],
            self.chi2[pos],
            self.k,
            part(self.trace),
            part(self.cov),
            part(self.finite),
            part(self.occam),
        )

    def ensure_trace(self, mask: np.ndarray, sigma: np.ndarray) -> None:
        """Effective parameters, covariance and finiteness from one Jacobian of the batch
        (once; ``mask`` and ``sigma`` (n, 4, m) of the whole cohort)."""
        if self.trace is not None:
            return
        _, jac = self.model.curves_jacobian(self.v)
        self.trace, self.cov, self.occam = hat_trace_and_cov(jac, mask[self.rows], sigma[self.rows])
        self.finite = torch.isfinite(jac).reshape(len(self.rows), -1).all(1).numpy()

    def criterion(self, pos: int, cost: float, mask: np.ndarray, sigma: np.ndarray) -> float:
        """Criterion of specimen ``pos`` of the batch: ``chi^2 + cost k``, ``cost`` = ``ln n``
        (the Bayesian information criterion) and ``k`` the effective number of parameters,
        the trace of the hat matrix under the unit-box prior (:meth:`ensure_trace`): the
        disc's parameters that RoM does not determine cost nothing."""
        self.ensure_trace(mask, sigma)
        return float(self.chi2[pos] + float(self.trace[pos]) * cost)


def fit_from(model, measured, weight, sigma, rows: np.ndarray, starts: torch.Tensor, max_iter: int):
    """Gauss-Newton from ``starts`` (r, g, dim) of the specimens ``rows`` (r,); the best start
    per specimen: unit coordinates (r, dim), curves (r, 4, m) and chi-square (r,).

    Parameters
    ----------
    model : CurveModel
        The model fitted.
    measured : ndarray, shape (n, 4, m)
        Measured RoM in degrees, NaN where not measured.
    weight : ndarray, shape (n, 4, m)
        Point weights (:func:`point_weights`).
    sigma : ndarray, shape (n, 4, m)
        Noise sd in degrees.
    rows : ndarray of int, shape (r,)
        The specimens fitted.
    starts : Tensor, shape (r, g, dim)
        ``g`` starts per specimen in unit coordinates.
    max_iter : int
        Gauss-Newton iterations at most.

    Returns
    -------
    v : Tensor, shape (r, dim)
    pred : Tensor, shape (r, 4, m)
    chi2 : ndarray, shape (r,)

    The starts are ranked by the chi-square of Gauss-Newton's own final residuals; only the
    best start's curves are evaluated again (its chi-square from them). The Jacobian is exact
    throughout: one from fewer ensemble members in the first iterations
    (``GaussNewtonOptions.jacobian_members``) moves near-tied verdicts, outside the box most."""
    problem = CalibrationProblem.from_arrays(model, measured[rows], weight[rows])
    layout = Starts(starts)
    split = any(is_split_effect(e) for e in getattr(model, "effects", ()))
    keep = _KEEP_SPLIT if split else _KEEP
    keep = keep if layout.g > keep["keep"] else {}
    options = GaussNewtonOptions(max_iter=max_iter, loss="l2", tol=_GN_TOL, **keep)
    v, _, _, res = gauss_newton_residuals(problem, layout.flat, layout.owner, options)
    z = layout.per_specimen(res.double().numpy(), *measured.shape[1:]) / sigma[rows][:, None]
    chi2 = (np.where(np.isfinite(measured[rows])[:, None], z, 0.0) ** 2).sum(axis=(2, 3))
    best = np.nan_to_num(chi2, nan=np.inf, posinf=np.inf).argmin(1)
    v = layout.pick(v, best)
    with torch.no_grad():
        pred = model.curves(v)
    return v, pred, chi_square(pred, measured[rows], sigma[rows])
