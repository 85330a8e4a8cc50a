"""``inverse``: the study's inverse-model baseline, RoM curves -> parameters in one pass.

Atad et al. ("Inverse model", after Liu et al. 2021 and Babaei et al. 2022): a feed-forward
ReLU network maps the 20 RoM values of a specimen (4 load cases x 5 moments, load case major
in the order of :data:`~femcal.schema.LOAD_CASES`) to the 13 parameters in the study's min-max
unit box, constrained to (0, 1) by a Sigmoid and trained with an MAE loss and
ReduceLROnPlateau on 50,000 configurations sampled in the box whose curves come from the NN
surrogate. The study reports it as fast (0.01 s for the Test set) but ill-posed: mean MAE
0.52 deg and mean R^2 0.54 on the synthetic Test specimens, because many configurations give
nearly the same curves.

Measured with this module (defaults; 50,000 Latin-hypercube samples from
``models/surrogate-large``; one CPU thread): training stops after 125 epochs in 176 s (2 s for
the samples), validation MAE 0.126 in the unit box. On the study's 64 Test specimens
(``calibrate(..., method="inverse")``, curves evaluated through the surrogate) the mean MAE is
0.080 deg and the mean R^2 0.990 in 1 ms for the batch (box centre: 1.48 deg, R^2 -1.48).
The problem is still ill-posed in the parameters: against the true Test configurations the
unit-box MAE is 0.03-0.08 for C10Annulus, Kappa, FiberAngle, K1Annulus and FiberAngleCirc but
0.2-0.3 for C01Nucleus, K2Circ, K1Rad, K2Rad and FiberAngleRad (box centre: 0.25) - the
curves fit, the parameters the curves do not determine are guesses.

Pieces:

* :class:`InverseNet` - the torch module; the input standardisation (of log RoM by default)
  lives in its buffers, so a saved network is the whole model;
* :class:`InverseLightningModule` - trains it with Lightning (MAE, AdamW, ReduceLROnPlateau,
  best validation weights restored);
* :class:`InverseModel` - scikit-learn style estimator (``fit``/``predict``/``save``/``load``);
* :func:`make_inverse_dataset` - the training set from the surrogate;
* :func:`train_inverse` - Optuna search in an RDB storage, every trial a nested MLflow run,
  the final model logged as an MLflow pyfunc (models from code) and registered;
* :func:`load_inverse` - the registered model back as an :class:`InverseModel`;
* the ``inverse`` calibrator.

The network only understands the full grid it was trained on; specimens with missing points or
another moment grid must use a fitting calibrator (``--method pgd``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytorch_lightning as pl
import torch
from sklearn.base import BaseEstimator
from torch import nn

from femcal.calibration.base import CalibrationProblem, Solution, register_calibrator
from femcal.calibration.model import CurveModel
from femcal.errors import ConfigError, InputDataError, ModelRegistryError, SurrogateNotFittedError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace
from femcal.surrogates.nn import ACTIVATIONS, _quiet_lightning

logger = logging.getLogger(__name__)

#: Registered model name and URI used by default.
DEFAULT_INVERSE_NAME = "ivd-inverse"
DEFAULT_INVERSE_URI = f"models:/{DEFAULT_INVERSE_NAME}@champion"
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
#: Sampling schemes of :func:`make_inverse_dataset`.
SAMPLINGS: tuple[str, ...] = ("lhs", "uniform")

_FORMAT = "femcal-inverse"
_FORMAT_VERSION = 1
_EVAL_BATCH = 16_384
_FIX_PGD = "use `--method pgd` (it fits the measured points only)"

#: MLflow "model from code" entry point, written beside the saved model when it is logged.
_PYFUNC_CODE = '''"""MLflow model-from-code entry point of a femcal inverse model."""

import mlflow
import pandas as pd

from femcal.calibration.inverse import InverseModel


class InversePyfunc(mlflow.pyfunc.PythonModel):
    """DataFrame with the RoM columns ('Flexion@1', ...) -> parameters in physical units."""

    def load_context(self, context):
        self.model = InverseModel.load(context.artifacts["inverse"])

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        return self.model.predict_frame(model_input)


mlflow.models.set_model(InversePyfunc())
'''


# ----------------------------------------------------------------------------- the network
class InverseNet(nn.Module):
    """RoM curves (n, 4, m) in degrees -> parameters (n, d) in the study's unit box (0, 1).

    Parameters
    ----------
    n_moments : int
        Moments per load case m; the input has ``4 * m`` values, load case major.
    n_params : int
        Number of parameters d.
    hidden : sequence of int
        Hidden-layer widths.
    activation : {"relu", "gelu", "silu", "tanh", "softplus"}
        Hidden activation.
    dropout : float
        Dropout after each hidden activation (0 disables it).
    log_input : bool
        Standardise ``log RoM`` (RoM must then be > 0) instead of RoM.
    input_loc, input_scale : array_like, shape (4 * m,), optional
        Standardisation of the (log) inputs; default 0 and 1.
    """

    def __init__(
        self,
        n_moments: int,
        n_params: int,
        *,
        hidden: Sequence[int] = (128, 256, 256, 256, 128),
        activation: str = "relu",
        dropout: float = 0.0,
        log_input: bool = True,
        input_loc: Sequence[float] | np.ndarray | None = None,
        input_scale: Sequence[float] | np.ndarray | None = None,
    ) -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ConfigError(
                f"Unknown activation '{activation}'; choose one of {', '.join(ACTIVATIONS)}."
            )
        self.n_load_cases = len(LOAD_CASES)
        self.n_moments = int(n_moments)
        self.n_params = int(n_params)
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = activation
        self.dropout = float(dropout)
        self.log_input = bool(log_input)
        n_in = self.n_load_cases * self.n_moments
        loc = np.zeros(n_in) if input_loc is None else np.asarray(input_loc, dtype=float)
        scale = np.ones(n_in) if input_scale is None else np.asarray(input_scale, dtype=float)
        if loc.shape != (n_in,) or scale.shape != (n_in,) or np.any(~(scale > 0)):
            raise ConfigError(
                f"input_loc and input_scale must have shape ({n_in},) with scale > 0; got "
                f"{loc.shape} and {scale.shape}."
            )
        self.register_buffer("input_loc", torch.tensor(loc, dtype=torch.float32))
        self.register_buffer("input_scale", torch.tensor(scale, dtype=torch.float32))
        layers: list[nn.Module] = []
        width = n_in
        for h in self.hidden:
            layers += [nn.Linear(width, h), ACTIVATIONS[activation]()]
            if self.dropout > 0:
                layers.append(nn.Dropout(self.dropout))
            width = h
        layers += [nn.Linear(width, self.n_params), nn.Sigmoid()]
        self.mlp = nn.Sequential(*layers)

    def architecture(self) -> dict[str, Any]:
        """Constructor arguments that rebuild this module (standardisation excluded)."""
        return {
            "n_moments": self.n_moments,
            "n_params": self.n_params,
            "hidden": list(self.hidden),
            "activation": self.activation,
            "dropout": self.dropout,
            "log_input": self.log_input,
        }

    def features(self, rom_deg: torch.Tensor) -> torch.Tensor:
        """Standardised inputs, shape (n, 4, m) or (n, 4 m) -> (n, 4 m)."""
        x = rom_deg.reshape(rom_deg.shape[0], -1)
        if self.log_input:
            x = torch.log(x)
        return (x - self.input_loc) / self.input_scale

    def forward(self, rom_deg: torch.Tensor) -> torch.Tensor:
        """Parameters in the unit box, shape (n, 4, m) -> (n, d), values in (0, 1)."""
        return self.mlp(self.features(rom_deg))


# ------------------------------------------------------------------------ Lightning wrapper
class InverseLightningModule(pl.LightningModule):
    """Trains an :class:`InverseNet` on batches ``(rom (b, 4, m), unit (b, d))``.

    Loss: MAE in the unit box. AdamW with ReduceLROnPlateau on ``val_mae`` (``train_loss``
    without validation). Logs per epoch ``train_loss``, ``val_mae`` and ``lr``; keeps the
    weights of the best validation epoch and restores them when fitting ends.

    Parameters
    ----------
    net : InverseNet
        The network (standardisation already set).
    learning_rate, weight_decay : float
        AdamW settings.
    scheduler_patience : int
        Epochs without improvement before the learning rate is multiplied by
        ``scheduler_factor``.
    scheduler_factor : float
        In (0, 1).
    monitor : {"val_mae", "train_loss"}
        The metric the scheduler watches (``train_loss`` when there is no validation).
    """

    def __init__(
        self,
        net: InverseNet,
        *,
        learning_rate: float = 1e-3,
        weight_decay: float = 0.0,
        scheduler_patience: int = 18,
        scheduler_factor: float = 0.05,
        monitor: str = "val_mae",
    ) -> None:
        super().__init__()
        if monitor not in ("val_mae", "train_loss"):
            raise ConfigError(f"monitor must be 'val_mae' or 'train_loss'; got {monitor!r}.")
        self.net = net
        self.monitor = monitor
        self.learning_rate = float(learning_rate)
        self.weight_decay = float(weight_decay)
        self.scheduler_patience = int(scheduler_patience)
        self.scheduler_factor = float(scheduler_factor)
        #: One dict per epoch: epoch, train_loss, val_mae (NaN without validation), lr.
        self.history: list[dict[str, float]] = []
        self.best_val = math.inf
        self.best_state: dict[str, torch.Tensor] | None = None
        self._sums = {"train": torch.zeros(()), "val": torch.zeros(())}
        self._counts = {"train": 0, "val": 0}

    def _accumulate(self, key: str, loss: torch.Tensor, n: int) -> None:
        self._sums[key] = self._sums[key] + loss.detach() * n
        self._counts[key] += n

    def _mean(self, key: str) -> float:
        n = self._counts[key]
        return float(self._sums[key]) / n if n else math.nan

    def training_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> torch.Tensor:
        rom, unit = batch
        loss = (self.net(rom) - unit).abs().mean()
        self._accumulate("train", loss, unit.numel())
        return loss

    def validation_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> None:
        rom, unit = batch
        self._accumulate("val", (self.net(rom) - unit).abs().mean(), unit.numel())

    def on_train_epoch_start(self) -> None:
        self._sums["train"], self._counts["train"] = torch.zeros(()), 0

    def on_validation_epoch_start(self) -> None:
        self._sums["val"], self._counts["val"] = torch.zeros(()), 0

    def on_validation_epoch_end(self) -> None:
        if self.trainer.sanity_checking:
            return
        val = self._mean("val")
        self.log("val_mae", val, on_epoch=True)
        if val < self.best_val:
            self.best_val = val
            self.best_state = {k: v.detach().clone() for k, v in self.net.state_dict().items()}

    def on_train_epoch_end(self) -> None:
        train = self._mean("train")
        lr = float(self.trainer.optimizers[0].param_groups[0]["lr"])
        self.log("train_loss", train, on_step=False, on_epoch=True)
        self.log("lr", lr, on_step=False, on_epoch=True)
        self.history.append(
            {
                "epoch": int(self.current_epoch),
                "train_loss": train,
                "val_mae": self._mean("val"),
                "lr": lr,
            }
        )
        self._counts["val"] = 0

    def on_fit_end(self) -> None:
        if self.best_state is not None:
            self.net.load_state_dict(self.best_state)

    def configure_optimizers(self) -> Any:
        opt = torch.optim.AdamW(
            self.net.parameters(), lr=self.learning_rate, weight_decay=self.weight_decay
        )
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, mode="min", factor=self.scheduler_factor, patience=self.scheduler_patience
        )
        return {
            "optimizer": opt,
            "lr_scheduler": {"scheduler": sched, "monitor": self.monitor, "interval": "epoch"},
        }


class _Batches(torch.utils.data.Dataset):
    """Tensors indexed along dim 0 by a list of indices (whole batches at once)."""

    def __init__(self, *tensors: torch.Tensor) -> None:
        self.tensors = tensors

    def __len__(self) -> int:
        return int(self.tensors[0].shape[0])

    def __getitem__(self, idx: Any) -> tuple[torch.Tensor, ...]:
        idx = torch.as_tensor(idx, dtype=torch.long)
        return tuple(t[idx] for t in self.tensors)


def _loader(
    tensors: Sequence[torch.Tensor], batch_size: int, generator: torch.Generator | None
) -> torch.utils.data.DataLoader:
    ds = _Batches(*tensors)
    base = (
        torch.utils.data.RandomSampler(ds, generator=generator)
        if generator is not None
        else torch.utils.data.SequentialSampler(ds)
    )
    sampler = torch.utils.data.BatchSampler(base, batch_size=batch_size, drop_last=False)
    return torch.utils.data.DataLoader(ds, sampler=sampler, batch_size=None)


# ------------------------------------------------------------------------------ estimator
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
    #: The constructor's settings besides ``space`` (what ``fixed``/``search_space`` may set).
    _SETTINGS: tuple[str, ...] = (
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

    def _init_args(self) -> dict[str, Any]:
        args = {k: getattr(self, k) for k in self._SETTINGS}
        args["hidden"] = [int(h) for h in args["hidden"]]
        return args

    def _check_settings(self) -> None:
        if self.activation not in ACTIVATIONS:
            raise ConfigError(
                f"Unknown activation '{self.activation}'; choose one of {', '.join(ACTIVATIONS)}."
            )
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

    def _check_fitted(self) -> None:
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
                f"full grid, {_FIX_PGD}."
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
        rom = self._check_rom(X_rom, m.size, "X_rom")
        unit = self._check_unit(U, rom.shape[0], "U")
        if (X_val is None) != (U_val is None):
            raise InputDataError("Give both X_val and U_val, or neither.")
        if X_val is not None:
            vrom = self._check_rom(X_val, m.size, "X_val")
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
        with _quiet_lightning(), torch.random.fork_rng(devices=[]):
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
            train_loader = _loader(
                train_t, int(self.batch_size), torch.Generator().manual_seed(seed)
            )
            cbs: list[pl.Callback] = [*callbacks]
            val_loader = None
            if has_val:
                val_loader = _loader(val_t, _EVAL_BATCH, None)
                cbs.append(
                    pl.callbacks.EarlyStopping(
                        "val_mae",
                        patience=int(self.patience),
                        min_delta=float(self.min_delta),
                        mode="min",
                    )
                )
            trainer = pl.Trainer(
                accelerator="cpu",
                devices=1,
                max_epochs=int(self.max_epochs),
                logger=logger if logger is not None else False,
                callbacks=cbs,
                enable_checkpointing=False,
                enable_progress_bar=progress,
                enable_model_summary=False,
                num_sanity_val_steps=0,
                deterministic=True,
                log_every_n_steps=min(50, n_batches),
            )
            trainer.fit(module, train_dataloaders=train_loader, val_dataloaders=val_loader)

        net.eval()
        for p in net.parameters():
            p.requires_grad_(False)
        self.net_ = net
        self.moments_ = m
        self.input_loc_ = loc
        self.input_scale_ = scale
        self.history_ = list(module.history)
        self.n_features_in_ = len(LOAD_CASES) * m.size
        if has_val:
            self.best_val_mae_ = float(np.mean(np.abs(self._forward(vrom) - vunit)))
        else:
            self.best_val_mae_ = math.nan
        logging.getLogger(__name__).info(
            "inverse model: %d epochs, best validation MAE %.4f (unit box)",
            len(self.history_),
            self.best_val_mae_,
        )
        return self

    # ------------------------------------------------------------------- predict
    def _forward(self, rom: np.ndarray) -> np.ndarray:
        out = []
        with torch.no_grad():
            for s in range(0, rom.shape[0], _EVAL_BATCH):
                # A C-contiguous copy: the result must not depend on the memory layout.
                chunk = torch.tensor(
                    np.ascontiguousarray(rom[s : s + _EVAL_BATCH]), dtype=torch.float32
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
        self._check_fitted()
        return self._forward(self._check_rom(rom, self.moments_.size, "rom"))

    def predict_physical(self, rom: np.ndarray) -> np.ndarray:
        """Parameters in physical units, shape (n, 4, m) -> (n, d), inside the box."""
        self._check_fitted()
        if self.space is None:
            raise ConfigError(
                "This InverseModel has no parameter space; construct it with "
                "InverseModel(space, ...) to get physical units."
            )
        return self.space.clip(self.space.from_unit(self.predict(rom)))

    def rom_columns(self) -> list[str]:
        """Column names of the wide RoM input: ``'<load case>@<moment>'``, load case major."""
        self._check_fitted()
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
        self._check_fitted()
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)

        def clean(v: Any) -> Any:
            return None if isinstance(v, float) and not math.isfinite(v) else v

        config = {
            "format": _FORMAT,
            "version": _FORMAT_VERSION,
            "init": self._init_args(),
            "space": None if self.space is None else self.space.to_dict(),
            "architecture": self.net_.architecture(),
            "fitted": {
                "moments": self.moments_.tolist(),
                "input_loc": self.input_loc_.tolist(),
                "input_scale": self.input_scale_.tolist(),
                "best_val_mae": clean(self.best_val_mae_),
                "history": [{k: clean(v) for k, v in row.items()} for row in self.history_],
            },
        }
        (path / "config.json").write_text(json.dumps(config, indent=2) + "\n")
        torch.save(self.net_.state_dict(), path / "weights.pt")

    @classmethod
    def load(cls, path: str | Path) -> InverseModel:
        """Read a model written by :meth:`save` from the directory ``path``."""
        path = Path(path)
        try:
            config = json.loads((path / "config.json").read_text())
        except FileNotFoundError:
            raise InputDataError(
                f"{path / 'config.json'} does not exist; give a directory written by "
                "InverseModel.save."
            ) from None
        if config.get("format") != _FORMAT:
            raise InputDataError(f"{path / 'config.json'} is not a saved InverseModel.")
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
        try:
            state = torch.load(path / "weights.pt", weights_only=True, map_location="cpu")
        except FileNotFoundError:
            raise InputDataError(f"{path / 'weights.pt'} does not exist.") from None
        net.load_state_dict(state)
        net.eval()
        for p in net.parameters():
            p.requires_grad_(False)
        model.net_ = net
        model.moments_ = np.asarray(fitted["moments"], dtype=float)
        model.input_loc_ = np.asarray(fitted["input_loc"], dtype=float)
        model.input_scale_ = np.asarray(fitted["input_scale"], dtype=float)
        bv = fitted.get("best_val_mae")
        model.best_val_mae_ = math.nan if bv is None else float(bv)
        model.history_ = [
            {k: (math.nan if v is None else v) for k, v in row.items()}
            for row in fitted.get("history", [])
        ]
        model.n_features_in_ = len(LOAD_CASES) * model.moments_.size
        return model


# --------------------------------------------------------------------------- training data
def make_inverse_dataset(
    curve_model: CurveModel,
    n_samples: int = 50_000,
    rng: np.random.Generator | int | None = None,
    *,
    sampling: str = "lhs",
    batch_size: int = _EVAL_BATCH,
) -> tuple[np.ndarray, np.ndarray]:
    """Configurations sampled in the study's unit box and their curves from the surrogate.

    Parameters
    ----------
    curve_model : CurveModel
        The surrogate on the moment grid of the curves.
    n_samples : int
        Number of configurations N.
    rng : numpy.random.Generator or int
        Source of the samples (an int seeds a new generator; default seed 0).
    sampling : {"lhs", "uniform"}
        Latin hypercube or independent uniform draws.
    batch_size : int
        Configurations per surrogate call.

    Returns
    -------
    rom : ndarray of float64, shape (N, 4, m)
        RoM in degrees.
    unit : ndarray of float64, shape (N, d)
        The configurations in the min-max unit box.
    """
    if sampling not in SAMPLINGS:
        raise ConfigError(f"Unknown sampling '{sampling}'; choose one of {', '.join(SAMPLINGS)}.")
    n = int(n_samples)
    if n < 1 or int(batch_size) < 1:
        raise ConfigError(f"n_samples and batch_size must be >= 1; got {n_samples}, {batch_size}.")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng or 0)
    d = curve_model.dim
    if sampling == "lhs":
        strata = np.stack([gen.permutation(n) for _ in range(d)], axis=1)
        unit = (strata + gen.random((n, d))) / n
    else:
        unit = gen.random((n, d))
    out = []
    with torch.no_grad():
        for s in range(0, n, int(batch_size)):
            u = torch.as_tensor(unit[s : s + int(batch_size)], dtype=torch.float32)
            out.append(curve_model.curves(curve_model.from_linear_unit(u)).double().numpy())
    rom = np.concatenate(out)
    if not np.all(np.isfinite(rom)) or np.any(rom <= 0):
        raise InputDataError(
            "The surrogate returned non-finite or non-positive RoM for some sampled "
            "configurations; check the surrogate (log_target=True keeps RoM > 0)."
        )
    return rom, unit


def rom_mae_deg(model: InverseModel, curve_model: CurveModel, rom: np.ndarray) -> float:
    """MAE in degrees between curves and the surrogate's curves at the model's predictions.

    Parameters
    ----------
    model : InverseModel
        Fitted inverse model.
    curve_model : CurveModel
        The surrogate on the model's moment grid.
    rom : ndarray, shape (n, 4, m)
        Curves (measured or from the surrogate).
    """
    unit = model.predict(rom)
    with torch.no_grad():
        parts = [
            curve_model.curves(
                curve_model.from_linear_unit(
                    torch.as_tensor(unit[s : s + _EVAL_BATCH], dtype=torch.float32)
                )
            )
            for s in range(0, unit.shape[0], _EVAL_BATCH)
        ]
    pred = torch.cat(parts).double().numpy()
    return float(np.mean(np.abs(pred - rom)))


# ------------------------------------------------------------------------------ training
@dataclass
class InverseTrainResult:
    """What :func:`train_inverse` produced.

    Attributes
    ----------
    model : InverseModel
        The final fitted model.
    best_params : dict
        Its settings (fixed ones merged with the best trial's).
    val_mae : float
        Validation MAE in the unit box.
    run_id : str
        The MLflow run of this training.
    model_uri : str or None
        The logged MLflow pyfunc model.
    version : str or None
        The registered model version (None when not registered).
    promoted : bool
        Whether the champion alias moved to ``version``.
    seconds : float
        Wall time of the whole call.
    val_rom_mae_deg : float
        Validation MAE in degrees of the curves re-evaluated through the surrogate at the
        predicted parameters (the Optuna objective and the promotion metric).
    n_trials : int
        Complete trials in the study after this call.
    extra : dict
        Anything else (study name, sample count).
    """

    model: InverseModel
    best_params: dict
    val_mae: float
    run_id: str
    model_uri: str | None = None
    version: str | None = None
    promoted: bool = False
    seconds: float = 0.0
    val_rom_mae_deg: float = math.nan
    n_trials: int = 0
    extra: dict = field(default_factory=dict)


def inverse_kwargs(params: Mapping[str, Any]) -> dict[str, Any]:
    """Flat hyper-parameters (``width``/``depth`` allowed) -> :class:`InverseModel` keywords."""
    kw = dict(params)
    if "width" in kw or "depth" in kw:
        width = int(kw.pop("width", 256))
        depth = int(kw.pop("depth", 5))
        kw["hidden"] = tuple([width] * depth)
    if "hidden" in kw:
        kw["hidden"] = tuple(int(h) for h in kw["hidden"])
    allowed = set(InverseModel._SETTINGS) - {"seed"}
    unknown = sorted(set(kw) - allowed)
    if unknown:
        raise ConfigError(
            f"Unknown inverse-model settings {unknown}; use width/depth or {sorted(allowed)} "
            "(the seed comes from train_inverse's seed)."
        )
    return kw


def _surrogate_fingerprint(curve_model: CurveModel) -> str:
    h = hashlib.sha256()
    for key, value in sorted(curve_model.net.state_dict().items()):
        h.update(key.encode())
        h.update(value.detach().cpu().contiguous().numpy().tobytes())
    h.update(curve_model.moments.numpy().tobytes())
    return h.hexdigest()[:12]


def log_inverse(model: InverseModel, *, name: str = "model") -> Any:
    """Log a fitted :class:`InverseModel` (with a space) as an MLflow pyfunc model.

    The pyfunc takes a DataFrame with the columns :meth:`InverseModel.rom_columns` and
    returns the parameters in physical units. The model is logged "from code": MLflow stores
    the saved model directory and a small entry-point script, not a pickle, with femcal's code
    and dependencies as for a surrogate (:func:`femcal.tracking.log_surrogate`).

    Returns
    -------
    mlflow.models.model.ModelInfo
    """
    import mlflow
    from mlflow.models import infer_signature

    from femcal.tracking import femcal_code, model_requirements

    model._check_fitted()
    if model.space is None:
        raise ConfigError("Only an InverseModel with a parameter space can be logged.")
    centre = np.exp(model.input_loc_) if model.log_input else model.input_loc_
    example = pd.DataFrame(centre[None, :], columns=model.rom_columns())
    signature = infer_signature(example, model.predict_frame(example))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "inverse"
        model.save(root)
        code = Path(tmp) / "inverse_pyfunc_model.py"
        code.write_text(_PYFUNC_CODE)
        info = mlflow.pyfunc.log_model(
            name=name,
            python_model=str(code),
            artifacts={"inverse": str(root)},
            signature=signature,
            input_example=example,
            pip_requirements=model_requirements(),
            code_paths=[str(femcal_code(Path(tmp)))],
        )
    return info


def train_inverse(
    curve_model: CurveModel,
    *,
    n_samples: int = 50_000,
    search_space: Mapping[str, Mapping[str, Any]] | None = None,
    fixed: Mapping[str, Any] | None = None,
    n_trials: int = 0,
    storage: str | None = None,
    study_name: str = "inverse",
    seed: int = 0,
    val_fraction: float = 0.1,
    sampling: str = "lhs",
    register_as: str | None = None,
    run_name: str = "train-inverse",
    progress: bool = False,
    heartbeat_seconds: int = 30,
) -> InverseTrainResult:
    """Sample a training set from the surrogate, search settings with Optuna, fit, log, register.

    Parameters
    ----------
    curve_model : CurveModel
        The surrogate on the moment grid the inverse model will accept (the study: 1..5 Nm).
    n_samples : int
        Configurations sampled in the unit box (the study: 50,000).
    search_space : mapping, optional
        Optuna search space (see :func:`femcal.train.suggest`) over :class:`InverseModel`
        settings (``width``/``depth`` allowed).
    fixed : mapping, optional
        Fixed settings, overridden by the search; enqueued as trial 0 where inside the space.
    n_trials : int
        Complete trials the study should hold; a resumed study only runs the missing ones.
        0 fits the final model on ``fixed`` alone.
    storage : str, optional
        Optuna RDB storage URL (``sqlite:///...``); needed when ``n_trials > 0``.
    study_name : str
        Base name of the study; a hash of the problem (surrogate, grid, samples, search
        space, fixed settings) is appended.
    seed : int
        Seeds the samples, the validation split, the sampler and every fit.
    val_fraction : float
        Fraction of the samples held out for validation and early stopping.
    sampling : {"lhs", "uniform"}
        How the configurations are drawn.
    register_as : str, optional
        Registered model name (e.g. "ivd-inverse"); the champion alias moves only on a better
        validation MAE in degrees.
    run_name : str
        Name of the parent MLflow run (in the active experiment).
    progress : bool
        Progress bars of Optuna and Lightning.
    heartbeat_seconds : int
        Trials send a heartbeat this often; a trial silent for three periods is failed and
        retried.

    Returns
    -------
    InverseTrainResult
    """
    import mlflow
    import optuna

    from femcal.tracking import register_and_promote
    from femcal.train import (
        _fixed_as_trial,
        _mlflow_logger,
        _n_complete,
        _OptunaPruning,
        study_name_for,
        suggest,
    )

    t0 = time.perf_counter()
    search_space = dict(search_space or {})
    fixed = dict(fixed or {})
    if n_trials < 0:
        raise ConfigError(f"n_trials must be >= 0; got {n_trials}.")
    if n_trials > 0 and not storage:
        raise ConfigError("An Optuna search (n_trials > 0) needs an RDB storage URL (sqlite:///…).")
    if not 0.0 < val_fraction < 1.0:
        raise ConfigError(f"val_fraction must lie in (0, 1); got {val_fraction}.")
    if int(n_samples) < 10:
        raise ConfigError(f"n_samples must be >= 10; got {n_samples}.")
    inverse_kwargs(fixed)  # fail early on unknown settings

    rng = np.random.default_rng(seed)
    rom, unit = make_inverse_dataset(curve_model, n_samples, rng, sampling=sampling)
    perm = rng.permutation(rom.shape[0])
    n_val = max(1, int(round(val_fraction * rom.shape[0])))
    X_va, U_va = rom[perm[:n_val]], unit[perm[:n_val]]
    X_tr, U_tr = rom[perm[n_val:]], unit[perm[n_val:]]
    moments = curve_model.moments.double().numpy()
    space = curve_model.space
    data_id = f"{_surrogate_fingerprint(curve_model)}-{n_samples}-{seed}-{sampling}-{val_fraction}"
    full_name = study_name_for(study_name, search_space=search_space, fixed=fixed, data_id=data_id)

    def fit(params: Mapping[str, Any], fit_seed: int, **kw: Any) -> InverseModel:
        model = InverseModel(space, **inverse_kwargs(params), seed=fit_seed)
        return model.fit(X_tr, U_tr, moments=moments, X_val=X_va, U_val=U_va, **kw)

    with mlflow.start_run(run_name=run_name) as parent:
        mlflow.log_params(
            {
                "n_trials": n_trials,
                "n_samples": n_samples,
                "sampling": sampling,
                "seed": seed,
                "val_fraction": val_fraction,
                "n_train": X_tr.shape[0],
                "n_val": X_va.shape[0],
                "moments": json.dumps(moments.tolist()),
                "optuna_study": full_name,
            }
        )
        mlflow.set_tag("femcal.stage", "train-inverse")
        mlflow.log_metric("dataset_seconds", time.perf_counter() - t0)

        best_params: dict[str, Any] = dict(fixed)
        n_complete = 0
        if n_trials > 0:
            import warnings

            with warnings.catch_warnings():  # heartbeats are 'experimental' in Optuna
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                rdb = optuna.storages.RDBStorage(
                    storage,
                    heartbeat_interval=heartbeat_seconds,
                    grace_period=3 * heartbeat_seconds,
                    heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(
                        max_retry=2
                    ),
                )
            study = optuna.create_study(
                study_name=full_name,
                storage=rdb,
                load_if_exists=True,
                direction="minimize",
                sampler=optuna.samplers.TPESampler(seed=seed),
                pruner=optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=20),
            )

            def objective(trial: optuna.Trial) -> float:
                hp = {**fixed, **suggest(trial, search_space)}
                with mlflow.start_run(run_name=f"trial-{trial.number}", nested=True) as run:
                    mlflow.log_params({**hp, "trial": trial.number, "optuna_study": full_name})
                    pruning = _OptunaPruning(trial, monitor="val_mae")
                    model = fit(
                        hp,
                        seed + trial.number,
                        logger=_mlflow_logger(run.info.run_id),
                        callbacks=[pruning],
                    )
                    value = rom_mae_deg(model, curve_model, X_va)
                    mlflow.log_metrics(
                        {"best_val_mae": model.best_val_mae_, "val_rom_mae_deg": value}
                    )
                    if pruning.pruned:
                        mlflow.set_tag("optuna.state", "PRUNED")
                        raise optuna.TrialPruned()
                    mlflow.set_tag("optuna.state", "COMPLETE")
                return value

            if not study.trials:
                start = _fixed_as_trial(fixed, search_space)
                if start:
                    study.enqueue_trial(start)  # the known recipe is trial 0
            done = _n_complete(study)
            if done < n_trials:
                logger.info("Optuna study %s: %d of %d trials done", full_name, done, n_trials)
                study.optimize(
                    objective,
                    callbacks=[
                        optuna.study.MaxTrialsCallback(
                            n_trials, states=(optuna.trial.TrialState.COMPLETE,)
                        )
                    ],
                    n_trials=n_trials - done + 4,  # headroom for pruned/failed trials
                    show_progress_bar=progress,
                )
            n_complete = _n_complete(study)
            best_params.update(study.best_trial.params)
            mlflow.log_metric("best_trial_val_rom_mae_deg", float(study.best_value))

        mlflow.log_params({f"final.{k}": v for k, v in best_params.items()})
        model = fit(best_params, seed, progress=progress)
        for row in model.history_:
            for key in ("train_loss", "val_mae", "lr"):
                value = row.get(key)
                if value is not None and np.isfinite(value):
                    mlflow.log_metric(f"final.{key}", float(value), step=int(row["epoch"]))
        val_mae = float(model.best_val_mae_)
        val_rom = rom_mae_deg(model, curve_model, X_va)
        mlflow.log_metrics({"val_mae": val_mae, "val_rom_mae_deg": val_rom})

        with tempfile.TemporaryDirectory() as tmp:
            model.save(Path(tmp) / "inverse_model")
            mlflow.log_artifacts(str(Path(tmp) / "inverse_model"), artifact_path="inverse_model")
        info = log_inverse(model)
        version, promoted = None, False
        if register_as:
            version, promoted = register_and_promote(
                info.model_uri,
                name=register_as,
                val_metric=val_rom,
                tags={
                    "optuna_study": full_name,
                    "train_run_id": parent.info.run_id,
                    "val_mae_unit": repr(val_mae),
                },
            )
            mlflow.set_tags({"registered_version": version, "promoted": str(promoted)})
        seconds = time.perf_counter() - t0
        mlflow.log_metric("train_seconds", seconds)
        return InverseTrainResult(
            model=model,
            best_params=best_params,
            val_mae=val_mae,
            run_id=parent.info.run_id,
            model_uri=info.model_uri,
            version=version,
            promoted=promoted,
            seconds=seconds,
            val_rom_mae_deg=val_rom,
            n_trials=n_complete,
            extra={"optuna_study": full_name, "n_samples": int(n_samples)},
        )


def load_inverse(uri: str = DEFAULT_INVERSE_URI) -> InverseModel:
    """Load an inverse model as an :class:`InverseModel` (weights and JSON only).

    Parameters
    ----------
    uri : str
        The folder the train-inverse stage writes (``models/inverse``), or an MLflow model
        URI: ``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/...``.

    Raises
    ------
    ModelRegistryError
        The folder does not exist, the URI cannot be resolved in the current store, or neither
        holds an inverse model.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    from femcal.tracking import is_local_model, open_model

    if is_local_model(uri):
        model = _inverse_in(open_model(uri).path)
        if model is None:
            raise ModelRegistryError(
                f"'{uri}' is not a femcal inverse model (no saved InverseModel in it); rebuild "
                "it with `dvc repro train-inverse` or fetch it with `dvc pull`."
            )
        return model
    with tempfile.TemporaryDirectory() as tmp:
        try:
            local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=tmp))
        except MlflowException as exc:
            raise ModelRegistryError(
                f"Could not load the inverse model '{uri}' from the MLflow store "
                f"{mlflow.get_tracking_uri()}: {exc.message}. Run `dvc repro train-inverse` to "
                "train and register one, or set MLFLOW_TRACKING_URI to the team's server."
            ) from None
        model = _inverse_in(local)
        if model is not None:
            return model
    raise ModelRegistryError(
        f"'{uri}' is not a femcal inverse model (no saved InverseModel in its artifacts); "
        "run `dvc repro train-inverse` to register one."
    )


