"""A fitted network on disk: config.json + weights.pt, NaN as null, clear errors."""

from __future__ import annotations

import json
import math

import pytest
import torch
from torch import nn

from femcal.errors import InputDataError
from femcal.training.persist import (
    freeze,
    history_from_json,
    history_to_json,
    load_weights,
    read_config,
    save_model_files,
)


def test_round_trip_and_errors(tmp_path) -> None:
    net = nn.Linear(3, 2)
    history = [{"epoch": 0, "val": math.nan}, {"epoch": 1, "val": 0.5}]
    config = {"format": "femcal-test", "version": 1, "history": history_to_json(history)}
    save_model_files(tmp_path / "m", config, net)
    assert json.loads((tmp_path / "m" / "config.json").read_text())["history"][0]["val"] is None

    read = read_config(tmp_path / "m", fmt="femcal-test", what="Thing")
    back = history_from_json(read["history"])
    assert math.isnan(back[0]["val"]) and back[1] == {"epoch": 1, "val": 0.5}
    other = nn.Linear(3, 2)
    other.load_state_dict(load_weights(tmp_path / "m"))
    assert torch.equal(other.weight, net.weight)
    assert freeze(other) is other and not other.training
    assert not any(p.requires_grad for p in other.parameters())

    with pytest.raises(InputDataError, match=r"is not a saved Other"):
        read_config(tmp_path / "m", fmt="femcal-other", what="Other")
    with pytest.raises(InputDataError, match=r"does not exist; give a directory written by Thing"):
        read_config(tmp_path / "none", fmt="femcal-test", what="Thing")
    (tmp_path / "m" / "weights.pt").unlink()
    with pytest.raises(InputDataError, match=r"weights\.pt does not exist"):
        load_weights(tmp_path / "m")
