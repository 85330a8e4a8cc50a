"""A failed FE run's reached levels are training rows; the loss is a mean over present rows.

A CalculiX job that stops at level k of 20 keeps its first k RoM values (``status`` ``ok``) and
only the unreached levels are ``failed`` (``femcal.prepare``, tests/test_prepare.py). These tests
pin the training side: :func:`femcal.datasets.ok_rows` keeps those levels, and the padded
configuration blocks the network trains on mask the slots a shorter curve leaves empty, so the
loss is the mean over the rows present whatever the padding holds.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from femcal.datasets import ok_rows
from femcal.schema import LOAD_CASES, STATUS_FAILED, STATUS_OK
from femcal.surrogates.romnet import RomNet
from femcal.surrogates.romnet_training import RomLightningModule, pack_blocks

MOMENTS = np.arange(1.0, 6.0)
LOWER, UPPER = np.array([0.5, -1.0]), np.array([2.0, 0.0])


def partial_table() -> pd.DataFrame:
    """Two configurations x four load cases x five moments; configuration 1's Flexion job
    reached 3 of 5 levels (the last two rows failed, NaN)."""
    cfg, lc, mom = np.meshgrid([0, 1], np.arange(len(LOAD_CASES)), MOMENTS, indexing="ij")
    table = pd.DataFrame(
        {
            "config_id": cfg.ravel(),
            "load_case": np.asarray(LOAD_CASES)[lc.ravel()],
            "moment_nm": mom.ravel(),
            "a": np.where(cfg.ravel() == 0, 0.7, 1.5),
            "b": np.where(cfg.ravel() == 0, -0.2, -0.8),
            "rom_deg": 2.0 * mom.ravel() ** 0.6,
            "status": STATUS_OK,
        }
    )
    tail = (table["config_id"] == 1) & (table["load_case"] == "Flexion") & (table["moment_nm"] > 3)
    table.loc[tail, "rom_deg"] = np.nan
    table.loc[tail, "status"] = STATUS_FAILED
    return table


def test_ok_rows_keep_the_levels_a_failed_run_reached() -> None:
    table = partial_table()
    rows = ok_rows(table)
    flexion = rows[(rows["config_id"] == 1) & (rows["load_case"] == "Flexion")]
    assert flexion["moment_nm"].tolist() == [1.0, 2.0, 3.0]
    assert np.isfinite(rows["rom_deg"]).all()
    assert len(rows) == len(table) - 2


def _blocks(table: pd.DataFrame) -> tuple[torch.Tensor, ...]:
    rows = ok_rows(table)
    lc = pd.Categorical(rows["load_case"], categories=list(LOAD_CASES)).codes.astype(np.int64)
    y = rows["rom_deg"].to_numpy(float)
    params = rows[["a", "b"]].to_numpy(float)
    return pack_blocks(lc, rows["moment_nm"].to_numpy(float), params, y, np.log(y))


def test_the_shorter_curve_leaves_masked_slots() -> None:
    params, lc, moment, target, rom, mask = _blocks(partial_table())
    assert params.shape == (2, 2) and mask.shape == (2, 20)
    assert mask.sum(dim=1).tolist() == [20, 18]  # configuration 1: two levels not reached


@pytest.mark.parametrize("loss", ["l1", "l2"])
def test_loss_is_the_mean_over_present_rows_whatever_the_padding(loss: str) -> None:
    torch.manual_seed(0)
    net = RomNet(LOWER, UPPER, hidden=(8,), moment_degree=2)
    module = RomLightningModule(net, loss=loss)
    batch = _blocks(partial_table())
    params, lc, moment, target, _, mask = batch
    keep = mask.reshape(-1)
    group = torch.arange(2).repeat_interleave(lc.shape[1])[keep]
    flat = [t.reshape(-1)[keep] for t in (lc, moment, target)]
    with torch.no_grad():
        scaled = net.members_scaled(flat[0], flat[1], params, group)
        diff = scaled - flat[2]
        expected = (diff.abs() if loss == "l1" else diff.square()).mean()
        got = module.training_step(batch, 0)
        # other values in the two padded slots: the same loss
        padded = [t.clone() for t in batch]
        padded[3][~mask] = 1e3
        padded[2][~mask] = 7.5
        again = module.training_step(tuple(padded), 0)
    # float32 sums of 38 rows in another order: equal to ~1e-7 relative
    assert float(got) == pytest.approx(float(expected), rel=1e-6)
    assert float(again) == pytest.approx(float(got), rel=1e-6)
