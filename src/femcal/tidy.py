"""The tidy table of a prepared split: its columns, reading it back with checks, and its wide
form (configurations x load cases x moments)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from femcal.errors import InputDataError, listed
from femcal.schema import KEY_COLUMNS, LOAD_CASES, OUTPUT_COLUMNS, STATUS_FAILED, STATUS_OK
from femcal.space import ParameterSpace

#: Relative tolerance (fraction of the bound width) of the bounds check on parameters.
BOUNDS_RTOL = 1e-9


_FIX_PREPARE = "run `dvc repro prepare` to rebuild it"


_MAX_LISTED = 5


def tidy_columns(space: ParameterSpace) -> list[str]:
    """Column names of a tidy table, in order, for the given parameter space."""
    return [*KEY_COLUMNS, *space.names, *OUTPUT_COLUMNS]


def listing(items: Sequence[str], total: int | None = None) -> str:
    """``items`` joined by ``"; "``, the first ``_MAX_LISTED`` of them and a count of the rest
    (:func:`femcal.errors.listed`; ``total``: how many there are in all)."""
    return listed(items, total=total, most=_MAX_LISTED, sep="; ")


def finalize(df: pd.DataFrame, space: ParameterSpace) -> pd.DataFrame:
    """Apply the canonical column order and dtypes of a tidy table."""
    df = df[tidy_columns(space)].copy()
    df["config_id"] = df["config_id"].astype(np.int64)
    for col in ("moment_nm", *space.names, "rom_deg", "idp_mpa"):
        df[col] = df[col].astype(np.float64)
    df["load_case"] = df["load_case"].astype(str)
    df["status"] = df["status"].astype(str)
    return df.reset_index(drop=True)


def load_tidy(path: Path, space: ParameterSpace) -> pd.DataFrame:
    """Read a tidy table written by :func:`prepare_dataset`, with validation.

    Parameters
    ----------
    path : Path
        A ``<split>.csv`` file.
    space : ParameterSpace
        The parameter space (``parameter_space.json``) the table was prepared with.

    Returns
    -------
    pandas.DataFrame, shape (n_rows, 3 + d + 3)
        Columns :func:`tidy_columns`, same dtypes as :func:`read_split`; floats round-trip
        exactly.

    Raises
    ------
    InputDataError
        The file is missing, lacks or adds columns, or holds invalid values.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"Prepared table {path} does not exist; {_FIX_PREPARE}.")
    try:
        df = pd.read_csv(
            path,
            float_precision="round_trip",
            dtype={"load_case": str, "status": str},
            keep_default_na=False,
            na_values=[""],
        )
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputDataError(
            f"{path} is not a readable CSV table ({exc}); {_FIX_PREPARE}."
        ) from None
    expected = tidy_columns(space)
    lacking = [c for c in expected if c not in df.columns]
    unknown = [str(c) for c in df.columns if c not in expected]
    if lacking or unknown:
        raise InputDataError(
            f"{path}: missing columns {lacking or 'none'}; unknown columns {unknown or 'none'} "
            f"(expected {expected}). The table does not match the parameter space; "
            f"{_FIX_PREPARE}."
        )
    if not pd.api.types.is_integer_dtype(df["config_id"]):
        raise InputDataError(f"{path}: column 'config_id' must hold integers; {_FIX_PREPARE}.")
    for col in ("moment_nm", *space.names, "rom_deg", "idp_mpa"):
        if not pd.api.types.is_numeric_dtype(df[col]):
            raise InputDataError(f"{path}: column '{col}' must be numeric; {_FIX_PREPARE}.")
    for col in ("moment_nm", *space.names):
        if not np.all(np.isfinite(df[col].to_numpy(dtype=float))):
            raise InputDataError(
                f"{path}: column '{col}' has missing or infinite values; {_FIX_PREPARE}."
            )
    bad_lc = sorted(set(df["load_case"].astype(str)) - set(LOAD_CASES))
    if bad_lc:
        raise InputDataError(
            f"{path}: column 'load_case' has unknown values {bad_lc} (expected "
            f"{list(LOAD_CASES)}); {_FIX_PREPARE}."
        )
    bad_status = sorted(set(df["status"].astype(str)) - {STATUS_OK, STATUS_FAILED})
    if bad_status:
        raise InputDataError(
            f"{path}: column 'status' has unknown values {bad_status} (expected "
            f"'{STATUS_OK}' or '{STATUS_FAILED}'); {_FIX_PREPARE}."
        )
    ok = (df["status"] == STATUS_OK).to_numpy()
    if not np.all(np.isfinite(df.loc[ok, "rom_deg"].to_numpy(dtype=float))):
        raise InputDataError(
            f"{path}: column 'rom_deg' is missing in rows with status '{STATUS_OK}'; "
            f"{_FIX_PREPARE}."
        )
    x = df[list(space.names)].to_numpy(dtype=float)
    tol = BOUNDS_RTOL * space.width
    outside = np.any((x < space.lower - tol) | (x > space.upper + tol), axis=1)
    if outside.any():
        rows = np.flatnonzero(outside)
        raise InputDataError(
            f"{path}: parameter values outside the bounds of the parameter space in rows "
            f"{rows[:_MAX_LISTED].tolist()}; the table and parameter_space.json do not belong "
            f"together; {_FIX_PREPARE}."
        )
    return finalize(df, space)


def to_wide(df: pd.DataFrame, value: str = "rom_deg") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pivot one output column of a tidy table to an array.

    Parameters
    ----------
    df : pandas.DataFrame
        A tidy table (every configuration with every load case and moment exactly once).
    value : str, optional
        Column to pivot ("rom_deg" or "idp_mpa").

    Returns
    -------
    config_ids : ndarray of int, shape (n,)
        Sorted configuration ids.
    moments : ndarray, shape (m,)
        Sorted moments in Nm.
    values : ndarray, shape (n, 4, m)
        ``values[i, k, j]`` for ``config_ids[i]``, ``LOAD_CASES[k]``, ``moments[j]``; NaN
        for failed rows.

    Raises
    ------
    InputDataError
        The table is not a complete grid of configuration x load case x moment.
    """
    config_ids = np.unique(df["config_id"].to_numpy())
    moments = np.unique(df["moment_nm"].to_numpy(dtype=float))
    lc_index = {name: k for k, name in enumerate(LOAD_CASES)}
    lci = df["load_case"].map(lc_index)
    if lci.isna().any():
        raise InputDataError(
            f"Unknown load cases {sorted(set(df['load_case'][lci.isna()]))}; expected "
            f"{list(LOAD_CASES)}."
        )
    ci = np.searchsorted(config_ids, df["config_id"].to_numpy())
    mi = np.searchsorted(moments, df["moment_nm"].to_numpy(dtype=float))
    li = lci.to_numpy(dtype=np.int64)
    shape = (config_ids.size, len(LOAD_CASES), moments.size)
    counts = np.zeros(shape, dtype=np.int64)
    np.add.at(counts, (ci, li, mi), 1)
    if not np.all(counts == 1):
        raise InputDataError(
            "The table is not a complete configuration x load case x moment grid: "
            f"{int(np.sum(counts == 0))} combinations missing, {int(np.sum(counts > 1))} "
            "repeated. Pivot a full tidy table (filter whole configurations only)."
        )
    values = np.full(shape, np.nan)
    values[ci, li, mi] = df[value].to_numpy(dtype=float)
    return config_ids, moments, values


def wide_rom(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RoM as (config_ids (n,), moments (m,), values (n, 4, m)); see :func:`to_wide`."""
    return to_wide(df, value="rom_deg")
