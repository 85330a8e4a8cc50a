"""The inverse network (RoM curves -> parameters in the unit box) and its Lightning wrapper."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from torch import nn

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES
from femcal.surrogates.romnet import ACTIVATIONS, check_activation


def last_val_mae(trainer: pl.Trainer, module: pl.LightningModule) -> float | None:
    """The float64 validation MAE of an :class:`InverseLightningModule`'s last epoch (for
    :class:`~femcal.training.lightning.BestWeights`); None before the first one."""
    value = getattr(module, "last_val_mae", math.nan)
    return None if math.isnan(value) else float(value)


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
        check_activation(activation)
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
    without validation). Logs per epoch ``train_loss``, ``val_mae`` and ``lr``; the epoch's
    validation MAE in float64 is :attr:`last_val_mae` (what
    :class:`~femcal.training.lightning.BestWeights` reads to keep the best epoch's weights).

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
        #: The validation MAE of the last validation epoch (NaN before the first one).
        self.last_val_mae = math.nan
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
        self.last_val_mae = val

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