def _inverse_in(folder: Path) -> InverseModel | None:
    """The saved InverseModel in a model folder (``artifacts/inverse`` or any ``config.json`` of
    its format outside ``code/``), or None."""
    for config in sorted(folder.rglob("config.json")):
        if config.relative_to(folder).parts[0] == "code":
            continue
        try:
            fmt = json.loads(config.read_text()).get("format")
        except (ValueError, OSError, AttributeError):
            continue
        if fmt == _FORMAT:
            return InverseModel.load(config.parent)
    return None


# ----------------------------------------------------------------------------- calibrator
def _check_problem(problem: CalibrationProblem, model: InverseModel) -> None:
    """The problem must be on the model's grid, in its box, with every point measured."""
    grid = problem.model.moments.double().numpy()
    trained = np.asarray(model.moments_, dtype=float)
    if grid.shape != trained.shape or not np.allclose(grid, trained, rtol=1e-6, atol=1e-9):
        raise InputDataError(
            f"The inverse model was trained on the moment grid {trained.tolist()} Nm; these "
            f"targets are on {grid.tolist()} Nm. It only accepts its full training grid: "
            f"{_FIX_PGD}."
        )
    if model.space is not None and model.space != problem.model.space:
        raise ConfigError(
            "The inverse model was trained on another parameter box "
            f"({list(model.space.names)}, lower {model.space.lower.tolist()}, upper "
            f"{model.space.upper.tolist()}) than the calibration's; retrain it "
            "(`dvc repro train-inverse`) or use `--method pgd`."
        )
    if model.net_.n_params != problem.dim:
        raise ConfigError(
            f"The inverse model predicts {model.net_.n_params} parameters; the calibration has "
            f"{problem.dim}."
        )
    mask = problem.mask.numpy()
    if not mask.all():
        lacking = ~mask.all(axis=(1, 2))
        points = [
            f"{LOAD_CASES[k]} at {grid[j]:g} Nm"
            for k in range(mask.shape[1])
            for j in range(mask.shape[2])
            if not mask[:, k, j].all()
        ]
        shown = ", ".join(points[:8]) + (f" and {len(points) - 8} more" if len(points) > 8 else "")
        raise InputDataError(
            f"Missing RoM values: {int(lacking.sum())} of {mask.shape[0]} specimens (positions "
            f"{np.flatnonzero(lacking)[:10].tolist()} of this batch) lack points ({shown}). The "
            f"inverse model needs all {mask.shape[1]} x {mask.shape[2]} points; {_FIX_PGD}."
        )


