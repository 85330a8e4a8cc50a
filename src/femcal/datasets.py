"""The prepared dataset as the stages read it: a split's tidy table and the parameter space.

``prepare`` writes ``<split>.csv`` (one row per configuration, load case and moment, failed
simulations kept with their status) and ``parameter_space.json`` into ``data.prepared_dir``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from femcal.schema import STATUS_OK
from femcal.space import ParameterSpace

if TYPE_CHECKING:  # pandas is imported by the readers, not by the CLI's first checks
    import pandas as pd

logger = logging.getLogger(__name__)

#: The parameter space's file in the prepared folder.
SPACE_FILE = "parameter_space.json"


def load_split(prepared_dir: Path, split: str):
    """Read a prepared split and the parameter space."""
    from femcal.tidy import load_tidy

    space = ParameterSpace.from_json(prepared_dir / SPACE_FILE)
    return load_tidy(prepared_dir / f"{split}.csv", space), space


def ok_rows(table: pd.DataFrame) -> pd.DataFrame:
    """Rows of a tidy table whose simulation succeeded (failed ones are kept in the data, not
    trained on)."""
    n_failed = int((table["status"] != STATUS_OK).sum())
    if n_failed:
        logger.info("Leaving %d failed simulation rows out of training.", n_failed)
    return table[table["status"] == STATUS_OK].reset_index(drop=True)


def training_configurations(path: Path) -> np.ndarray:
    """Distinct converged configurations (physical units) of a prepared split, shape (N, d)."""
    from femcal.tidy import load_tidy

    space = ParameterSpace.from_json(path.parent / SPACE_FILE)
    table = ok_rows(load_tidy(path, space))
    return table.drop_duplicates("config_id")[list(space.names)].to_numpy(dtype=float)
