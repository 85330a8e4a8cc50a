"""Turn the study's raw FE files into one tidy, validated table per split.

The tidy table has one row per configuration x load case x moment (the 0 Nm unloaded state
is dropped) with the columns ``config_id, load_case, moment_nm, <13 parameters>, rom_deg,
idp_mpa, status``. A simulation that aborted (RoM zero or missing from some moment to the
last one) is kept as rows with ``status == "failed"`` and NaN outputs; it is never dropped
and never turned into zeros.
"""

from __future__ import annotations

import logging
import math
import os
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES, STATUS_FAILED, STATUS_OK
from femcal.space import ParameterSpace
from femcal.tidy import BOUNDS_RTOL, finalize, listing

logger = logging.getLogger(__name__)

#: Name of the bounds file in every split folder.
BOUNDS_FILE = "ParameterBounds.csv"
#: Name of the parameter-space file written next to the tidy tables.
PARAMETER_SPACE_FILE = "parameter_space.json"
#: Largest magnitude accepted for the 0 Nm (unloaded) column.
ZERO_MOMENT_ATOL = 1e-6

_MISSING_TOKENS = frozenset({"", "nan", "na", "n/a", "null", "none", "-nan"})
_FIX_REFETCH = "re-run the 'fetch' stage to restore the published files, or fix the file"


@dataclass(frozen=True)
class SplitLayout:
    """Folder and file names of one split of the study's dataset.

    Parameters
    ----------
    name : str
        Split key ("large", "small", "test").
    folder : str
        Folder under the raw root ("Large", "Small", "Test").
    suffix : str
        File-name infix: ``""``, ``"Small_128_"`` or ``"TestData_64_"``.
    """

    name: str
    folder: str
    suffix: str

    @property
    def configurations(self) -> str:
        """File name of the configuration table, e.g. ``MaterialConfigurations_Small_128.csv``."""
        tag = f"_{self.suffix.rstrip('_')}" if self.suffix else ""
        return f"MaterialConfigurations{tag}.csv"

    @property
    def bounds(self) -> str:
        """File name of the bounds table."""
        return BOUNDS_FILE

    def results(self, quantity: str, load_case: str) -> str:
        """File name of a result table; ``quantity`` is ``"ROM"`` or ``"IDP"``."""
        return f"{quantity}_Results_{load_case}_{self.suffix}wMoment.csv"

    def relpaths(self) -> list[str]:
        """All files of the split, as POSIX paths relative to the raw root."""
        names = [self.configurations, self.bounds]
        names += [self.results(q, lc) for q in ("ROM", "IDP") for lc in LOAD_CASES]
        return [f"{self.folder}/{n}" for n in names]


#: The study's three splits.
SPLITS: dict[str, SplitLayout] = {
    "large": SplitLayout("large", "Large", ""),
    "small": SplitLayout("small", "Small", "Small_128_"),
    "test": SplitLayout("test", "Test", "TestData_64_"),
}


# ---------------------------------------------------------------------- helpers
def _layout(split: str) -> SplitLayout:
    key = str(split).strip().lower()
    if key not in SPLITS:
        raise ConfigError(f"Unknown split {split!r}; expected one of {sorted(SPLITS)}.")
    return SPLITS[key]


def _read_cells(path: Path) -> tuple[list[str], list[list[object]]]:
    """Read a CSV as text: (stripped header, data rows). Blank lines are kept as empty rows."""
    if not path.is_file():
        raise InputDataError(
            f"Expected data file {path} does not exist; run the 'fetch' stage or give the "
            "right raw-data folder."
        )
    try:
        table = pd.read_csv(
            path,
            header=None,
            dtype=str,
            na_filter=False,
            skip_blank_lines=False,
            index_col=False,
        )
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputDataError(
            f"{path} is not a readable CSV table ({exc}); {_FIX_REFETCH}."
        ) from None
    rows = table.to_numpy(dtype=object).tolist()
    if not rows:
        raise InputDataError(f"{path} is empty; {_FIX_REFETCH}.")
    header = ["" if _is_blank(c) else str(c).strip() for c in rows[0]]
    return header, rows[1:]


