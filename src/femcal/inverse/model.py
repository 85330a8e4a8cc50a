"""The inverse model as a scikit-learn style estimator: fit, predict, save and load.

:class:`InverseModel` trains an :class:`~femcal.inverse.net.InverseNet` with Lightning (the
toolkit of :mod:`femcal.training`) and keeps it as a fitted attribute; a saved model is a
folder of ``config.json`` and ``weights.pt`` (:mod:`femcal.training.persist`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytorch_lightning as pl
import torch
from sklearn.base import BaseEstimator

from femcal.errors import (
    ConfigError,
    InputDataError,
    SurrogateNotFittedError,
    UntrustedArtifactError,
)
from femcal.inverse.net import InverseLightningModule, InverseNet, last_val_mae
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace
from femcal.surrogates.romnet import check_activation
from femcal.training import persist
from femcal.training.lightning import batch_loader, fit_on_cpu, quiet_lightning

log = logging.getLogger(__name__)

#: The study's hyper-parameters (Atad et al., appendix table), as InverseModel keywords.
STUDY_SETTINGS: dict[str, Any] = {
    "hidden": (128, 256, 256, 256, 128),
    "activation": "relu",
    "batch_size": 48,
    "learning_rate": 0.000654,
    "max_epochs": 776,
    "weight_decay": 6e-6,
    "patience": 50,
    "min_delta": 0.0,
    "dropout": 0.028433,
    "scheduler_patience": 18,
    "scheduler_factor": 0.05,
}
#: The settings of :class:`InverseModel` besides ``space`` (what ``fixed`` and
#: ``search_space`` may set).
INVERSE_SETTINGS: tuple[str, ...] = (
    "hidden",
    "activation",
    "learning_rate",
    "weight_decay",
    "dropout",
    "batch_size",
    "max_epochs",
    "patience",
    "min_delta",
    "scheduler_patience",
    "scheduler_factor",
    "log_input",
    "val_fraction",
    "seed",
)

#: ``format`` of a saved model's ``config.json``.
FORMAT = "femcal-inverse"
FORMAT_VERSION = 1
#: Curves per forward pass when predicting.
EVAL_BATCH = 16_384
#: What to do instead when the inverse network cannot take the curves.
FIX_PGD = "use `--method pgd` (it fits the measured points only)"


class InverseModel(BaseEstimator):
    """Inverse network RoM curves -> parameters (scikit-learn estimator contract).

    ``__init__`` stores the settings; :meth:`fit` sets the attributes ending in ``_``.

    Parameters
    ----------
    space : ParameterSpace, optional
        The parameter box whose min-max unit box the targets live in; needed for physical
        outputs (:meth:`predict_physical`, the MLflow pyfunc) and checked by the calibrator.
    hidden : sequence of int
        Hidden-layer widths (the study's five layers).
    activation : str
        Hidden activation (the study: ReLU).
    learning_rate : float
        Initial AdamW learning rate (the study: 0.000654 at batch size 48).
    weight_decay : float
        AdamW weight decay (the study's 6e-6).
    dropout : float
        Dropout after each hidden activation (the study: 0.028; with 50,000 samples the
        validation loss stays within 6 % of the training loss without it).
    batch_size : int
        Samples per step. The study used 48, which is slow on CPU: one epoch of 45,000
        samples takes 2.2 s at 48 and 1.2 s at 256 on one thread (measured, this network),
        and the study's 776 epochs at 48 would take about half an hour. 256 is the default.
    max_epochs : int
        Upper bound on epochs (the study: 776). With the defaults, 50,000 samples stop early
        after about 140 epochs.
    patience : int
        Early stopping: epochs without a validation MAE better by ``min_delta`` (the study:
        50); the best weights are restored in any case.
    min_delta : float
        Smallest improvement of the validation MAE (unit box) that counts for early stopping.
    scheduler_patience, scheduler_factor : int, float
        ReduceLROnPlateau on the validation MAE (the study: 18 and 0.05; 5 and 0.2 reach the
        same plateau in fewer epochs). :data:`STUDY_SETTINGS` holds the study's recipe.
    log_input : bool
        Standardise log RoM (RoM must be > 0) rather than RoM.
    val_fraction : float
        Fraction of the samples held out for validation when ``X_val`` is not given (0 trains
        on everything, without early stopping).
    seed : int
        Seeds the split, the initial weights, dropout and the batch order.

    Attributes
    ----------
    net_ : InverseNet
        The fitted network, eval mode, weights frozen.
    moments_ : ndarray, shape (m,)
        The moment grid in Nm of the training curves (the only grid :meth:`predict` accepts).
    input_loc_, input_scale_ : ndarray, shape (4 * m,)
        Input standardisation of (log) RoM, load case major (also buffers of ``net_``).
    best_val_mae_ : float
        MAE in the unit box on the validation samples (NaN without validation).
    history_ : list of dict
        One dict per epoch: epoch, train_loss, val_mae, lr.
    n_features_in_ : int
        ``4 * m``.
    """

    def __init__(
        self,
        space: ParameterSpace | None = None,
        *,
        hidden: Sequence[int] = (128, 256, 256, 256, 128),
        activation: str = "relu",
        learning_rate: float = 1e-3,
        weight_decay: float = 6e-6,
        dropout: float = 0.0,
        batch_size: int = 256,
        max_epochs: int = 150,
        patience: int = 20,
        min_delta: float = 1e-5,
        scheduler_patience: int = 5,
        scheduler_factor: float = 0.2,
        log_input: bool = True,
        val_fraction: float = 0.1,
        seed: int = 0,
    ) -> None:
        self.space = space
        self.hidden = hidden
        self.activation = activation
        self.learning_rate = learning_rate
        self.weight_decay = weight_decay
        self.dropout = dropout
        self.batch_size = batch_size
        self.max_epochs = max_epochs
        self.patience = patience
        self.min_delta = min_delta
        self.scheduler_patience = scheduler_patience
        self.scheduler_factor = scheduler_factor
        self.log_input = log_input
        self.val_fraction = val_fraction
        self.seed = seed

    # ------------------------------------------------------------------ settings
    #: The constructor's settings besides ``space`` (see :data:`INVERSE_SETTINGS`).
    _SETTINGS: tuple[str, ...] = INVERSE_SETTINGS

    def _init_args(self) -> dict[str, Any]:
        args = {k: getattr(self, k) for k in self._SETTINGS}
        args["hidden"] = [int(h) for h in args["hidden"]]
        return args

    def _check_settings(self) -> None:
        check_activation(self.activation)
        problems = []
        hidden = list(self.hidden)
        if not hidden or any(int(h) < 1 for h in hidden):
            problems.append(f"hidden={hidden} (need one or more widths >= 1)")
        for name, low in (("batch_size", 1), ("max_epochs", 1), ("patience", 0)):
            if int(getattr(self, name)) < low:
                problems.append(f"{name}={getattr(self, name)} (need >= {low})")
        if not float(self.min_delta) >= 0:
            problems.append(f"min_delta={self.min_delta} (need >= 0)")
        if int(self.scheduler_patience) < 0:
            problems.append(f"scheduler_patience={self.scheduler_patience} (need >= 0)")
        if not float(self.learning_rate) > 0:
            problems.append(f"learning_rate={self.learning_rate} (need > 0)")
        if not float(self.weight_decay) >= 0:
            problems.append(f"weight_decay={self.weight_decay} (need >= 0)")
        if not 0.0 <= float(self.dropout) < 1.0:
            problems.append(f"dropout={self.dropout} (need 0 <= dropout < 1)")
        if not 0.0 < float(self.scheduler_factor) < 1.0:
            problems.append(f"scheduler_factor={self.scheduler_factor} (need 0 < factor < 1)")
        if not 0.0 <= float(self.val_fraction) < 1.0:
            problems.append(f"val_fraction={self.val_fraction} (need 0 <= fraction < 1)")
        if problems:
            raise ConfigError(f"Invalid InverseModel settings: {'; '.join(problems)}.")

    def check_fitted(self) -> None:
        """Raise :class:`~femcal.errors.SurrogateNotFittedError` unless fitted."""
        if not hasattr(self, "net_"):
            raise SurrogateNotFittedError(
                "This InverseModel is not fitted yet: call fit(X_rom, U, moments=...), "
                "InverseModel.load(path) or load_inverse(uri) first."
            )

    # ---------------------------------------------------------------------- data
    def _check_rom(self, rom: Any, n_moments: int, what: str) -> np.ndarray:
        rom = np.asarray(rom, dtype=float)
        if rom.ndim != 3 or rom.shape[1:] != (len(LOAD_CASES), n_moments):
            raise InputDataError(
                f"{what} must have shape (n, {len(LOAD_CASES)}, {n_moments}) (load cases "
                f"{', '.join(LOAD_CASES)} x moments); got {rom.shape}."
            )
        if not np.all(np.isfinite(rom)):
            raise InputDataError(
                f"{what}: every RoM value must be given (finite); the inverse network needs the "
                f"full grid, {FIX_PGD}."
            )
        if self.log_input and np.any(rom <= 0):
            raise InputDataError(
                f"{what}: RoM must be > 0 degrees (the network reads log RoM); got a minimum of "
                f"{rom.min():g}."
            )
        return rom

    def _check_unit(self, unit: Any, n: int, what: str) -> np.ndarray:
        unit = np.asarray(unit, dtype=float)
        if unit.ndim != 2 or unit.shape[0] != n:
            raise InputDataError(f"{what} must have shape ({n}, d); got {unit.shape}.")
        if self.space is not None and unit.shape[1] != self.space.dim:
            raise InputDataError(
                f"{what} has {unit.shape[1]} columns; the space has {self.space.dim} parameters."
            )
        if not np.all(np.isfinite(unit)) or unit.min() < 0.0 or unit.max() > 1.0:
            raise InputDataError(
                f"{what}: targets must be finite values in the unit box [0, 1] "
                "((x - lower) / (upper - lower))."
            )
        return unit

    # ----------------------------------------------------------------------- fit
    def fit(
        self,
        X_rom: np.ndarray,
        U: np.ndarray,
        *,
        moments: Sequence[float] | np.ndarray,
        X_val: np.ndarray | None = None,
        U_val: np.ndarray | None = None,
        logger: Any = None,
        callbacks: Sequence[pl.Callback] = (),
        progress: bool = False,
    ) -> InverseModel:
        """Train the network.

        Parameters
        ----------
        X_rom : array_like, shape (N, 4, m)
            RoM curves in degrees, load cases in the order of LOAD_CASES.
        U : array_like, shape (N, d)
            Parameters in the min-max unit box [0, 1].
        moments : array_like, shape (m,)
            The moments in Nm of the last axis of ``X_rom``.
        X_val, U_val : array_like, shapes (M, 4, m) and (M, d), optional
            Validation data; when omitted, ``val_fraction`` of the samples.
        logger : Lightning logger, optional
            E.g. an MLFlowLogger for per-epoch metrics; None disables logging.
        callbacks : sequence of Lightning callbacks
            Extra callbacks (e.g. Optuna pruning on ``val_mae``).
        progress : bool
            Show Lightning's progress bar.

        Returns
        -------
        InverseModel
            ``self``.
        """
        self._check_settings()
        m = np.asarray(moments, dtype=float).reshape(-1)
        if m.size == 0 or not np.all(np.isfinite(m)) or np.any(m <= 0):
            raise InputDataError(f"moments must be finite and > 0 Nm; got {m.tolist()}.")
        rom, unit, vrom, vunit = self._training_data(X_rom, U, m.size, X_val, U_val)
        has_val = vrom.shape[0] > 0

        t = np.log(rom) if self.log_input else rom
        t = t.reshape(t.shape[0], -1)
        loc = t.mean(axis=0)
        scale = t.std(axis=0)
        scale = np.where(scale > 1e-12, scale, 1.0)
        arch = {
            "hidden": [int(h) for h in self.hidden],
            "activation": self.activation,
            "dropout": float(self.dropout),
            "log_input": bool(self.log_input),
        }
        f32 = torch.float32
        train_t = (torch.as_tensor(rom, dtype=f32), torch.as_tensor(unit, dtype=f32))
        val_t = (torch.as_tensor(vrom, dtype=f32), torch.as_tensor(vunit, dtype=f32))
        n_batches = max(1, math.ceil(rom.shape[0] / int(self.batch_size)))
        seed = int(self.seed)
        with quiet_lightning(), torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            net = InverseNet(m.size, unit.shape[1], **arch, input_loc=loc, input_scale=scale)
            module = InverseLightningModule(
                net,
                learning_rate=self.learning_rate,
                weight_decay=self.weight_decay,
                scheduler_patience=self.scheduler_patience,
                scheduler_factor=self.scheduler_factor,
                monitor="val_mae" if has_val else "train_loss",
            )
            train_loader = batch_loader(
                train_t, int(self.batch_size), torch.Generator().manual_seed(seed)
            )
            fit_on_cpu(
                module,
                train_loader,
                batch_loader(val_t, EVAL_BATCH, None) if has_val else None,
                monitor="val_mae",
                patience=int(self.patience),
                min_delta=float(self.min_delta),
                read=last_val_mae,
                max_epochs=int(self.max_epochs),
                n_batches=n_batches,
                logger=logger,
                callbacks=callbacks,
                progress=progress,
            )

        self.net_ = persist.freeze(net)
        self.moments_ = m
        self.input_loc_ = loc
        self.input_scale_ = scale
        self.history_ = list(module.history)
        self.n_features_in_ = len(LOAD_CASES) * m.size
        if has_val:
            self.best_val_mae_ = float(np.mean(np.abs(self._forward(vrom) - vunit)))
        else:
            self.best_val_mae_ = math.nan
        log.info(
            "inverse model: %d epochs, best validation MAE %.4f (unit box)",
            len(self.history_),
            self.best_val_mae_,
        )
        return self

    def _training_data(
        self,
        X_rom: np.ndarray,
        U: np.ndarray,
        n_moments: int,
        X_val: np.ndarray | None,
        U_val: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The checked training and validation data of :meth:`fit`: curves (N, 4, m) in
        degrees and unit-box parameters (N, d) each.

        Without ``X_val``/``U_val``, ``val_fraction`` of the samples (a permutation drawn with
        ``seed``) are held out for validation.
        """
        rom = self._check_rom(X_rom, n_moments, "X_rom")
        unit = self._check_unit(U, rom.shape[0], "U")
        if (X_val is None) != (U_val is None):
            raise InputDataError("Give both X_val and U_val, or neither.")
        if X_val is not None:
            vrom = self._check_rom(X_val, n_moments, "X_val")
            vunit = self._check_unit(U_val, vrom.shape[0], "U_val")
            if vunit.shape[1] != unit.shape[1]:
                raise InputDataError(
                    f"U_val has {vunit.shape[1]} columns and U {unit.shape[1]}; give the same "
                    "parameters."
                )
        else:
            n = rom.shape[0]
            n_val = int(round(float(self.val_fraction) * n))
            n_val = min(max(n_val, 1), n - 1) if self.val_fraction > 0 and n > 1 else 0
            perm = np.random.default_rng(self.seed).permutation(n)
            val, train = perm[:n_val], perm[n_val:]
            vrom, vunit = rom[val], unit[val]
            rom, unit = rom[train], unit[train]
        return rom, unit, vrom, vunit

    # ------------------------------------------------------------------- predict
    def _forward(self, rom: np.ndarray) -> np.ndarray:
        out = []
        with torch.no_grad():
            for s in range(0, rom.shape[0], EVAL_BATCH):
                # A C-contiguous copy: the result must not depend on the memory layout.
                chunk = torch.tensor(
                    np.ascontiguousarray(rom[s : s + EVAL_BATCH]), dtype=torch.float32
                )
                out.append(self.net_(chunk).double().numpy())
        if not out:
            return np.zeros((0, self.net_.n_params))
        return np.concatenate(out)

    def predict(self, rom: np.ndarray) -> np.ndarray:
        """Parameters in the study's unit box.

        Parameters
        ----------
        rom : array_like, shape (n, 4, m)
            RoM in degrees on the training grid ``moments_``, every point given.

        Returns
        -------
        ndarray of float64, shape (n, d)
            Values in (0, 1).
        """
        self.check_fitted()
        return self._forward(self._check_rom(rom, self.moments_.size, "rom"))

    def predict_physical(self, rom: np.ndarray) -> np.ndarray:
        """Parameters in physical units, shape (n, 4, m) -> (n, d), inside the box."""
        self.check_fitted()
        if self.space is None:
            raise ConfigError(
                "This InverseModel has no parameter space; construct it with "
                "InverseModel(space, ...) to get physical units."
            )
        return self.space.clip(self.space.from_unit(self.predict(rom)))

    def rom_columns(self) -> list[str]:
        """Column names of the wide RoM input: ``'<load case>@<moment>'``, load case major."""
        self.check_fitted()
        return [f"{lc}@{m:g}" for lc in LOAD_CASES for m in self.moments_]

    def predict_frame(self, frame: pd.DataFrame) -> pd.DataFrame:
        """Parameters in physical units from a wide DataFrame (the MLflow pyfunc's interface).

        Parameters
        ----------
        frame : DataFrame, n rows
            Columns :meth:`rom_columns` (e.g. ``Flexion@1`` ... ``AxialRotation@5``), degrees.

        Returns
        -------
        DataFrame, n rows
            One column per parameter of ``space``, physical units.
        """
        cols = self.rom_columns()
        missing = [c for c in cols if c not in frame.columns]
        if missing:
            raise InputDataError(
                f"The inverse model needs the RoM columns {cols}; missing {missing}."
            )
        rom = frame[cols].to_numpy(dtype=float).reshape(len(frame), len(LOAD_CASES), -1)
        x = self.predict_physical(rom)
        assert self.space is not None
        return pd.DataFrame(x, columns=list(self.space.names), index=frame.index)

    # ----------------------------------------------------------------------- I/O
    def save(self, path: str | Path) -> None:
        """Write ``config.json`` (settings, space, grid, standardisation, history) and
        ``weights.pt`` into the directory ``path`` (created or overwritten)."""
        self.check_fitted()
        config = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "init": self._init_args(),
            "space": None if self.space is None else self.space.to_dict(),
            "architecture": self.net_.architecture(),
            "fitted": {
                "moments": self.moments_.tolist(),
                "input_loc": self.input_loc_.tolist(),
                "input_scale": self.input_scale_.tolist(),
                "best_val_mae": persist.finite_or_none(self.best_val_mae_),
                "history": persist.history_to_json(self.history_),
            },
        }
        persist.save_model_files(path, config, self.net_)

    @classmethod
    def load(cls, path: str | Path) -> InverseModel:
        """Read a model written by :meth:`save` from the directory ``path``."""
        config = persist.read_config(path, fmt=FORMAT, what="InverseModel")
        space = None if config.get("space") is None else ParameterSpace.from_dict(config["space"])
        init = dict(config["init"])
        init["hidden"] = tuple(init["hidden"])
        model = cls(space, **init)
        fitted = config["fitted"]
        net = InverseNet(
            **config["architecture"],
            input_loc=fitted["input_loc"],
            input_scale=fitted["input_scale"],
        )
        net.load_state_dict(persist.load_weights(path))
        model.net_ = persist.freeze(net)
        model.moments_ = np.asarray(fitted["moments"], dtype=float)
        model.input_loc_ = np.asarray(fitted["input_loc"], dtype=float)
        model.input_scale_ = np.asarray(fitted["input_scale"], dtype=float)
        bv = fitted.get("best_val_mae")
        model.best_val_mae_ = float(persist.none_to_nan(bv))
        model.history_ = persist.history_from_json(fitted.get("history", []))
        model.n_features_in_ = len(LOAD_CASES) * model.moments_.size
        return model


def trusted_inverse_class(spec: Any, *, source: str) -> type:
    """:class:`InverseModel` when ``spec`` names it (``"module:QualName"``), else an error.

    What a logged inverse model's ``femcal_loader.json`` may name (see
    :func:`femcal.training.pyfunc.trusted_loader`); nothing is imported on the file's say-so.

    Raises
    ------
    UntrustedArtifactError
        ``spec`` names another class.
    """
    expected = f"{InverseModel.__module__}:{InverseModel.__qualname__}"
    if spec != expected:
        raise UntrustedArtifactError(
            f"{source} names the class {spec!r}, which is not femcal's inverse model "
            f"({expected}); femcal refuses to import it. Do not load this model."
        )
    return InverseModel
