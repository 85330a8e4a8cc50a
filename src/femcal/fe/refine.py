"""FE-in-the-loop refinement of calibrated parameters (output space mapping).

A calibration through a surrogate lands where the surrogate matches the measurement, which is
not always where the FE model does: near its solution the surrogate may be off by more than
the noise, and FE then does not confirm the fit. :func:`refine_with_fe` closes that gap with
a few FE runs per specimen:

1. run FE at the current parameters ``x_k`` and measure the misfit against the measurement;
2. stop where FE confirms the fit (its MAE is within ``tol_deg``) or the budget is spent;
3. otherwise take a projected Levenberg-Marquardt step on the FE residual ``y - FE(x_k)``
   with the surrogate's Jacobian at ``x_k``: the surrogate corrected by the misfit it has
   there, ``s(x) + FE(x_k) - s(x_k)``, linearised (output space mapping, Bandler et al. 2004,
   IEEE Trans. MTT 52:337);
4. FE judges each new point: a point FE finds worse than the best so far is not taken, and
   the next try from the best point is shorter (more damping); an accepted one lowers it;
5. every FE run, taken or not, also corrects the Jacobian along its step (Broyden's rank-one
   update of the surrogate's Jacobian), so the next steps use what FE has shown.

The damping keeps the steps short along the directions the data do not identify (most of the
disc's parameters, from RoM): solving the corrected problem to the end instead moves far
along them, where the correction measured at ``x_k`` no longer holds, and FE refuses.
``tests/fe/test_refine.py`` checks both on a synthetic study; the figures with and without
the Broyden update are on the docs' page *Benchmarks > Measurements behind the defaults*.

The surrogate's Jacobian steers, FE decides: when the surrogate's sensitivities are right the
iteration converges to a point where FE itself fits the measurement, not to one where the
surrogate thinks it does. Each round costs one FE run (every load case of the measurement)
per specimen that is not yet confirmed.

The FE model enters as a function ``fe_curves(x, ids) -> (k, 4, m)``, so any solver (or a
store of earlier runs) can serve; :func:`campaign_curves` runs a campaign of the FE registry
on Dask and keeps every run in a resumable store.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

logger = logging.getLogger(__name__)

#: ``fe_curves(x, ids)``: RoM in degrees, shape (k, 4, m), of the k parameter rows ``x``
#: (k, d) in physical units, NaN where a run failed; ``ids`` (k,) are the rows' specimens
#: (positions 0..n-1, the same in every call: a store may key its runs by them).
FECurves = Callable[[np.ndarray, int], np.ndarray]


@dataclass
class RefineResult:
    """What :func:`refine_with_fe` returns for n specimens.

    Attributes
    ----------
    specimens : tuple of str, length n
    x_start : ndarray, shape (n, d)
        The calibrated parameters refinement started from (physical units).
    x : ndarray, shape (n, d)
        The best parameters FE has seen for each specimen.
    fe_curves : ndarray, shape (n, 4, m)
        FE RoM in degrees at ``x`` (NaN where the run failed).
    surrogate_curves : ndarray, shape (n, 4, m)
        The uncorrected surrogate at ``x``.
    fe_mae_start : ndarray, shape (n,)
        FE-evaluated MAE of ``x_start`` against the measurement, degrees.
    fe_mae_deg : ndarray, shape (n,)
        FE-evaluated MAE of ``x`` (the FE-confirmed error), over the measured points its run
        reached.
    fe_points_missed : ndarray of int, shape (n,)
        Measured points the run at ``x`` did not reach (it failed before them).
    fe_runs : ndarray of int, shape (n,)
        FE runs spent on each specimen (the first, at ``x_start``, included).
    confirmed : ndarray of bool, shape (n,)
        FE confirms the fit: ``fe_mae_deg <= tol_deg`` and no measured point missed.
    tol_deg : float
    history : pandas.DataFrame
        One row per FE run: ``specimen``, ``run`` (1 = the calibration), ``fe_mae_deg``,
        ``surrogate_mae_deg`` (the uncorrected surrogate at the same point),
        ``fe_points_missed`` (measured points the run did not reach: a run is accepted only if
        it misses no more than the best one and fits better on the points both reached),
        ``accepted``
        (FE found it better than every earlier point) and ``damping`` (of the step that led
        there; NaN for the first run).
    """

    specimens: tuple[str, ...]
    x_start: np.ndarray
    x: np.ndarray
    fe_curves: np.ndarray
    surrogate_curves: np.ndarray
    fe_mae_start: np.ndarray
    fe_mae_deg: np.ndarray
    fe_runs: np.ndarray
    fe_points_missed: np.ndarray
    confirmed: np.ndarray
    tol_deg: float
    history: pd.DataFrame = field(repr=False)

    def table(self, names: Sequence[str] = PARAMETER_NAMES) -> pd.DataFrame:
        """One row per specimen: FE error before and after, runs, and both parameter sets."""
        df = pd.DataFrame(
            {
                "specimen": list(self.specimens),
                "fe_mae_deg_start": self.fe_mae_start,
                "fe_mae_deg": self.fe_mae_deg,
                "fe_runs": self.fe_runs,
                "fe_points_missed": self.fe_points_missed,
                "confirmed": self.confirmed,
            }
        )
        for j, name in enumerate(names):
            df[f"{name}_start"] = self.x_start[:, j]
            df[name] = self.x[:, j]
        return df

    def summary(self) -> dict[str, Any]:
        """The headline figures (JSON-ready)."""
        finite = np.isfinite(self.fe_mae_deg)
        return {
            "n_specimens": len(self.specimens),
            "fe_mae_deg_start": _nanmean(self.fe_mae_start),
            "fe_confirmed_mae_deg": _nanmean(self.fe_mae_deg),
            "fe_confirmed_mae_deg_max": float(np.max(self.fe_mae_deg[finite]))
            if finite.any()
            else float("nan"),
            "n_confirmed": int(self.confirmed.sum()),
            "n_specimens_with_missed_points": int((self.fe_points_missed > 0).sum()),
            "tol_deg": self.tol_deg,
            "fe_runs_total": int(self.fe_runs.sum()),
            "fe_runs_per_specimen_max": int(self.fe_runs.max()) if self.fe_runs.size else 0,
            "fe_runs_per_specimen_mean": float(self.fe_runs.mean()) if self.fe_runs.size else 0,
        }


def _nanmean(v: np.ndarray) -> float:
    return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")


def _mae(pred: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """MAE (n,) over the points both have; inf where FE gave none of the measured points."""
    diff = np.abs(pred - measured)
    count = np.isfinite(diff).sum(axis=(1, 2))
    total = np.nansum(diff, axis=(1, 2))
    return np.where(count > 0, total / np.maximum(count, 1), np.inf)


def _missed(fe: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Measured points a run did not reach (it failed before them), (n,) int."""
    return (np.isfinite(measured) & ~np.isfinite(fe)).sum(axis=(1, 2))


