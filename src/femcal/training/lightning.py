"""Lightning helpers shared by the trained models: batches, best weights, pruning, loggers.

Every model trains on CPU tensors held in memory: :func:`batch_loader` hands whole batches
(one indexing per tensor, no per-sample collation), :func:`cpu_trainer` builds the Trainer
both models use, :func:`fit_on_cpu` fits a module on it (best weights and early stopping
when there is validation data), :class:`BestWeights` keeps the best validation epoch's weights,
:class:`OptunaPruning` reports to an Optuna trial and :func:`quiet_lightning` silences
Lightning's info logs while restoring torch's global state.
"""

from __future__ import annotations

import contextlib
import logging
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytorch_lightning as pl
import torch

#: Reads the monitored value after a validation epoch: ``(trainer, module) -> float or None``.
ValueReader = Callable[[pl.Trainer, pl.LightningModule], "float | None"]


class BatchDataset(torch.utils.data.Dataset):
    """Tensors indexed along dim 0 by a list of indices (whole batches at once).

    Parameters
    ----------
    *tensors : Tensor, shapes (n, ...)
        Tensors with the same first dimension ``n``.
    """

    def __init__(self, *tensors: torch.Tensor) -> None:
        self.tensors = tuple(tensors)

    def __len__(self) -> int:
        return int(self.tensors[0].shape[0])

    def __getitem__(self, idx: Any) -> tuple[torch.Tensor, ...]:
        idx = torch.as_tensor(idx, dtype=torch.long)  # a list index is slow to convert per tensor
        return tuple(t[idx] for t in self.tensors)


def batch_loader(
    tensors: Sequence[torch.Tensor], batch_size: int, generator: torch.Generator | None
) -> torch.utils.data.DataLoader:
    """A DataLoader of whole batches of ``tensors``.

    Parameters
    ----------
    tensors : sequence of Tensor, shapes (n, ...)
        The data; a batch is the tuple of their rows at the batch's indices.
    batch_size : int
        Rows per batch (the last batch may be smaller).
    generator : torch.Generator or None
        Shuffles the rows each epoch from this generator; None keeps them in order.

    Returns
    -------
    DataLoader
        Yields tuples of tensors of shapes (b, ...), ``b <= batch_size``.
    """
    ds = BatchDataset(*tensors)
    base = (
        torch.utils.data.RandomSampler(ds, generator=generator)
        if generator is not None
        else torch.utils.data.SequentialSampler(ds)
    )
    sampler = torch.utils.data.BatchSampler(base, batch_size=batch_size, drop_last=False)
    return torch.utils.data.DataLoader(ds, sampler=sampler, batch_size=None)


def _callback_metric(monitor: str) -> ValueReader:
    def read(trainer: pl.Trainer, pl_module: pl.LightningModule) -> float | None:
        value = trainer.callback_metrics.get(monitor)
        return None if value is None else float(value)

    return read


class BestWeights(pl.Callback):
    """Keep the state_dict of the best validation epoch in memory; restore it at fit end.

    Parameters
    ----------
    monitor : str
        The logged metric to minimise (read from ``trainer.callback_metrics``).
    read : callable, optional
        ``(trainer, module) -> float or None`` read instead of the logged metric (e.g. a
        module's float64 epoch mean rather than its float32 logged copy).
    """

    def __init__(self, monitor: str = "val_mae_deg", *, read: ValueReader | None = None) -> None:
        self.monitor = monitor
        self.read = read or _callback_metric(monitor)
        self.best = math.inf
        self.state: dict[str, torch.Tensor] | None = None

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        value = self.read(trainer, pl_module)
        if value is None:
            return
        if value < self.best:
            self.best = value
            self.state = {k: v.detach().clone() for k, v in pl_module.state_dict().items()}

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.state is not None:
            pl_module.load_state_dict(self.state)


class OptunaPruning(pl.Callback):
    """Report the validation metric to Optuna after each epoch and stop hopeless trials.

    Parameters
    ----------
    trial : optuna.Trial
        The running trial.
    monitor : str
        The logged metric reported as the trial's intermediate value.

    Attributes
    ----------
    pruned : bool
        Whether the trial asked to stop (the caller then raises ``optuna.TrialPruned``).
    """

    def __init__(self, trial: Any, monitor: str = "val_mae_deg") -> None:
        self.trial = trial
        self.monitor = monitor
        self.pruned = False

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        value = trainer.callback_metrics.get(self.monitor)
        if value is None:
            return
        self.trial.report(float(value), step=trainer.current_epoch)
        if self.trial.should_prune():
            self.pruned = True
            trainer.should_stop = True


