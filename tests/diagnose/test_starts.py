"""The starts of a batch fit: one shape (r, g, dim), laid out flat only for Gauss-Newton."""

from __future__ import annotations

import numpy as np
import torch

from femcal.diagnose.fits import Starts


def test_the_flat_layout_keeps_each_specimens_starts_together_and_picks_them_back():
    rng = np.random.default_rng(0)
    values = torch.as_tensor(rng.random((3, 4, 5)), dtype=torch.float32)  # r=3, g=4, dim=5
    starts = Starts(values)
    assert starts.g == 4 and starts.flat.shape == (12, 5)
    assert starts.owner.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]
    # a value per flat start (here the start itself, 5 = 5 numbers) comes back per specimen
    back = starts.per_specimen(starts.flat.numpy(), 5)
    np.testing.assert_array_equal(back, values.numpy())
    best = np.array([3, 0, 2])
    np.testing.assert_array_equal(starts.pick(starts.flat, best), values[np.arange(3), best])