def _is_blank(cell: object) -> bool:
    return not isinstance(cell, str) or cell.strip() == ""


def _parse_numbers(
    path: Path, header: Sequence[str], rows: list[list[object]], *, what: str
) -> tuple[np.ndarray, np.ndarray]:
    """Parse text cells to floats exactly.

    Returns
    -------
    values : ndarray, shape (n, k)
        Parsed numbers, NaN where the cell is empty or a missing-value token.
    missing : ndarray of bool, shape (n, k)
        Where the cell was empty or a missing-value token.

    Raises
    ------
    InputDataError
        A cell is not a finite number.
    """
    n, k = len(rows), len(header)
    values = np.full((n, k), np.nan)
    missing = np.zeros((n, k), dtype=bool)
    bad: list[str] = []
    for i, row in enumerate(rows):
        for j, cell in enumerate(row[:k]):
            text = cell.strip() if isinstance(cell, str) else ""
            if text.lower() in _MISSING_TOKENS:
                missing[i, j] = True
                continue
            try:
                number = float(text)
            except ValueError:
                number = math.nan
            if not math.isfinite(number):
                bad.append(f"column '{header[j]}', row {i} (line {i + 2}): {text!r}")
                continue
            values[i, j] = number
        missing[i, len(row) :] = True
    if bad:
        raise InputDataError(
            f"{path}: {what} must be finite numbers; non-numeric or infinite entries at "
            f"{listing(bad)}. Replace them with numbers ({_FIX_REFETCH})."
        )
    return values, missing


def _read_configurations(path: Path, space: ParameterSpace, bounds_name: str) -> np.ndarray:
    """Read a configuration table, shape (n, d), columns in ``space.names`` order."""
    header, rows = _read_cells(path)
    while rows and all(_is_blank(c) for c in rows[-1]):  # trailing empty lines
        rows.pop()
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise InputDataError(f"{path}: repeated column names {dup}; each parameter appears once.")
    unknown = [c for c in header if c not in space.names]
    lacking = [c for c in space.names if c not in header]
    if unknown or lacking:
        raise InputDataError(
            f"{path}: the parameter columns do not match the bounds file {bounds_name}. "
            f"Unknown columns (not in the bounds file): {unknown or 'none'}; missing columns "
            f"(in the bounds file, not here): {lacking or 'none'}. Rename the columns so the "
            "configuration header equals the bounds header."
        )
    if not rows:
        raise InputDataError(f"{path} has a header but no configurations; {_FIX_REFETCH}.")
    values, missing = _parse_numbers(path, header, rows, what="parameter values")
    if missing.any():
        cells = [f"column '{header[j]}', row {i} (line {i + 2})" for i, j in np.argwhere(missing)]
        raise InputDataError(
            f"{path}: missing (empty or NaN) parameter values at {listing(cells)}. Every "
            f"configuration needs all {space.dim} parameters; fill them in ({_FIX_REFETCH})."
        )
    order = [header.index(name) for name in space.names]
    x = values[:, order]
    tol = BOUNDS_RTOL * space.width
    outside = np.argwhere((x < space.lower - tol) | (x > space.upper + tol))
    if outside.size:
        cells = [
            f"column '{space.names[j]}', row {i} (line {i + 2}): {float(x[i, j])!r} not in "
            f"[{space.lower[j]:g}, {space.upper[j]:g}]"
            for i, j in outside
        ]
        raise InputDataError(
            f"{path}: parameter values outside the bounds of {bounds_name}: "
            f"{listing(cells, len(outside))}. Fix the values or the bounds file."
        )
    return x