def mlflow_logger(run_id: str, prefix: str = "") -> Any:
    """A Lightning MLFlowLogger writing into the existing MLflow run ``run_id``."""
    import mlflow
    from pytorch_lightning.loggers import MLFlowLogger

    return MLFlowLogger(tracking_uri=mlflow.get_tracking_uri(), run_id=run_id, prefix=prefix)


def cpu_trainer(
    *,
    max_epochs: int,
    n_batches: int,
    logger: Any = None,
    callbacks: Sequence[pl.Callback] = (),
    progress: bool = False,
) -> pl.Trainer:
    """The deterministic one-device CPU Trainer of femcal's models.

    No checkpoints, no sanity validation, no model summary; metrics are logged every
    ``min(50, n_batches)`` steps.

    Parameters
    ----------
    max_epochs : int
        Upper bound on epochs.
    n_batches : int
        Training batches per epoch.
    logger : Lightning logger, optional
        None disables logging.
    callbacks : sequence of Lightning callbacks
    progress : bool
        Show Lightning's progress bar.
    """
    return pl.Trainer(
        accelerator="cpu",
        devices=1,
        max_epochs=int(max_epochs),
        logger=logger if logger is not None else False,
        callbacks=list(callbacks),
        enable_checkpointing=False,
        enable_progress_bar=progress,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        deterministic=True,
        log_every_n_steps=min(50, n_batches),
    )


def fit_on_cpu(
    module: pl.LightningModule,
    train_loader: torch.utils.data.DataLoader,
    val_loader: torch.utils.data.DataLoader | None,
    *,
    monitor: str,
    patience: int,
    min_delta: float = 0.0,
    read: ValueReader | None = None,
    callbacks: Sequence[pl.Callback] = (),
    **trainer: Any,
) -> pl.Trainer:
    """Fit ``module`` with :func:`cpu_trainer`; with validation data, keep the best epoch.

    With ``val_loader``, :class:`BestWeights` on ``monitor`` and Lightning's early stopping
    (``patience`` epochs without an improvement of more than ``min_delta``) follow
    ``callbacks``.

    Parameters
    ----------
    module : LightningModule
        The module to train (in place).
    train_loader, val_loader : DataLoader
        Training batches; validation batches or None (no validation, no early stopping).
    monitor : str
        The logged validation metric to minimise.
    patience : int
        Epochs without improvement before stopping.
    min_delta : float
        Smallest change that counts as an improvement.
    read : callable, optional
        How :class:`BestWeights` reads the metric (default: the logged value).
    callbacks : sequence of Lightning callbacks
        Extra callbacks (e.g. Optuna pruning), before the two above.
    **trainer
        The other keywords of :func:`cpu_trainer` (``max_epochs``, ``n_batches``,
        ``logger``, ``progress``).

    Returns
    -------
    Trainer
        The fitted Trainer.
    """
    cbs: list[pl.Callback] = [*callbacks]
    if val_loader is not None:
        cbs.append(BestWeights(monitor, read=read))
        cbs.append(
            pl.callbacks.EarlyStopping(monitor, patience=patience, min_delta=min_delta, mode="min")
        )
    fitted = cpu_trainer(callbacks=cbs, **trainer)
    fitted.fit(module, train_dataloaders=train_loader, val_dataloaders=val_loader)
    return fitted


@contextlib.contextmanager
def quiet_lightning() -> Iterator[None]:
    """Lightning's info logs and data-loader hints silenced; global torch state restored."""
    names = ("lightning.pytorch", "pytorch_lightning", "lightning.fabric", "lightning_fabric")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    deterministic = torch.are_deterministic_algorithms_enabled()
    try:
        for lg in loggers:
            lg.setLevel(logging.WARNING)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*does not have many workers.*")
            warnings.filterwarnings("ignore", message=".*smaller than the logging interval.*")
            warnings.filterwarnings("ignore", message=".*Trying to infer the `batch_size`.*")
            warnings.filterwarnings("ignore", message=".*but have no `val_dataloader`.*")
            warnings.filterwarnings("ignore", message=".*LeafSpec.*")
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)
        torch.use_deterministic_algorithms(deterministic)
