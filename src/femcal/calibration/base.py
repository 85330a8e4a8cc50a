"""Calibrator registry and the shared problem and solution objects.

A calibrator is one function registered under a name::

    @register_calibrator("pgd")
    def pgd(problem: CalibrationProblem, *, rng: np.random.Generator, **options) -> Solution

It receives every specimen of a batch at once and returns a :class:`Solution`; the front
function :func:`femcal.calibration.result.calibrate` times the batch, evaluates the solution
through the surrogate and returns a :class:`~femcal.calibration.result.CalibrationResult`
(SciPy style: ``x``, ``fun``, ``success``, ``message``,
``nit`` plus named fields). A new calibrator is a new module that registers itself, listed in
the registry's ``builtins`` (:data:`calibrator_registry`, a :class:`~femcal.registry.Registry`),
or an installed package's entry point in the group ``femcal.calibrators``.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from femcal.calibration.model import CurveModel
from femcal.errors import ConfigError, InputDataError
from femcal.registry import Registry
from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)

#: Entry-point group of installed calibrator plugins.
ENTRY_POINT_GROUP = "femcal.calibrators"

#: The calibrator registry: the built-in methods and installed plugins (entry points of
#: :data:`ENTRY_POINT_GROUP`, a module registering functions, or a function).
calibrator_registry: Registry[Callable[..., Solution]] = Registry(
    "calibrator",
    what="calibration method",
    group=ENTRY_POINT_GROUP,
    builtins=(
        "femcal.calibration.ga",
        "femcal.calibration.inverse",
        "femcal.calibration.pgd",
        "femcal.calibration.pgd_study",
    ),
    fix=(
        'Or register your own: a function decorated with @register_calibrator("name"), in a '
        f"package with an entry point in the group {ENTRY_POINT_GROUP}."
    ),
    expects="a calibrator function",
)


def register_calibrator(
    name: str, *, replace: bool = False
) -> Callable[[Callable[..., Solution]], Callable[..., Solution]]:
    """Decorator registering a calibrator function under ``name``.

    ConfigError if another function already holds ``name`` (unless ``replace=True``).
    """
    return calibrator_registry.register(name, replace=replace)


def available_calibrators() -> list[str]:
    """Registered calibrator names, sorted."""
    return calibrator_registry.names()


def get_calibrator(name: str) -> Callable[..., Solution]:
    """The calibrator registered under ``name`` (ConfigError listing the names otherwise)."""
    return calibrator_registry.get(name)


@dataclass
class CalibrationProblem:
    """Targets of a batch of specimens on one moment grid, and the model to fit.

    Attributes
    ----------
    model : CurveModel
        The surrogate on the moment grid.
    target : Tensor, shape (n, 4, m)
        Measured RoM in degrees, 0 where not measured.
    weight : Tensor, shape (n, 4, m)
        Weight of each point (0 where not measured); each specimen's weights sum to its
        number of measured points.
    mask : Tensor of bool, shape (n, 4, m)
        Measured points.
    measured : ndarray, shape (n, 4, m)
        The targets as given, float64, NaN where not measured.
    point_sd : Tensor, shape (n,), optional
        Each specimen's error sd (deg) of a point of normalised weight 1, where the weights
        given were inverse variances (:meth:`from_arrays`' ``weight_sd``); calibrators that
        count the error scale (``pgd``'s ranges and fit tolerance) use it per specimen. None:
        one scale for the batch, the calibrator's own option.
    """

    model: CurveModel
    target: torch.Tensor
    weight: torch.Tensor
    mask: torch.Tensor
    measured: np.ndarray
    point_sd: torch.Tensor | None = None

    @property
    def n_specimens(self) -> int:
        return int(self.target.shape[0])

    @property
    def dim(self) -> int:
        return self.model.dim

    @classmethod
    def from_arrays(
        cls,
        model: CurveModel,
        rom_deg: np.ndarray,
        weight: np.ndarray | None = None,
        *,
        weight_sd: float | None = None,
    ) -> CalibrationProblem:
        """Build from measured curves (n, 4, m) with NaN = not measured.

        Each specimen's weights are scaled to a mean of 1 over its measured points. With
        ``weight_sd``, the weights given are inverse variances relative to a point of sd
        ``weight_sd`` (deg; weight 1 = that sd, e.g.
        :meth:`femcal.moments.MomentPolicy.point_weights` with its ``hypot(noise, error)``), and
        the problem keeps each specimen's error scale after the scaling:
        ``point_sd = weight_sd / sqrt(mean weight)`` (shape (n,)).
        """
        if weight_sd is not None and not (np.isfinite(weight_sd) and weight_sd > 0):
            raise ConfigError(
                f"weight_sd must be a finite sd > 0 in degrees (the error of a point of weight "
                f"1) or None; got {weight_sd!r}."
            )
        rom = np.asarray(rom_deg, dtype=float)
        if rom.ndim != 3 or rom.shape[1:] != (len(LOAD_CASES), len(model.moments)):
            raise InputDataError(
                f"Targets must have shape (n, {len(LOAD_CASES)}, {len(model.moments)}) for the "
                f"moment grid {model.moments.tolist()}; got {rom.shape}."
            )
        mask = np.isfinite(rom)
        w = np.ones_like(rom) if weight is None else np.asarray(weight, dtype=float)
        w = np.where(mask, w, 0.0)
        total = w.sum(axis=(1, 2), keepdims=True)
        if np.any(total <= 0):
            bad = np.flatnonzero(total.reshape(-1) <= 0).tolist()
            raise InputDataError(
                f"Specimens at positions {bad} have no measured point with a positive weight; "
                "give at least one RoM value per specimen."
            )
        count = mask.sum(axis=(1, 2), keepdims=True)
        w = w * count / total
        point_sd = None
        if weight_sd is not None:  # sd of a point of mean weight: weight_sd / sqrt(mean w)
            point_sd = torch.tensor(
                float(weight_sd) * np.sqrt(count / total).reshape(-1), dtype=torch.float64
            )
        return cls(
            model=model,
            target=torch.tensor(np.where(mask, rom, 0.0), dtype=torch.float32),
            weight=torch.tensor(w, dtype=torch.float32),
            mask=torch.tensor(mask),
            measured=np.where(mask, rom, np.nan),
            point_sd=point_sd,
        )

    def chi2(self, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each specimen's residuals in units of its points' own sd (needs :attr:`point_sd`).

        Parameters
        ----------
        pred : ndarray, shape (n, 4, m)
            Predicted curves, one per specimen.

        Returns
        -------
        chi2 : ndarray, shape (n,)
            ``sum_k w_k (measured_k - pred_k)^2 / point_sd^2`` over the measured points, ``w``
            the normalised weights (the sd of point k is ``point_sd / sqrt(w_k)``).
        n_points : ndarray of int, shape (n,)
            Measured points of weight > 0.
        """
        if self.point_sd is None:
            raise ConfigError(
                "chi2 needs each specimen's error scale: build the problem with weight_sd "
                "(the sd of a point of weight 1, in degrees)."
            )
        w = self.weight.double().numpy()  # 0 where not measured
        resid = np.where(w > 0, self.measured - np.asarray(pred, dtype=float), 0.0)
        scale = self.point_sd.double().numpy()
        return (w * resid**2).sum(axis=(1, 2)) / scale**2, (w > 0).sum(axis=(1, 2))

    def effective_parameters(self, x: np.ndarray, *, batch: int = 256) -> np.ndarray:
        """Each specimen's effective number of fitted parameters at ``x`` (needs
        :attr:`point_sd`): the trace of the hat matrix of the linearised fit, every point
        weighed by its own sd, the unit box as a prior (:func:`hat_trace_and_cov`, as
        ``femcal diagnose`` counts them). A parameter the data do not see counts 0.

        Parameters
        ----------
        x : ndarray, shape (n, d)
            Parameters in physical units, one row per specimen (clipped to the box).
        batch : int
            Specimens per Jacobian (bounds memory).

        Returns
        -------
        ndarray, shape (n,)
        """
        if self.point_sd is None:
            raise ConfigError(
                "effective_parameters needs each specimen's error scale: build the problem "
                "with weight_sd (the sd of a point of weight 1, in degrees)."
            )
        w = self.weight.double().numpy()
        mask = w > 0
        sd = self.point_sd.double().numpy()[:, None, None] / np.sqrt(np.where(mask, w, 1.0))
        v = self.model.from_physical(np.asarray(x, dtype=float))
        out = np.zeros(self.n_specimens)
        for lo in range(0, self.n_specimens, batch):
            hi = min(lo + batch, self.n_specimens)
            with torch.no_grad():
                _, jac = self.model.curves_jacobian(v[lo:hi])
            out[lo:hi] = hat_trace_and_cov(jac, mask[lo:hi], sd[lo:hi])[0]
        return out

    def subset(self, index: np.ndarray | slice) -> CalibrationProblem:
        """The problem restricted to some specimens."""
        return dataclasses.replace(
            self,
            target=self.target[index],
            weight=self.weight[index],
            mask=self.mask[index],
            measured=self.measured[index],
            point_sd=None if self.point_sd is None else self.point_sd[index],
        )

    def scores(
        self, pred: torch.Tensor, rows: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """Weighted MAE and mean R² over load cases of predicted curves.

        Parameters
        ----------
        pred : Tensor, shape (r, 4, m)
            Predicted curves of ``r`` candidate rows.
        rows : LongTensor, shape (r,), optional
            Specimen of each row (default: row i is specimen i).

        Returns
        -------
        dict
            ``mae`` (r,) in degrees (weighted mean of absolute errors) and ``r2`` (r,) (the
            study's mean R² over the measured load cases; unweighted).
        """
        if rows is None:
            rows = torch.arange(pred.shape[0])
        y, w, mask = self.target[rows], self.weight[rows], self.mask[rows]
        err = (pred - y) * mask
        mae = (err.abs() * w).sum((1, 2)) / mask.sum((1, 2))
        count = mask.sum(2)
        mean_y = (y * mask).sum(2, keepdim=True) / count.clamp_min(1)[..., None]
        ss_tot = (((y - mean_y) * mask) ** 2).sum(2)
        ss_res = (err**2).sum(2)
        r2 = torch.where(ss_tot > 0, 1 - ss_res / ss_tot.clamp_min(1e-30), (ss_res == 0).float())
        has = count > 0
        r2 = (r2 * has).sum(1) / has.sum(1).clamp_min(1)
        return {"mae": mae, "r2": r2}


@dataclass
class Solution:
    """What a calibrator returns for a batch of n specimens.

    Attributes
    ----------
    x : ndarray, shape (n, d)
        Calibrated parameters, physical units (inside the box unless the calibrator is an
        unprojected ablation).
    nit : int
        Iterations (optimiser steps or generations) of the batch.
    success : ndarray of bool, shape (n,)
        Whether the calibrator's own convergence test passed for each specimen.
    message : str
        What happened, in words.
    x_low, x_high : ndarray, shape (n, d), optional
        Per-parameter range of the near-optimal solutions (identifiability), physical units.
    info : dict
        Anything else worth logging (settings, counts).
    """

    x: np.ndarray
    nit: int
    success: np.ndarray
    message: str
    x_low: np.ndarray | None = None
    x_high: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)


def chi2_p_value(chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """Chi-square survival function, shape (n,): the p-value of residuals whose chi-square is
    ``chi2`` on ``dof`` degrees of freedom (floored at 1; fractional degrees of freedom, such
    as points minus a fit's effective parameters, are fine). The test of
    :attr:`CalibrationResult.p_value`, of ``pgd``'s refit and of ``femcal diagnose``'s
    adequacy."""
    from scipy.stats import chi2 as chi2_dist

    return chi2_dist.sf(chi2, np.maximum(np.asarray(dof, dtype=float), 1.0))


def hat_trace_and_cov(
    jac: torch.Tensor | np.ndarray, mask: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Effective number of fitted parameters, their covariance and Laplace's Occam factor.

    The linearised fit of ``d`` parameters in unit coordinates with the unit box as a prior of
    sd 1 per axis: with the information ``I = J^T Σ^-1 J``, the covariance is ``(I + 1)^-1``
    and the effective number of parameters the trace of the hat matrix, ``tr(I (I + 1)^-1)``
    (0 for an axis the data do not see, 1 for one they fix).

    Parameters
    ----------
    jac : Tensor or ndarray, shape (n, 4, m, d)
        The curves' Jacobian in unit coordinates; non-finite entries count as 0.
    mask : ndarray of bool, shape (n, 4, m)
        Measured points.
    sigma : ndarray, shape (n, 4, m) or broadcastable
        Each point's sd (deg).

    Returns
    -------
    trace : ndarray, shape (n,)
    cov : ndarray, shape (n, d, d)
    occam : ndarray, shape (n,)
        ``ln det(1 + I / 2 pi)``: the posterior's volume over the box's (a Gaussian of
        variance ``1 / 2 pi`` per axis has the box's volume, so an axis the data do not fix
        costs nothing and a fixed one ``ln(information / 2 pi)``).
    """
    jac = jac.double().numpy() if isinstance(jac, torch.Tensor) else np.asarray(jac, float)
    n, d = jac.shape[0], jac.shape[-1]
    j = jac / np.broadcast_to(sigma, mask.shape)[..., None]
    j = np.where(mask[..., None], np.nan_to_num(j, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    j = j.reshape(n, -1, d)
    info = np.einsum("npi,npj->nij", j, j)
    cov = np.linalg.inv(info + np.eye(d))
    trace = np.einsum("nij,nji->n", info, cov)
    _, occam = np.linalg.slogdet(np.eye(d) + info / (2 * np.pi))
    return trace, cov, occam