def _better(
    fe_new: np.ndarray, fe_old: np.ndarray, measured: np.ndarray, missed_old: np.ndarray
) -> np.ndarray:
    """FE's judgement (n,): the new run misses no more measured points than the old one and
    fits better on the points both reached (a run cannot win by leaving hard points out)."""
    common = np.isfinite(fe_new) & np.isfinite(fe_old) & np.isfinite(measured)
    count = common.sum(axis=(1, 2))
    new = np.where(common, np.abs(fe_new - measured), 0.0).sum(axis=(1, 2))
    old = np.where(common, np.abs(fe_old - measured), 0.0).sum(axis=(1, 2))
    return (_missed(fe_new, measured) <= missed_old) & (count > 0) & (new < old)


def refine_with_fe(
    model: Any,
    measured: np.ndarray,
    x0: np.ndarray,
    fe_curves: FECurves,
    *,
    specimens: Sequence[str] | None = None,
    weight: np.ndarray | None = None,
    max_fe_runs: int = 5,
    tol_deg: float = 0.05,
    damping: float = 0.01,
) -> RefineResult:
    """Refine calibrated parameters until the FE model itself confirms the fit.

    Parameters
    ----------
    model : CurveModel
        The surrogate on the measurement's moment grid (:class:`~femcal.calibration.
        SurrogateCurveModel`), whose Jacobian steers the steps.
    measured : ndarray, shape (n, 4, m)
        Measured RoM in degrees, NaN where not measured.
    x0 : ndarray, shape (n, d)
        Calibrated parameters (physical units) to start from.
    fe_curves : callable
        ``fe_curves(x, ids) -> (k, 4, m)``: the FE model's RoM at the rows of ``x``
        (:data:`FECurves`, e.g. :func:`campaign_curves`).
    specimens : sequence of str, length n, optional
        Names (default "0", "1", ...).
    weight : ndarray, shape (n, 4, m), optional
        Weights of the corrected Gauss-Newton fit (e.g. the moment policy's); default 1.
    max_fe_runs : int
        FE runs per specimen at most, the first (at ``x0``) included; 1 only validates.
    tol_deg : float
        A specimen is confirmed, and stops, once its FE-evaluated MAE is at most this (the
        noise of the measurement is the natural choice).
    damping : float
        Levenberg-Marquardt damping of the first step, relative to the diagonal of the
        Gauss-Newton matrix; divided by 3 after a step FE accepts, multiplied by 4 after one
        it refuses.

    Returns
    -------
    RefineResult

    Raises
    ------
    InputDataError
        When the shapes of ``measured``, ``x0`` or ``fe_curves``' answer do not agree.
    ConfigError
        When ``max_fe_runs < 1`` or ``tol_deg <= 0``.
    """
    if int(max_fe_runs) < 1:
        raise ConfigError(f"max_fe_runs must be >= 1 (1 only validates); got {max_fe_runs!r}.")
    if not tol_deg > 0:
        raise ConfigError(f"tol_deg must be > 0 degrees; got {tol_deg!r}.")
    y = np.asarray(measured, dtype=float)
    x0 = np.asarray(x0, dtype=float)
    n, d = x0.shape[0], model.dim
    shape = (n, len(LOAD_CASES), len(model.moments))
    if y.shape != shape or x0.shape != (n, d):
        raise InputDataError(
            f"refine_with_fe: measured must have shape {shape} and x0 ({n}, {d}) for the "
            f"model's {d} parameters and moment grid; got {y.shape} and {x0.shape}."
        )
    names = tuple(str(i) for i in range(n)) if specimens is None else tuple(map(str, specimens))
    if len(names) != n:
        raise InputDataError(f"refine_with_fe: {len(names)} specimen names for {n} specimens.")
    w = np.ones_like(y) if weight is None else np.asarray(weight, dtype=float)
    run_fe = _checked(fe_curves, shape[1:])
    st = _Refinement.start(model, y, x0, run_fe, names, damping)
    for round_ in range(1, int(max_fe_runs)):
        active = np.flatnonzero(~((st.mae <= tol_deg) & (st.missed == 0)))
        if active.size == 0:
            break
        v_try = _step(model, st, y, w, active)
        x_try = model.to_physical(v_try.double().numpy())
        fe_try = run_fe(x_try, active)
        s_try = _surrogate(model, v_try)
        mae_try = _mae(fe_try, y[active])
        missed_try = _missed(fe_try, y[active])
        st.runs[active] += 1
        better = _better(fe_try, st.fe[active], y[active], st.missed[active])
        st.learn(active, v_try, fe_try)
        for j, i in enumerate(active):
            st.rows.append(
                {
                    "specimen": names[i],
                    "run": int(st.runs[i]),
                    "fe_mae_deg": mae_try[j],
                    "fe_points_missed": int(missed_try[j]),
                    "surrogate_mae_deg": _mae(s_try[j : j + 1], y[i : i + 1])[0],
                    "accepted": bool(better[j]),
                    "damping": float(st.lam[i]),
                }
            )
        won = st.accept(active, better, v_try, fe_try, s_try, mae_try, missed_try)
        logger.info(
            "FE refinement round %d: %d specimens run, %d improved; FE-confirmed MAE %.4f deg "
            "(%d of %d within %.3g deg).",
            round_,
            active.size,
            won.size,
            _nanmean(np.where(np.isfinite(st.mae), st.mae, np.nan)),
            int(((st.mae <= tol_deg) & (st.missed == 0)).sum()),
            n,
            tol_deg,
        )
    return st.result(model, names, tol_deg)


