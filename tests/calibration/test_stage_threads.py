"""femcal calibrate's own torch threads leave a core to its MLflow process."""

from __future__ import annotations

import pytest
import torch

from femcal.stages.calibrate import leave_a_core_to_mlflow


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize(("given", "left"), [(1, 1), (2, 1), (4, 3)])
def test_one_thread_fewer_never_none(restore_threads, given, left):
    torch.set_num_threads(given)
    assert leave_a_core_to_mlflow() == left
    assert torch.get_num_threads() == left
