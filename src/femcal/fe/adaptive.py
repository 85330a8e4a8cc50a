"""Adaptive sampling: FE runs where the calibrations land and where the ensemble disagrees.

A surrogate trained on a space-filling design is equally good everywhere on average, and
calibration only needs it good where the specimens' solutions lie. Each round of
:func:`adapt_surrogate`:

1. calibrates the target specimens through the current surrogate, starting from the
   configurations it was trained on whose curves lie nearest each specimen's, the earlier
   rounds' FE runs among them (as the ``calibrate`` stage starts from its training set): the
   parameters are not identifiable from RoM, and from uniform random starts each round's
   solution lands anywhere along the specimen's valley of equal fits, where the earlier rounds
   taught the surrogate nothing;
2. runs FE at their solutions, and measures the surrogate's error there *before* learning
   from those runs (the error near the calibrated solutions, the figure that should fall
   round after round);
3. runs FE where the ensemble's members disagree most, among a Latin hypercube of candidates
   (:func:`ensemble_spread`: the members' standard deviation, a free estimate of the
   surrogate's error);
4. fine-tunes the surrogate on the training data and every new run
   (:attr:`NeuralSurrogate.warm_start <femcal.surrogates.nn.NeuralSurrogate>`), for a fixed
   number of epochs without a validation split (keeping the best epoch on a split of the old
   configurations would keep the weights from before the new runs; docs: *Benchmarks >
   Measurements behind the defaults*);
5. scores it on held-out FE configurations, which no round trains on.

Whether the result replaces the champion is the caller's decision, on that held-out score
(the ``adapt`` stage registers it as a challenger and moves ``champion`` only if it wins).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch

from femcal.errors import ConfigError, InputDataError
from femcal.fe.options import AdaptOptions
from femcal.fe.refine import FECurves
from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)


def _grid_rows(x: np.ndarray, moments: Sequence[float]) -> tuple[torch.Tensor, ...]:
    """Load-case index, moment and parameters of every (row, load case, moment), C order."""
    n, m = x.shape[0], len(moments)
    cfg, lc, mom = np.meshgrid(
        np.arange(n), np.arange(len(LOAD_CASES)), np.arange(m), indexing="ij"
    )
    return (
        torch.tensor(lc.reshape(-1), dtype=torch.long),
        torch.tensor(np.asarray(moments, dtype=float)[mom.reshape(-1)], dtype=torch.float32),
        torch.tensor(x[cfg.reshape(-1)], dtype=torch.float32),
    )


def ensemble_spread(surrogate: Any, x: np.ndarray, moments: Sequence[float]) -> np.ndarray:
    """Disagreement of the ensemble's members at parameter rows, in degrees.

    Parameters
    ----------
    surrogate : object
        A fitted neural surrogate with ``torch_module()`` (a :class:`RomNet` of >= 2 members).
    x : ndarray, shape (N, d)
        Parameters in physical units.
    moments : sequence of float, length m
        The moment grid in Nm.

    Returns
    -------
    ndarray, shape (N,)
        The members' standard deviation, averaged over the 4 x m points of each row's curves.
    """
    net = surrogate.torch_module()
    if net.n_members < 2:
        raise ConfigError(
            f"The ensemble spread needs >= 2 members; this surrogate has {net.n_members}. "
            "Train it with final_members >= 2."
        )
    x = np.asarray(x, dtype=float)
    lc, mom, par = _grid_rows(x, moments)
    with torch.no_grad():
        members = net.members_degrees(lc, mom, par).double().numpy()  # (k, N * 4 * m)
    return members.std(axis=0).reshape(x.shape[0], -1).mean(axis=1)


def curves_to_rows(
    x: np.ndarray,
    curves: np.ndarray,
    moments: Sequence[float],
    names: Sequence[str],
    *,
    first_id: int = 0,
) -> tuple[pd.DataFrame, np.ndarray]:
    """Training rows (``load_case``, ``moment_nm``, parameters, ``config_id``) and RoM.

    Points an FE run did not reach (NaN) are left out; the levels it did reach are data.
    """
    lc, mom, _ = _grid_rows(np.asarray(x, dtype=float), moments)
    n = x.shape[0]
    per = len(LOAD_CASES) * len(moments)
    X = pd.DataFrame(np.repeat(np.asarray(x, dtype=float), per, axis=0), columns=list(names))
    X.insert(0, "moment_nm", mom.double().numpy())
    X.insert(0, "load_case", np.asarray(LOAD_CASES, dtype=object)[lc.numpy()])
    X["config_id"] = np.repeat(np.arange(first_id, first_id + n), per)
    y = np.asarray(curves, dtype=float).reshape(-1)
    keep = np.isfinite(y) & (y > 0)
    return X[keep].reset_index(drop=True), y[keep]


@dataclass
class AdaptResult:
    """What :func:`adapt_surrogate` returns.

    Attributes
    ----------
    surrogate : object
        The fine-tuned surrogate (a copy; the one passed in is untouched).
    rounds : pandas.DataFrame
        One row per round: ``round``, ``n_runs`` (FE configurations run), ``n_failed_points``,
        ``error_at_solutions_deg`` (the surrogate before the round against FE at the
        calibrated solutions), ``fe_calibration_mae_deg`` (FE at the solutions against the
        targets), ``spread_explored_deg`` (the ensemble spread where it explored),
        ``heldout_mae_deg`` (after the round's fine-tuning).
    heldout_mae_start : float
        The surrogate's held-out MAE before the first round, degrees.
    runs : pandas.DataFrame
        The new FE configurations: ``round``, ``reason`` ("calibration" or "disagreement"),
        ``config_id`` and the parameters.
    """

    surrogate: Any
    rounds: pd.DataFrame
    heldout_mae_start: float
    runs: pd.DataFrame = field(repr=False)

    def summary(self) -> dict[str, Any]:
        last = self.rounds.iloc[-1] if len(self.rounds) else None
        return {
            "n_rounds": int(len(self.rounds)),
            "n_new_configurations": int(len(self.runs)),
            "heldout_mae_deg_start": self.heldout_mae_start,
            "heldout_mae_deg": float(last["heldout_mae_deg"]) if last is not None else None,
            "error_at_solutions_deg": [float(v) for v in self.rounds["error_at_solutions_deg"]],
            "fe_calibration_mae_deg": [float(v) for v in self.rounds["fe_calibration_mae_deg"]],
        }


#: The moment bands of the held-out error: the study's range and beyond it.
MOMENT_BANDS: tuple[tuple[float, float], ...] = ((0.0, 5.0), (5.0, 10.0))


def band_mae(
    surrogate: Any,
    X: pd.DataFrame,
    y: np.ndarray,
    bands: Sequence[tuple[float, float]] = MOMENT_BANDS,
) -> dict[str, float]:
    """MAE in degrees of ``surrogate`` on rows ``X`` per moment band ``(lo, hi]``, in Nm.

    Keys are ``"lo-hi"`` (e.g. ``"0-5"``, ``"5-10"``); a band without rows is NaN.
    """
    pred = surrogate.predict(X)
    m = X["moment_nm"].to_numpy(dtype=float)
    out = {}
    for lo, hi in bands:
        sel = (m > lo) & (m <= hi)
        out[f"{lo:g}-{hi:g}"] = _mae(pred[sel], np.asarray(y)[sel]) if sel.any() else float("nan")
    return out


def _configurations(X: pd.DataFrame, names: Sequence[str]) -> np.ndarray:
    """The distinct configurations (k, d) of training rows: one per ``config_id`` if the rows
    have one, else per distinct parameter row."""
    if "config_id" in X.columns:
        return X.groupby("config_id", sort=True)[list(names)].first().to_numpy(dtype=float)
    return np.unique(X[list(names)].to_numpy(dtype=float), axis=0)


def _mae(a: np.ndarray, b: np.ndarray) -> float:
    d = np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))
    return float(np.nanmean(d)) if np.isfinite(d).any() else float("nan")


def adapt_surrogate(
    surrogate: Any,
    targets: np.ndarray,
    moments: Sequence[float],
    fe_curves: FECurves,
    train: tuple[pd.DataFrame, np.ndarray],
    heldout: tuple[pd.DataFrame, np.ndarray],
    options: AdaptOptions | None = None,
    **overrides: Any,
) -> AdaptResult:
    """Rounds of FE runs at calibrated solutions and at disagreement, with fine-tuning.

    Parameters
    ----------
    surrogate : NeuralSurrogate
        The fitted surrogate (an ensemble of >= 2 members); it is copied, not changed.
    targets : ndarray, shape (n, 4, m)
        Curves of the specimens to calibrate, degrees (NaN where not measured).
    moments : sequence of float, length m
        Their moment grid, Nm (also the grid of every new FE run).
    fe_curves : callable
        ``fe_curves(x, ids) -> (k, 4, m)`` (:func:`femcal.fe.refine.campaign_curves`); ids are
        numbered from ``options.first_id`` on, one per new configuration.
    train : (DataFrame, ndarray)
        The surrogate's training rows and RoM; the new runs are added to them.
    heldout : (DataFrame, ndarray)
        FE rows no round trains on, for the held-out MAE.
    options : AdaptOptions, optional
        Rounds, exploration, fine-tuning, calibration, seed and numbering (default:
        :class:`~femcal.fe.options.AdaptOptions`'s).
    **overrides
        Fields of :class:`~femcal.fe.options.AdaptOptions` replacing those of ``options``.

    Returns
    -------
    AdaptResult

    Raises
    ------
    ConfigError
        When the rounds, ``n_explore`` or ``n_candidates`` are out of range.
    InputDataError
        When ``targets`` do not have the shape (n, 4, m) of ``moments``.
    """
    o = dataclasses.replace(options or AdaptOptions(), **overrides)
    targets = np.asarray(targets, dtype=float)
    if targets.ndim != 3 or targets.shape[1:] != (len(LOAD_CASES), len(moments)):
        raise InputDataError(
            f"adapt_surrogate: targets must have shape (n, {len(LOAD_CASES)}, {len(moments)}) "
            f"for the moments {list(moments)}; got {targets.shape}."
        )
    rng = o.seed if isinstance(o.seed, np.random.Generator) else np.random.default_rng(o.seed)
    model = copy.deepcopy(surrogate)
    names = list(model.space.names)
    tune = _finetuning(model, o.finetune)
    # The recipe the surrogate was trained with, restored after the rounds: the challenger's
    # get_params() say how to train it from scratch, not how it was fine-tuned.
    recipe = {k: v for k, v in model.get_params().items() if k in tune}
    X_train, y_train = train
    X_ho, y_ho = heldout
    heldout_start = _mae(model.predict(X_ho), y_ho)
    logger.info("adaptive sampling: held-out MAE %.4f deg before round 1", heldout_start)
    rows: list[dict[str, Any]] = []
    runs: list[pd.DataFrame] = []
    next_id = int(o.first_id)
    for r in range(1, int(o.rounds) + 1):
        x_sol, cal_mae = _calibrate_targets(model, targets, moments, X_train, o, rng)
        explore, spread = _explore(model, moments, o, rng)
        x_new = np.vstack([x_sol, explore])
        ids = np.arange(next_id, next_id + len(x_new))
        fe = fe_curves(x_new, ids)
        row = _round_row(r, model, moments, x_new, len(x_sol), fe, targets)
        row["surrogate_calibration_mae_deg"] = cal_mae
        row["spread_explored_deg"] = spread
        X_new, y_new = curves_to_rows(x_new, fe, moments, names, first_id=next_id)
        X_train = pd.concat([X_train, X_new], ignore_index=True)
        y_train = np.concatenate([y_train, y_new])
        model.set_params(**tune)
        model.fit(X_train, y_train)
        row["heldout_mae_deg"] = _mae(model.predict(X_ho), y_ho)
        rows.append(row)
        runs.append(_runs_frame(r, x_new, ids, names, len(x_sol)))
        next_id += len(x_new)
        logger.info(
            "adaptive sampling round %d: %d FE runs; surrogate error at the calibrated solutions "
            "%.4f deg (before this round); held-out MAE %.4f deg after fine-tuning",
            r,
            len(x_new),
            row["error_at_solutions_deg"],
            row["heldout_mae_deg"],
        )
    model.set_params(**recipe)
    if rows and hasattr(model, "record_validation_error"):
        # the fine-tuning had no validation rows: the held-out split's error is the model's
        moments_ho, pred_ho = X_ho["moment_nm"].to_numpy(dtype=float), model.predict(X_ho)
        model.record_validation_error(moments_ho, pred_ho - y_ho, pred_ho)
    return AdaptResult(
        surrogate=model,
        rounds=pd.DataFrame(rows),
        heldout_mae_start=heldout_start,
        runs=pd.concat(runs, ignore_index=True),
    )


def _finetuning(model: Any, finetune: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``set_params`` of each round's fine-tuning: a warm start, without a validation
    split, for 100 epochs at a third of the surrogate's learning rate, unless ``finetune``
    says otherwise."""
    return {
        "max_epochs": 100,
        "patience": 100,
        "learning_rate": float(model.learning_rate) / 3,
        "val_fraction": 0.0,
        **dict(finetune or {}),
        "warm_start": True,
    }


def _calibrate_targets(
    model: Any,
    targets: np.ndarray,
    moments: Sequence[float],
    X_train: pd.DataFrame,
    o: AdaptOptions,
    rng: np.random.Generator,
) -> tuple[np.ndarray, float]:
    """Calibrate the targets through ``model``, starting from its training configurations.

    Returns the solutions (n, d) in physical units and the mean calibration MAE through the
    surrogate, degrees.
    """
    from femcal.calibration import SurrogateCurveModel, calibrate

    bank = _configurations(X_train, list(model.space.names))
    cal = calibrate(
        SurrogateCurveModel(model, moments),
        targets,
        seed=rng,
        options={"ranges": False, "start_bank": bank, **dict(o.calibrate_options or {})},
    )
    x_sol = cal.parameters_frame()[list(model.space.names)].to_numpy(dtype=float)
    return x_sol, float(np.mean(cal.mae_deg))


def _explore(
    model: Any, moments: Sequence[float], o: AdaptOptions, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """The ``n_explore`` most disputed of ``n_candidates`` Latin-hypercube candidates (k, d)
    and their mean ensemble spread in degrees (NaN when none are explored)."""
    explore = np.empty((0, len(model.space.names)))
    spread = float("nan")
    if o.n_explore:
        candidates = model.space.sample_lhs(int(o.n_candidates), rng)
        s = ensemble_spread(model, candidates, moments)
        top = np.argsort(-s, kind="stable")[: int(o.n_explore)]
        explore, spread = candidates[top], float(s[top].mean())
    return explore, spread


def _round_row(
    r: int,
    model: Any,
    moments: Sequence[float],
    x_new: np.ndarray,
    n_sol: int,
    fe: np.ndarray,
    targets: np.ndarray,
) -> dict[str, Any]:
    """The figures of round ``r`` before its fine-tuning: FE at the new configurations
    ``x_new`` (the first ``n_sol`` the calibrated solutions) against the surrogate and the
    targets."""
    from femcal.calibration import SurrogateCurveModel

    before = SurrogateCurveModel(model, moments).predict(x_new)
    return {
        "round": r,
        "n_runs": len(x_new),
        "n_failed_points": int((~np.isfinite(fe)).sum()),
        "error_at_solutions_deg": _mae(before[:n_sol], fe[:n_sol]),
        "fe_calibration_mae_deg": _mae(fe[:n_sol], targets),
    }


def _runs_frame(
    r: int, x_new: np.ndarray, ids: np.ndarray, names: Sequence[str], n_sol: int
) -> pd.DataFrame:
    """Round ``r``'s new configurations: ``round``, ``reason``, ``config_id``, parameters."""
    frame = pd.DataFrame(x_new, columns=list(names))
    frame.insert(0, "config_id", ids)
    frame.insert(0, "reason", ["calibration"] * n_sol + ["disagreement"] * (len(x_new) - n_sol))
    frame.insert(0, "round", r)
    return frame