def _surrogate(model: Any, v: torch.Tensor) -> np.ndarray:
    """The uncorrected surrogate's curves (k, 4, m) at unit coordinates ``v`` (k, d)."""
    with torch.no_grad():
        return model.curves(v).double().numpy()


def _checked(fe_curves: FECurves, curve_shape: tuple[int, int]) -> FECurves:
    """``fe_curves`` that raises when its answer is not of shape (k, *curve_shape)."""

    def run_fe(x: np.ndarray, ids: np.ndarray) -> np.ndarray:
        out = np.asarray(fe_curves(x, ids), dtype=float)
        if out.shape != (x.shape[0], *curve_shape):
            raise InputDataError(
                f"refine_with_fe: fe_curves returned shape {out.shape} for {x.shape[0]} "
                f"rows; expected {(x.shape[0], *curve_shape)}."
            )
        return out

    return run_fe


@dataclass
class _Refinement:
    """The state of :func:`refine_with_fe` for n specimens: the best point FE has seen for
    each, what steers its next step, and the history so far.

    Attributes
    ----------
    v : torch.Tensor, shape (n, d)
        The best points in unit coordinates, inside the box.
    fe, s : ndarray, shape (n, 4, m)
        FE's and the uncorrected surrogate's RoM there, degrees.
    mae : ndarray, shape (n,)
        FE-evaluated MAE there over the measured points the run reached (inf: none).
    missed : ndarray of int, shape (n,)
        Measured points the run there did not reach.
    x_start, mae_start : ndarray
        The calibration refinement started from (n, d, physical units) and its FE MAE (n,).
    runs : ndarray of int, shape (n,)
        FE runs so far.
    lam : ndarray, shape (n,)
        Levenberg-Marquardt damping of the next step.
    need_jac : ndarray of bool, shape (n,)
        The surrogate's Jacobian at ``v`` is still to be computed (the point moved).
    jac, broyden : torch.Tensor, shape (n, 4 * m, d)
        The surrogate's Jacobian at ``v`` and what FE taught about it (Broyden's updates).
    rows : list of dict
        The history, one row per FE run.
    """

    v: torch.Tensor
    fe: np.ndarray
    s: np.ndarray
    mae: np.ndarray
    missed: np.ndarray
    x_start: np.ndarray
    mae_start: np.ndarray
    runs: np.ndarray
    lam: np.ndarray
    need_jac: np.ndarray
    jac: torch.Tensor
    broyden: torch.Tensor
    rows: list[dict[str, Any]]

    @classmethod
    def start(
        cls,
        model: Any,
        y: np.ndarray,
        x0: np.ndarray,
        run_fe: FECurves,
        names: Sequence[str],
        damping: float,
    ) -> _Refinement:
        """Run FE at the calibrated parameters ``x0`` (n, d): the first point of each specimen."""
        n, d = x0.shape[0], model.dim
        v_best = model.from_physical(x0).float()  # (n, d) unit coordinates, inside the box
        x_start = model.to_physical(v_best.double().numpy())
        fe_best = run_fe(x_start, np.arange(n))
        s_best = _surrogate(model, v_best)
        mae_best = _mae(fe_best, y)  # over the measured points the run reached
        missed_best = _missed(fe_best, y)
        mae_start = mae_best.copy()
        rows: list[dict[str, Any]] = [
            {
                "specimen": names[i],
                "run": 1,
                "fe_mae_deg": mae_start[i],
                "fe_points_missed": int(missed_best[i]),
                "surrogate_mae_deg": _mae(s_best[i : i + 1], y[i : i + 1])[0],
                "accepted": True,
                "damping": float("nan"),
            }
            for i in range(n)
        ]
        return cls(
            v=v_best,
            fe=fe_best,
            s=s_best,
            mae=mae_best,
            missed=missed_best,
            x_start=x_start,
            mae_start=mae_start,
            runs=np.ones(n, dtype=int),
            lam=np.full(n, float(damping)),
            need_jac=np.ones(n, dtype=bool),
            jac=torch.zeros((n, y[0].size, d)),
            broyden=torch.zeros((n, y[0].size, d)),  # what FE taught about the Jacobian
            rows=rows,
        )

    def learn(self, active: np.ndarray, v_try: torch.Tensor, fe_try: np.ndarray) -> None:
        """Broyden's rank-one update: the Jacobian along the step as FE measured it."""
        dv = v_try - self.v[active]
        dfe = torch.tensor(np.nan_to_num(fe_try - self.fe[active]), dtype=torch.float32)
        jb = self.jac[active] + self.broyden[active]
        miss = dfe.reshape(active.size, -1) - (jb @ dv[..., None])[..., 0]
        norm2 = (dv * dv).sum(1).clamp_min(1e-12)
        self.broyden[active] += miss[:, :, None] * dv[:, None, :] / norm2[:, None, None]

    def accept(
        self,
        active: np.ndarray,
        better: np.ndarray,
        v_try: torch.Tensor,
        fe_try: np.ndarray,
        s_try: np.ndarray,
        mae_try: np.ndarray,
        missed_try: np.ndarray,
    ) -> np.ndarray:
        """Move the specimens whose try FE found ``better`` there, with a bolder next step;
        the others try a shorter step from the same point. Returns the specimens moved."""
        won, lost = active[better], active[~better]
        self.v[won] = v_try[better]
        self.fe[won], self.s[won], self.mae[won] = fe_try[better], s_try[better], mae_try[better]
        self.missed[won] = missed_try[better]
        self.need_jac[won] = True
        self.lam[won] = np.maximum(self.lam[won] / 3.0, 1e-6)  # FE agreed: bolder next time
        self.lam[lost] *= 4.0  # FE found it worse: a shorter step from the same point
        return won

    def result(self, model: Any, names: tuple[str, ...], tol_deg: float) -> RefineResult:
        """The :class:`RefineResult` of the best points."""
        # Over the points reached; a run that missed measured points confirms nothing there.
        confirmed = (self.mae <= tol_deg) & (self.missed == 0)
        mae_best = np.where(np.isfinite(self.mae), self.mae, np.nan)
        return RefineResult(
            specimens=names,
            x_start=self.x_start,
            x=model.to_physical(self.v.double().numpy()),
            fe_curves=self.fe,
            surrogate_curves=self.s,
            fe_mae_start=np.where(np.isfinite(self.mae_start), self.mae_start, np.nan),
            fe_mae_deg=mae_best,
            fe_runs=self.runs,
            fe_points_missed=self.missed,
            confirmed=confirmed,
            tol_deg=float(tol_deg),
            history=pd.DataFrame(self.rows),
        )


