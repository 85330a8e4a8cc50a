"""Lightning helpers: the batch loader, best weights, the CPU trainer; same seed, same result."""

from __future__ import annotations

import numpy as np
import pytorch_lightning as pl
import torch
from torch import nn

from femcal.training.lightning import (
    BestWeights,
    batch_loader,
    cpu_trainer,
    fit_on_cpu,
    quiet_lightning,
)


class _Regression(pl.LightningModule):
    """A tiny linear regression that logs ``val_mae`` every epoch."""

    def __init__(self) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))
        self.val_maes: list[float] = []

    def training_step(self, batch, batch_idx):
        x, y = batch
        return (self.net(x).squeeze(-1) - y).abs().mean()

    def validation_step(self, batch, batch_idx):
        x, y = batch
        mae = (self.net(x).squeeze(-1) - y).abs().mean()
        self.log("val_mae", mae, on_epoch=True)
        self.val_maes.append(float(mae))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.5)  # large: the loss jumps about


def _data(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(64, 3))
    y = x @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.normal(size=64)
    return torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32)


def _fit(seed: int) -> tuple[_Regression, BestWeights]:
    x, y = _data()
    with quiet_lightning(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        module = _Regression()
        best = BestWeights("val_mae")
        trainer = cpu_trainer(max_epochs=6, n_batches=4, callbacks=[best])
        trainer.fit(
            module,
            train_dataloaders=batch_loader((x, y), 16, torch.Generator().manual_seed(seed)),
            val_dataloaders=batch_loader((x, y), 64, None),
        )
    return module, best


def test_batch_loader_yields_whole_batches() -> None:
    x = torch.arange(10.0)
    y = 2 * x
    ordered = list(batch_loader((x, y), 4, None))
    assert [len(b[0]) for b in ordered] == [4, 4, 2]
    assert torch.equal(ordered[0][0], torch.tensor([0.0, 1.0, 2.0, 3.0]))
    shuffled = list(batch_loader((x, y), 4, torch.Generator().manual_seed(0)))
    assert sorted(torch.cat([b[0] for b in shuffled]).tolist()) == x.tolist()
    assert all(torch.equal(b[1], 2 * b[0]) for b in shuffled)
    again = list(batch_loader((x, y), 4, torch.Generator().manual_seed(0)))
    assert all(torch.equal(a[0], b[0]) for a, b in zip(shuffled, again))


def test_best_weights_are_restored_and_the_same_seed_gives_the_same_model() -> None:
    a, best = _fit(seed=0)
    b, _ = _fit(seed=0)
    c, _ = _fit(seed=1)
    # The restored weights are those of the best validation epoch, not the last one.
    assert best.best == min(a.val_maes)
    x, y = _data()
    with torch.no_grad():
        restored = float((a.net(x).squeeze(-1) - y).abs().mean())
    assert restored == min(a.val_maes)
    for pa, pb in zip(a.state_dict().values(), b.state_dict().values()):
        assert torch.equal(pa, pb)
    assert a.val_maes == b.val_maes
    assert a.val_maes != c.val_maes


def test_quiet_lightning_restores_torch_state() -> None:
    before = torch.are_deterministic_algorithms_enabled()
    with quiet_lightning():
        torch.use_deterministic_algorithms(not before)
    assert torch.are_deterministic_algorithms_enabled() == before


def test_fit_on_cpu_stops_early_and_keeps_the_best_epoch() -> None:
    x, y = _data()
    train = batch_loader((x, y), 16, torch.Generator().manual_seed(0))
    with quiet_lightning(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        module = _Regression()
        trainer = fit_on_cpu(
            module,
            train,
            batch_loader((x, y), 64, None),
            monitor="val_mae",
            patience=1,
            min_delta=10.0,  # no epoch improves by 10: stop after patience + 1 epochs
            max_epochs=20,
            n_batches=4,
        )
    assert trainer.current_epoch == 2
    with torch.no_grad():
        restored = float((module.net(x).squeeze(-1) - y).abs().mean())
    assert restored == min(module.val_maes)


def test_fit_on_cpu_without_validation_runs_every_epoch() -> None:
    x, y = _data()
    with quiet_lightning():
        module = _Regression()
        trainer = fit_on_cpu(
            module,
            batch_loader((x, y), 16, None),
            None,
            monitor="val_mae",
            patience=1,
            max_epochs=3,
            n_batches=4,
        )
    assert trainer.current_epoch == 3
    assert module.val_maes == []
