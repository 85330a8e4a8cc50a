"""Training :class:`~femcal.surrogates.romnet.RomNet` with Lightning: the LightningModule and
the padded configuration blocks it trains on. Imported only to train, so that loading a
surrogate and calibrating never import Lightning."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch

from femcal.errors import ConfigError
from femcal.surrogates.romnet import LOSSES, LR_SCHEDULES, RomNet


# ------------------------------------------------------------------------ Lightning wrapper
class RomLightningModule(pl.LightningModule):
    """Trains the members of a :class:`RomNet` with Lightning.

    A batch is a tuple of padded configuration blocks ``(params, load_case_index, moment_nm,
    target, rom_deg, mask)`` with shapes (b, d), (b, r), (b, r), (b, r), (b, r), (b, r): ``b``
    configurations with up to ``r`` rows each; ``target`` is the scaled output, ``mask`` marks
    real rows. Logs per epoch ``train_loss`` and ``val_loss`` (in scaled units, mean over the
    members) and ``val_mae_deg`` (MAE in degrees of the member mean on validation).

    Parameters
    ----------
    net : RomNet
        The model to train (its scalings already set).
    loss : {"l1", "l2"}
        Loss on the scaled output.
    learning_rate : float
        Peak learning rate of AdamW.
    weight_decay : float
        AdamW's decoupled weight decay.
    lr_schedule : {"onecycle", "cosine", "constant"}
        Per-step schedule over ``trainer.estimated_stepping_batches``.
    """

    def __init__(
        self,
        net: RomNet,
        *,
        loss: str = "l1",
        learning_rate: float = 3e-3,
        weight_decay: float = 0.0,
        lr_schedule: str = "onecycle",
    ) -> None:
        super().__init__()
        if loss not in LOSSES:
            raise ConfigError(f"Unknown loss '{loss}'; choose one of {', '.join(LOSSES)}.")
        if lr_schedule not in LR_SCHEDULES:
            raise ConfigError(
                f"Unknown lr_schedule '{lr_schedule}'; choose one of {', '.join(LR_SCHEDULES)}."
            )
        self.net = net
        self.loss_name = loss
        self.learning_rate = float(learning_rate)
        self.weight_decay = float(weight_decay)
        self.lr_schedule = lr_schedule
        #: One dict per epoch: epoch, train_loss, val_loss, val_mae_deg (NaN without validation).
        self.history: list[dict[str, float]] = []
        self._train_sum = torch.zeros(())
        self._train_n = 0
        self._val_sums = [torch.zeros(()), torch.zeros(())]
        self._val_n = 0

    @staticmethod
    def _flatten(batch: Sequence[torch.Tensor]) -> tuple[torch.Tensor, ...]:
        params, lc, moment, target, rom, mask = batch
        keep = mask.reshape(-1)
        group = torch.arange(params.shape[0]).repeat_interleave(lc.shape[1])[keep]
        flat = (t.reshape(-1)[keep] for t in (lc, moment, target, rom))
        return (params, group, *flat)

    def _loss(self, scaled: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        diff = scaled - target.unsqueeze(0)
        per = diff.abs() if self.loss_name == "l1" else diff.square()
        return per.mean()

    def training_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> torch.Tensor:
        params, group, lc, moment, target, _ = self._flatten(batch)
        loss = self._loss(self.net.members_scaled(lc, moment, params, group), target)
        # Accumulated here and logged once per epoch: self.log per step costs ~1 ms.
        n = target.numel()
        self._train_sum = self._train_sum + loss.detach() * n
        self._train_n += n
        return loss

    def on_train_epoch_start(self) -> None:
        self._train_sum = torch.zeros(())
        self._train_n = 0

    def validation_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> None:
        params, group, lc, moment, target, rom = self._flatten(batch)
        scaled = self.net.members_scaled(lc, moment, params, group)
        deg = self.net.to_degrees(scaled).mean(0)
        n = target.numel()
        val_loss = self._loss(scaled, target)
        val_mae = (deg - rom).abs().mean()
        self.log("val_loss", val_loss, on_epoch=True, batch_size=n)
        self.log("val_mae_deg", val_mae, on_epoch=True, batch_size=n)
        self._val_sums = [s + v.detach() * n for s, v in zip(self._val_sums, (val_loss, val_mae))]
        self._val_n += n

    def on_validation_epoch_start(self) -> None:
        self._val_sums = [torch.zeros(()), torch.zeros(())]
        self._val_n = 0

    def on_train_epoch_end(self) -> None:
        train_loss = float(self._train_sum) / max(self._train_n, 1)
        self.log("train_loss", train_loss, on_step=False, on_epoch=True)
        row = {"epoch": int(self.current_epoch), "train_loss": train_loss}
        for key, total in zip(("val_loss", "val_mae_deg"), self._val_sums):
            row[key] = float(total) / self._val_n if self._val_n else math.nan
        self.history.append(row)
        self._val_n = 0

    def configure_optimizers(self) -> Any:
        opt = torch.optim.AdamW(
            self.net.parameters(),
            lr=self.learning_rate,
            weight_decay=self.weight_decay,
            foreach=True,  # one fused update over all tensors; ~2x faster step on CPU
        )
        if self.lr_schedule == "constant":
            return opt
        total = max(1, int(self.trainer.estimated_stepping_batches))
        if self.lr_schedule == "onecycle":
            sched = torch.optim.lr_scheduler.OneCycleLR(
                opt, max_lr=self.learning_rate, total_steps=total, pct_start=0.1
            )
        else:
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(
                opt, T_max=total, eta_min=self.learning_rate * 1e-3
            )
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


# ---------------------------------------------------------------------------- data packing
def pack_blocks(
    lc: np.ndarray, moment: np.ndarray, params: np.ndarray, y: np.ndarray, target: np.ndarray
) -> tuple[torch.Tensor, ...]:
    """Rows -> padded blocks of rows sharing one parameter vector (see RomLightningModule)."""
    uniq, inverse = np.unique(params, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    g = uniq.shape[0]
    order = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse, minlength=g)
    r = int(counts.max())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(order.size) - np.repeat(starts, counts)
    grp = inverse[order]

    def block(values: np.ndarray, fill: float) -> np.ndarray:
        out = np.full((g, r), fill, dtype=values.dtype)
        out[grp, slot] = values[order]
        return out

    mask = np.zeros((g, r), dtype=bool)
    mask[grp, slot] = True
    f32 = torch.float32
    return (
        torch.as_tensor(uniq, dtype=f32),
        torch.as_tensor(block(lc.astype(np.int64), 0)),
        torch.as_tensor(block(moment, 1.0), dtype=f32),  # padding: a valid moment, masked out
        torch.as_tensor(block(target, 0.0), dtype=f32),
        torch.as_tensor(block(y, 0.0), dtype=f32),
        torch.as_tensor(mask),
    )