def _read_results(path: Path, n_configs: int, config_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a result table.

    Returns
    -------
    moments : ndarray, shape (m + 1,)
        Header moments in Nm, starting with 0.
    values : ndarray, shape (n_configs, m + 1)
        Values, NaN where missing.
    """
    header, rows = _read_cells(path)
    try:
        moments = np.array([float(c) for c in header])
    except ValueError:
        raise InputDataError(
            f"{path}: the header must list the applied moments in Nm as numbers (0, 1, ..., 5); "
            f"got {header}. Restore the numeric header ({_FIX_REFETCH})."
        ) from None
    if (
        moments.size < 2
        or not np.all(np.isfinite(moments))
        or moments[0] != 0.0
        or np.any(np.diff(moments) <= 0)
    ):
        raise InputDataError(
            f"{path}: the header must be strictly increasing moments starting at 0 Nm; got "
            f"{header}. Restore the header ({_FIX_REFETCH})."
        )
    # Rows past the configurations that are blank are trailing empty lines, not data.
    while len(rows) > n_configs and all(_is_blank(c) for c in rows[-1]):
        rows.pop()
    if len(rows) != n_configs:
        raise InputDataError(
            f"{path} has {len(rows)} rows but the configuration file {config_path} has "
            f"{n_configs}; row i of every result file must be configuration i. Use the result "
            f"files that belong to this configuration file ({_FIX_REFETCH})."
        )
    values, _ = _parse_numbers(path, header, rows, what="results")
    return moments, values


def _failed_tail(values: np.ndarray) -> np.ndarray:
    """Cells that belong to a zero-or-missing run reaching the last moment, shape (n, m)."""
    void = np.isnan(values) | (values == 0.0)
    return np.flip(np.logical_and.accumulate(np.flip(void, axis=1), axis=1), axis=1)


def _check_unloaded(path: Path, header_moments: np.ndarray, values: np.ndarray) -> None:
    """The 0 Nm column must be ~0 (or missing for a simulation that failed from the start)."""
    v0 = values[:, 0]
    failed_from_start = np.all(_failed_tail(values[:, 1:]), axis=1)
    bad = np.flatnonzero(~((np.abs(v0) < ZERO_MOMENT_ATOL) | (np.isnan(v0) & failed_from_start)))
    if bad.size:
        cells = [f"row {i} (line {i + 2}): {float(v0[i])!r}" for i in bad]
        raise InputDataError(
            f"{path}: column '{header_moments[0]:g}' (the unloaded 0 Nm state) must be 0 "
            f"(|value| < {ZERO_MOMENT_ATOL:g}); got {listing(cells, bad.size)}. The columns "
            f"may be shifted; {_FIX_REFETCH}."
        )


def _classify(
    path: Path, moments: np.ndarray, values: np.ndarray, *, positive: bool, quantity: str
) -> np.ndarray:
    """Validate loaded values (moments > 0) and mark the failed tail.

    Parameters
    ----------
    values : ndarray, shape (n, m)
        Values at the loaded moments.
    positive : bool
        Whether values outside the failed tail must be > 0 (RoM) or may have any sign (IDP).

    Returns
    -------
    ndarray of bool, shape (n, m)
        True where the simulation had failed (zero or missing up to the last moment).
    """
    tail = _failed_tail(values)
    kept = ~tail
    gaps = np.argwhere(kept & np.isnan(values))
    if gaps.size:
        cells = [f"row {i} (line {i + 2}), column '{moments[j]:g}'" for i, j in gaps]
        raise InputDataError(
            f"{path}: missing {quantity} values followed by values at later moments, at "
            f"{listing(cells, len(gaps))}. An aborted simulation must be empty or zero from "
            "some moment to the last one; fill in the gap or blank the rest of the row."
        )
    if positive:
        nonpos = np.argwhere(kept & (values <= 0.0))
        if nonpos.size:
            cells = [
                f"row {i} (line {i + 2}), column '{moments[j]:g}': {float(values[i, j])!r}"
                for i, j in nonpos
            ]
            raise InputDataError(
                f"{path}: {quantity} must be positive; non-positive values that are not an "
                f"aborted tail (zero up to the last moment) at {listing(cells, len(nonpos))}. "
                f"Fix the sign or the values ({_FIX_REFETCH})."
            )
    return tail


# ------------------------------------------------------------------ public API
def read_split(raw_root: Path, split: str, space: ParameterSpace | None = None) -> pd.DataFrame:
    """Read and validate one split of the raw dataset into a tidy table.

    Parameters
    ----------
    raw_root : Path
        Folder holding ``Large/``, ``Small/`` and ``Test/`` (the study's ``datasets/``).
    split : str
        One of :data:`SPLITS` ("large", "small", "test").
    space : ParameterSpace, optional
        Parameter names and bounds to validate against; read from the split's
        ``ParameterBounds.csv`` when omitted.

    Returns
    -------
    pandas.DataFrame, shape (n_configs * 4 * n_moments, 3 + d + 3)
        Columns :func:`tidy_columns`; rows ordered by configuration, load case (in
        :data:`~femcal.schema.LOAD_CASES` order), moment. Failed rows have
        ``status == "failed"`` and NaN ``rom_deg`` and ``idp_mpa``.

    Raises
    ------
    InputDataError
        A file is missing or malformed (the message names the file, column and fix).
    ConfigError
        ``split`` is not a known split.
    """
    layout = _layout(split)
    folder = Path(raw_root) / layout.folder
    bounds_path = folder / layout.bounds
    if space is None:
        space = ParameterSpace.from_bounds_csv(bounds_path)
    config_path = folder / layout.configurations
    x = _read_configurations(config_path, space, bounds_name=str(bounds_path))
    n = x.shape[0]

    moments: np.ndarray | None = None
    moments_source: Path | None = None
    rom_blocks: list[np.ndarray] = []
    idp_blocks: list[np.ndarray] = []
    fail_blocks: list[np.ndarray] = []
    for load_case in LOAD_CASES:
        loaded: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for quantity in ("ROM", "IDP"):
            path = folder / layout.results(quantity, load_case)
            header_moments, values = _read_results(path, n, config_path)
            if moments is None:
                moments, moments_source = header_moments, path
            elif not np.array_equal(header_moments, moments):
                raise InputDataError(
                    f"{path}: moments {header_moments.tolist()} differ from "
                    f"{moments.tolist()} in {moments_source}; all result files of a split must "
                    f"share the same moments ({_FIX_REFETCH})."
                )
            _check_unloaded(path, header_moments, values)
            loaded[quantity] = (path, values[:, 1:])
        rom_path, rom = loaded["ROM"]
        idp_path, idp = loaded["IDP"]
        rom_failed = _classify(rom_path, moments[1:], rom, positive=True, quantity="RoM")
        idp_failed = _classify(idp_path, moments[1:], idp, positive=False, quantity="IDP")
        rom_blocks.append(np.where(rom_failed, np.nan, rom))
        idp_blocks.append(np.where(rom_failed | idp_failed, np.nan, idp))
        fail_blocks.append(rom_failed)

    assert moments is not None
    loaded_moments = moments[1:]
    m, n_lc = loaded_moments.size, len(LOAD_CASES)
    rom_all = np.stack(rom_blocks, axis=1)  # (n, 4, m)
    idp_all = np.stack(idp_blocks, axis=1)
    failed = np.stack(fail_blocks, axis=1)

    columns: dict[str, object] = {
        "config_id": np.repeat(np.arange(n, dtype=np.int64), n_lc * m),
        "load_case": np.tile(np.repeat(np.array(LOAD_CASES, dtype=object), m), n),
        "moment_nm": np.tile(loaded_moments, n * n_lc),
    }
    x_rows = np.repeat(x, n_lc * m, axis=0)
    for j, name in enumerate(space.names):
        columns[name] = x_rows[:, j]
    columns["rom_deg"] = rom_all.reshape(-1)
    columns["idp_mpa"] = idp_all.reshape(-1)
    columns["status"] = np.where(failed.reshape(-1), STATUS_FAILED, STATUS_OK).astype(object)
    df = finalize(pd.DataFrame(columns), space)

    n_failed = int(failed.sum())
    if n_failed:
        n_curves = int(failed.any(axis=2).sum())
        logger.warning(
            "Split %s: %d of %d rows failed (%d aborted simulations of %d configuration x "
            "load case curves); they are kept with status '%s' and NaN outputs.",
            layout.name,
            n_failed,
            len(df),
            n_curves,
            n * n_lc,
            STATUS_FAILED,
        )
    else:
        logger.info("Split %s: %d rows, all simulations converged.", layout.name, len(df))
    return df


def _atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp)`` on a temporary file next to ``path``, then move it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # A unique name created with the usual permissions (mkstemp would make it owner-only).
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def prepare_dataset(
    raw_root: Path,
    out_dir: Path,
    splits: Sequence[str] = ("large", "small", "test"),
    limit_configs: int | None = None,
) -> dict[str, Path]:
    """Write the tidy table of every split and the parameter space.

    The parameter space is read from ``Large/ParameterBounds.csv``; the bounds file of every
    requested split must describe the same space (line endings and number spelling do not
    matter).

    Parameters
    ----------
    raw_root : Path
        Folder holding ``Large/``, ``Small/`` and ``Test/``.
    out_dir : Path
        Output folder; receives ``<split>.csv`` and ``parameter_space.json``.
    splits : sequence of str, optional
        Splits to prepare.
    limit_configs : int, optional
        Keep only the first ``limit_configs`` configurations of each split (quick runs and
        tests); None keeps all.

    Returns
    -------
    dict of str to Path
        ``{split: out_dir / f"{split}.csv", ..., "parameter_space": out_dir /
        "parameter_space.json"}``.

    Raises
    ------
    InputDataError
        A raw file is missing or malformed, or a split's bounds differ from Large's.
    """
    raw_root, out_dir = Path(raw_root), Path(out_dir)
    if limit_configs is not None and int(limit_configs) < 1:
        raise ConfigError(
            f"limit_configs must be a positive number of configurations or null; got "
            f"{limit_configs}."
        )
    reference_path = raw_root / SPLITS["large"].folder / BOUNDS_FILE
    space = ParameterSpace.from_bounds_csv(reference_path)
    tables: dict[str, pd.DataFrame] = {}
    for split in splits:
        layout = _layout(split)
        bounds_path = raw_root / layout.folder / layout.bounds
        split_space = ParameterSpace.from_bounds_csv(bounds_path)
        if split_space != space:
            raise InputDataError(
                f"{bounds_path} differs from {reference_path}: names {list(split_space.names)} "
                f"vs {list(space.names)}, lower {split_space.lower.tolist()} vs "
                f"{space.lower.tolist()}, upper {split_space.upper.tolist()} vs "
                f"{space.upper.tolist()}. All splits must share the study's bounds; restore "
                f"the file ({_FIX_REFETCH})."
            )
        table = read_split(raw_root, layout.name, space)
        if limit_configs is not None:
            table = table[table["config_id"] < int(limit_configs)].reset_index(drop=True)
        tables[layout.name] = table

    written: dict[str, Path] = {}
    for name, df in tables.items():
        path = out_dir / f"{name}.csv"
        _atomic_write(path, lambda tmp, df=df: df.to_csv(tmp, index=False, lineterminator="\n"))
        written[name] = path
        logger.info("Wrote %s (%d rows).", path, len(df))
    space_path = out_dir / PARAMETER_SPACE_FILE
    _atomic_write(space_path, space.to_json)
    written["parameter_space"] = space_path
    return written