@register_calibrator("inverse")
def inverse(
    problem: CalibrationProblem,
    *,
    rng: np.random.Generator,
    model: InverseModel | None = None,
    model_uri: str = DEFAULT_INVERSE_URI,
) -> Solution:
    """The study's inverse-model baseline: parameters from the targets in one forward pass.

    Parameters
    ----------
    problem : CalibrationProblem
        Targets of n specimens on the inverse model's full moment grid (no missing points).
        Point weights are ignored: the network reads the curves as they are.
    rng : numpy.random.Generator
        Unused (the prediction is deterministic); part of the calibrator interface.
    model : InverseModel, optional
        A fitted inverse model; loaded from ``model_uri`` when omitted (pass it to keep the
        loading out of the timing and to load it once for several chunks).
    model_uri : str
        MLflow model URI of the registered inverse model.

    Returns
    -------
    Solution
        ``x`` (n, d) in physical units inside the box, ``nit = 1``, ``success`` all True.
    """
    if model is None:
        logger.info("Loading the inverse model %s", model_uri)
        model = load_inverse(model_uri)
    model._check_fitted()
    _check_problem(problem, model)
    unit = model.predict(problem.measured)
    space = problem.model.space
    x = space.clip(problem.model.linear_unit_to_physical(unit))
    n = problem.n_specimens
    return Solution(
        x=x,
        nit=1,
        success=np.ones(n, dtype=bool),
        message="Inverse network: parameters predicted from the curves in one forward pass.",
        info={
            "inverse_val_mae_unit": float(model.best_val_mae_),
            "inverse_moments": model.moments_.tolist(),
        },
    )