def _step(
    model: Any, st: _Refinement, y: np.ndarray, w: np.ndarray, active: np.ndarray
) -> torch.Tensor:
    """The next point (k, d) to try of the ``active`` specimens, in unit coordinates: a
    projected Levenberg-Marquardt step on the FE residual at the best point, with the
    surrogate's Jacobian corrected by FE (computed anew where the best point moved)."""
    d = model.dim
    fresh = active[st.need_jac[active]]
    if fresh.size:
        _, jf = model.curves_jacobian(st.v[fresh])
        st.jac[fresh] = jf.reshape(fresh.size, -1, d).float()
        st.need_jac[fresh] = False
    # The FE residual at the best point; points FE or the measurement lack weigh 0.
    r = y[active] - st.fe[active]
    wa = np.where(np.isfinite(r), w[active], 0.0).reshape(active.size, -1)
    r = np.nan_to_num(r).reshape(active.size, -1)
    step = _lm_step(
        st.jac[active] + st.broyden[active],
        torch.tensor(r, dtype=torch.float32),
        torch.tensor(wa, dtype=torch.float32),
        st.v[active],
        torch.tensor(st.lam[active], dtype=torch.float32),
    )
    return (st.v[active] + step).clamp(0.0, 1.0)


def _lm_step(
    jac: torch.Tensor, r: torch.Tensor, w: torch.Tensor, v: torch.Tensor, lam: torch.Tensor
) -> torch.Tensor:
    """Projected Levenberg-Marquardt steps, shape (b, d), in unit coordinates.

    ``jac`` (b, p, d), residuals ``r`` and weights ``w`` (b, p), the points ``v`` (b, d) and
    the dampings ``lam`` (b,). A variable at a bound whose step would leave the box is frozen
    (as in :func:`femcal.calibration.pgd.gauss_newton`).
    """
    jtw = jac.transpose(1, 2) * w[:, None, :]
    hess = jtw @ jac
    grad = (jtw @ r[..., None])[..., 0]  # the descent direction J^T W r
    blocked = ((v <= 0) & (grad < 0)) | ((v >= 1) & (grad > 0))
    free = (~blocked).to(v.dtype)
    hf = hess * free[:, :, None] * free[:, None, :]
    diag = torch.diagonal(hf, dim1=1, dim2=2)
    eye = torch.eye(v.shape[1], dtype=v.dtype)
    system = hf + torch.diag_embed(lam[:, None] * (diag + 1e-6) + 1e-9)
    system = system + eye * (1 - free)[:, None, :]
    return torch.linalg.solve(system, (grad * free)[..., None])[..., 0]


