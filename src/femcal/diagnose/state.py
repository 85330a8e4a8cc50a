"""The state a diagnosis' steps share: the cohort, its noise, and every model fitted so far."""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from femcal.calibration.model import CurveModel
from femcal.diagnose.explain import adequate_quick
from femcal.diagnose.fits import Fit, fit_from, fit_solutions
from femcal.diagnose.options import DiagnoseOptions
from femcal.effects.composite import EffectModel
from femcal.effects.terms import Model, Term


@dataclass
class DiagnosisState:
    """What the steps of :func:`femcal.diagnose.diagnose` read and update.

    Attributes
    ----------
    base : CurveModel
        The disc surrogate on the measurement grid.
    specimens : list of str, length n
    measured : ndarray, shape (n, 4, m)
        RoM (deg), NaN where not measured (or of weight 0).
    weight : ndarray, shape (n, 4, m)
        Relative fit weights ``1 / sigma^2``.
    sigma : ndarray, shape (n, 4, m)
        Each point's sd: the noise over the root of its weight and the surrogate's error.
    sigma_m : ndarray, shape (m,)
        The sd of a point of weight 1.
    surrogate_sd : ndarray, shape (n, 4, m)
        The surrogate's own part of each point's sd (deg).
    options : DiagnoseOptions
    candidates : list of Term
        The effects the search may add (each a term of its own).
    start_bank : ndarray, shape (N, 13), or None
        Disc configurations to start from.
    rng : numpy.random.Generator
        The disc-alone fit's draws; the later steps draw from :meth:`model_rng`.
    per_spec : list of dict
        Per specimen, every fitted model: ``Model -> (fit, row in the fit)``.
    chosen : list of Model
        Per specimen, the model the steps chose so far.

    The steps of :func:`femcal.diagnose.diagnose` after the disc alone change ``per_spec``
    (through :meth:`fit` and :meth:`record`; each fit's effective parameters are computed on
    first use) and ``chosen``; everything else is set before them. The description reads the
    state and changes nothing in it.
    """

    base: CurveModel
    specimens: list[str]
    measured: np.ndarray
    weight: np.ndarray
    sigma: np.ndarray
    sigma_m: np.ndarray
    surrogate_sd: np.ndarray
    options: DiagnoseOptions
    candidates: list[Term]
    start_bank: np.ndarray | None
    rng: np.random.Generator
    per_spec: list[dict[Model, tuple[Fit, int]]] = field(default_factory=list)
    chosen: list[Model] = field(default_factory=list)
    _models: dict[Model, EffectModel] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.specimens)

    @property
    def mask(self) -> np.ndarray:
        """Bool (n, 4, m): the measured points."""
        return np.isfinite(self.measured)

    @property
    def n_points(self) -> np.ndarray:
        """Measured points per specimen (n,)."""
        return self.mask.reshape(self.n, -1).sum(1).astype(float)

    @property
    def log_n(self) -> np.ndarray:
        """What one effective parameter costs in the criterion, ``ln n`` (n,)."""
        return np.log(np.maximum(self.n_points, 2.0))

    def model(self, effects: Model) -> CurveModel:
        """The disc (the empty model) or the disc with ``effects``, built once."""
        if not effects:
            return self.base
        if effects not in self._models:
            self._models[effects] = EffectModel(self.base, list(effects))
        return self._models[effects]

    def model_rng(self, effects: Model) -> np.random.Generator:
        """A generator of its own for model ``effects``, from the options' seed and the
        model's name: its draws do not depend on which specimens are diagnosed together."""
        key = zlib.crc32("+".join(effects.key).encode())
        return np.random.default_rng([self.options.seed, key])

    def rows(self, rows: Sequence[int]) -> DiagnosisState:
        """The state of specimens ``rows`` alone, with their fits so far (each fit's rows
        renumbered)."""
        rows = [int(i) for i in rows]
        sub = DiagnosisState(
            base=self.base,
            specimens=[self.specimens[i] for i in rows],
            measured=self.measured[rows],
            weight=self.weight[rows],
            sigma=self.sigma[rows],
            sigma_m=self.sigma_m,
            surrogate_sd=self.surrogate_sd[rows],
            options=self.options,
            candidates=self.candidates,
            start_bank=self.start_bank,
            rng=self.rng,
        )
        sub.chosen = [self.chosen[i] for i in rows] if self.chosen else [Model() for _ in rows]
        sub.per_spec = [{} for _ in rows]
        fits = {id(f): f for i in rows for f, _ in self.per_spec[i].values()}
        for fit in fits.values():
            keep = [pos for pos, i in enumerate(fit.rows) if int(i) in rows]
            sub.record(fit.take(keep, [rows.index(int(fit.rows[pos])) for pos in keep]))
        return sub

    def record(self, fit: Fit) -> None:
        """Keep a batch fit as each of its specimens' fit of its model."""
        for pos, i in enumerate(fit.rows):
            self.per_spec[int(i)][fit.effects] = (fit, pos)

    def fit(self, effects: Model, rows: np.ndarray, starts: torch.Tensor) -> Fit:
        """Fit model ``effects`` to specimens ``rows`` (r,) from ``starts`` (r, g, dim); the
        best start per specimen, recorded."""
        model = self.model(effects)
        rows = np.asarray(rows)
        v, pred, chi2 = fit_from(
            model, self.measured, self.weight, self.sigma, rows, starts, self.options.max_iter
        )
        fit = Fit(effects, model, v, rows, pred, chi2, model.dim)
        self.record(fit)
        return fit

    def solutions(self, rows: Sequence[int], effects: Model) -> torch.Tensor:
        """Unit coordinates (r, dim) of model ``effects`` fitted to specimens ``rows``."""
        return fit_solutions(self.per_spec, rows, effects)

    def criterion(self, effects: Model, i: int) -> float:
        """Specimen ``i``'s criterion of a fitted model: ``chi^2 + k ln n``, ``k`` the
        effective number of parameters."""
        fit, pos = self.per_spec[i][effects]
        return fit.criterion(pos, float(self.log_n[i]), self.mask, self.sigma)

    def adequate(self, effects: Model, i: int) -> bool:
        """Whether model ``effects`` explains specimen ``i`` within the noise (chi-square with
        the effective degrees of freedom, and sign runs)."""
        fit, pos = self.per_spec[i][effects]
        fit.ensure_trace(self.mask, self.sigma)
        return adequate_quick(
            fit, pos, i, self.measured, self.sigma, self.n_points, self.options.alpha
        )
