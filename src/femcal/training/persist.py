"""A fitted torch model on disk: ``config.json`` (settings, fit summary) and ``weights.pt``.

The folder holds data only (JSON and a ``state_dict`` read with ``weights_only=True``), never a
pickle: loading a model runs no code of its. Non-finite floats (NaN validation metrics of a fit
without validation) are written as JSON ``null`` and read back as NaN.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch

from femcal.errors import InputDataError

#: The two files of a saved model.
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "weights.pt"


def finite_or_none(value: Any) -> Any:
    """``value``, or None for a non-finite float (JSON has no NaN)."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def none_to_nan(value: Any) -> Any:
    """Inverse of :func:`finite_or_none`: None -> NaN, anything else unchanged."""
    return math.nan if value is None else value


def history_to_json(history: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per-epoch rows with non-finite floats as None (see :func:`finite_or_none`)."""
    return [{k: finite_or_none(v) for k, v in row.items()} for row in history]


def history_from_json(rows: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per-epoch rows read back, None as NaN."""
    return [{k: none_to_nan(v) for k, v in row.items()} for row in rows]


def save_model_files(path: str | Path, config: Mapping[str, Any], module: torch.nn.Module) -> Path:
    """Write ``config.json`` and ``weights.pt`` (the module's ``state_dict``) into ``path``.

    Parameters
    ----------
    path : str or Path
        The directory, created or overwritten.
    config : mapping
        JSON-serialisable; by convention ``format``, ``version``, ``init``, ``architecture``
        and ``fitted``.
    module : torch.nn.Module
        The fitted network.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    (path / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")
    torch.save(module.state_dict(), path / WEIGHTS_FILE)
    return path


def read_config(path: str | Path, *, fmt: str, what: str) -> dict[str, Any]:
    """The ``config.json`` of a saved model, checked to be of the format ``fmt``.

    Parameters
    ----------
    path : str or Path
        The model's directory.
    fmt : str
        The expected ``format`` entry (e.g. ``"femcal-nn"``).
    what : str
        The class that writes it, for messages (e.g. ``"NeuralSurrogate"``).

    Raises
    ------
    InputDataError
        The file is missing or of another format.
    """
    file = Path(path) / CONFIG_FILE
    try:
        config = json.loads(file.read_text())
    except FileNotFoundError:
        raise InputDataError(
            f"{file} does not exist; give a directory written by {what}.save."
        ) from None
    if config.get("format") != fmt:
        raise InputDataError(f"{file} is not a saved {what}.")
    return config


def load_weights(path: str | Path) -> dict[str, torch.Tensor]:
    """The ``state_dict`` in ``path/weights.pt`` (tensors only, on CPU)."""
    file = Path(path) / WEIGHTS_FILE
    try:
        return torch.load(file, weights_only=True, map_location="cpu")
    except FileNotFoundError:
        raise InputDataError(f"{file} does not exist.") from None


def freeze(module: torch.nn.Module) -> torch.nn.Module:
    """``module`` in eval mode with every parameter's ``requires_grad`` off; returned."""
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    return module