def campaign_curves(
    solver: str,
    settings: Mapping[str, Any],
    *,
    store: str | Path,
    moments: Sequence[float],
    scheduler_address: str | None = None,
    n_workers: int = 2,
    progress: bool = False,
) -> FECurves:
    """An :data:`FECurves` that runs the FE registry's ``solver`` as a campaign.

    Every call is one campaign of the rows of ``x`` x the four load cases at ``moments``, on
    Dask, recorded in ``store`` (a rerun replays finished runs from it). The configurations
    are numbered by ``ids``, so a later campaign of the same parameters under the same
    numbers (the validation of the refined specimens) finds them there. A failed run gives
    NaN from the last level it reached.
    """
    from femcal.fe.campaign import run_campaign
    from femcal.fe.options import CampaignOptions

    levels = [float(m) for m in moments]
    options = CampaignOptions(
        scheduler_address=scheduler_address, n_workers=n_workers, progress=progress
    )

    def fe(x: np.ndarray, ids: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        design = pd.DataFrame(x, columns=list(PARAMETER_NAMES))
        design.insert(0, "config_id", np.asarray(ids, dtype=np.int64))
        where = {int(c): j for j, c in enumerate(design["config_id"])}
        campaign = run_campaign(
            solver,
            settings,
            design,
            options,
            store=store,
            load_cases=LOAD_CASES,
            moments=levels,
        )
        out = np.full((x.shape[0], len(LOAD_CASES), len(levels)), np.nan)
        for rec in campaign.records.itertuples(index=False):
            values = [np.nan if v is None else float(v) for v in rec.rom_deg]
            out[where[int(rec.config_id)], LOAD_CASES.index(rec.load_case)] = values
        return out

    return fe
