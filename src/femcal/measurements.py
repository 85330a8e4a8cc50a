"""Read and validate measured range of motion (RoM) for calibration.

A user's measurements are read into :class:`Measurements`: per specimen, load case and
applied moment, the measured RoM in degrees, a weight for the fit and, optionally, the
intradiscal pressure (IDP) in MPa. :func:`read_measurements` detects one of three layouts:

1. **Long CSV**, one row per measured point, columns ``specimen, load_case, moment_nm,
   rom_deg`` and optionally ``idp_mpa`` and ``weight`` (names are case-insensitive,
   surrounding spaces are ignored). Every cell must be filled in.
2. **Wide CSV** (the study's layout with a specimen and load-case column in front): columns
   ``specimen, load_case`` then one column per moment in Nm (``1,2,3,4,5`` or ``1.0,2.5``),
   one row per specimen and load case. An empty cell means "not measured". A ``0`` column
   (the unloaded state) is allowed and ignored when all its values are 0.
3. **A folder holding the study's result files** ``ROM_Results_<LoadCase>*.csv`` (header =
   moments ``0..5`` in Nm, row *i* = specimen ``"i"``). Load cases without a file are
   missing; empty cells and a run of zeros or empty cells up to the last moment (an aborted
   simulation) are "not measured". The ``IDP_Results_*`` files are not read.

Semicolon- and tab-separated files are accepted as well (the separator is detected from the
header line). Every problem raises :class:`~femcal.errors.InputDataError` naming the file,
the line (1-based, as shown by a text editor) and column, what was found and how to fix it;
all problems of a file are reported at once (the first few are listed).

A specimen that misses whole load cases is not an error: it is logged as a warning and
reported by :meth:`Measurements.missing_load_cases`.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from femcal.errors import InputDataError
from femcal.schema import LOAD_CASES, canonical_load_case

logger = logging.getLogger(__name__)

#: Required columns of the long layout, in the order of :meth:`Measurements.to_long`.
LONG_COLUMNS: tuple[str, ...] = ("specimen", "load_case", "moment_nm", "rom_deg")
#: Optional columns of the long layout.
LONG_OPTIONAL_COLUMNS: tuple[str, ...] = ("weight", "idp_mpa")
#: Columns in front of the moment columns in the wide layout.
WIDE_COLUMNS: tuple[str, ...] = ("specimen", "load_case")
#: Largest magnitude accepted in a 0 Nm (unloaded) column; such a column must be "all 0".
ZERO_MOMENT_ATOL = 1e-6

_STUDY_FILE = re.compile(r"^ROM_Results_(?P<rest>.+)\.csv$", re.IGNORECASE)
_MISSING_TOKENS = frozenset({"", "nan", "na", "n/a", "null", "none", "-nan"})
_MAX_LISTED = 5
_LOAD_CASE_HELP = (
    f"use one of {', '.join(LOAD_CASES)} (common spellings such as 'lateral bending', "
    "'axial_rotation' or 'Lateral-Bending' are accepted)"
)
_LAYOUTS_HELP = (
    "Expected one of: (1) the long layout, columns "
    f"{', '.join(LONG_COLUMNS)} and optionally {', '.join(LONG_OPTIONAL_COLUMNS)}, one row "
    "per measured point; (2) the wide layout, columns specimen, load_case followed by one "
    "column per moment in Nm (e.g. 1,2,3,4,5), one row per specimen and load case; (3) a "
    "folder holding the study's ROM_Results_<LoadCase>*.csv files (header 0,1,2,3,4,5, one "
    "row per specimen)"
)


# ------------------------------------------------------------------ the container
@dataclass(frozen=True, eq=False)
class Measurements:
    """Measured RoM of ``n`` specimens on the grid specimen x load case x moment.

    Build it with :func:`read_measurements` or :func:`from_arrays`; the constructor
    validates and copies its inputs (the arrays are read-only).

    Parameters
    ----------
    specimens : tuple of str, shape (n,)
        Specimen names, in first-appearance order.
    moments : ndarray, shape (m,)
        Sorted unique moments in Nm (all > 0) over all specimens.
    rom_deg : ndarray, shape (n, 4, m)
        Measured RoM in degrees (>= 0), NaN where not measured; axis 1 follows
        :data:`~femcal.schema.LOAD_CASES`.
    weight : ndarray, shape (n, 4, m)
        Weights (>= 0) of the points in the fit; forced to 0 where not measured.
    idp_mpa : ndarray, shape (n, 4, m), or None
        Measured IDP in MPa (finite where measured, NaN elsewhere), or None.
    source : str, optional
        Where the data came from (a file path), used in messages.
    """

    specimens: tuple[str, ...]
    moments: np.ndarray
    rom_deg: np.ndarray
    weight: np.ndarray
    idp_mpa: np.ndarray | None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        fields = _validated(
            self.specimens, self.moments, self.rom_deg, self.weight, self.idp_mpa, self.source
        )
        for name, value in zip(
            ("specimens", "moments", "rom_deg", "weight", "idp_mpa", "source"), fields
        ):
            object.__setattr__(self, name, value)

    @property
    def n_specimens(self) -> int:
        """Number of specimens ``n``."""
        return len(self.specimens)

    def mask(self) -> np.ndarray:
        """Where a point was measured.

        Returns
        -------
        ndarray of bool, shape (n, 4, m)
            True where ``rom_deg`` is not NaN (points with weight 0 count as measured).
        """
        return ~np.isnan(self.rom_deg)

    def missing_load_cases(self) -> dict[str, list[str]]:
        """Load cases in which a specimen has no measured point.

        Returns
        -------
        dict of str to list of str
            ``{specimen: [load case, ...]}`` in :data:`~femcal.schema.LOAD_CASES` order, only
            for specimens that miss at least one load case.
        """
        measured = self.mask().any(axis=2)  # (n, 4)
        return {
            name: [lc for k, lc in enumerate(LOAD_CASES) if not measured[i, k]]
            for i, name in enumerate(self.specimens)
            if not measured[i].all()
        }

    def to_long(self) -> pd.DataFrame:
        """The measured points as a long table.

        Returns
        -------
        pandas.DataFrame, shape (n_points, 5) or (n_points, 6)
            Columns ``specimen, load_case, moment_nm, rom_deg, weight`` (and ``idp_mpa``
            when present), one row per measured point, ordered by specimen (in
            :attr:`specimens` order), load case (in ``LOAD_CASES`` order) and moment.
        """
        i, k, j = np.nonzero(self.mask())
        columns: dict[str, object] = {
            "specimen": pd.array([self.specimens[a] for a in i], dtype="str"),
            "load_case": pd.array([LOAD_CASES[a] for a in k], dtype="str"),
            "moment_nm": self.moments[j].astype(np.float64),
            "rom_deg": self.rom_deg[i, k, j].astype(np.float64),
            "weight": self.weight[i, k, j].astype(np.float64),
        }
        if self.idp_mpa is not None:
            columns["idp_mpa"] = self.idp_mpa[i, k, j].astype(np.float64)
        return pd.DataFrame(columns)

    def subset(self, specimens: Sequence[str]) -> Measurements:
        """The measurements of some specimens only.

        Parameters
        ----------
        specimens : sequence of str
            Names of the specimens to keep, in the order wanted (each once).

        Returns
        -------
        Measurements
            Same source; moments that none of the kept specimens measured are dropped.

        Raises
        ------
        InputDataError
            A name is unknown or repeated, or no name is given.
        """
        names = [specimens] if isinstance(specimens, str) else [str(s) for s in specimens]
        unknown = [s for s in names if s not in self.specimens]
        repeated = sorted({s for s in names if names.count(s) > 1})
        if not names or unknown or repeated:
            problem = (
                "no specimen was requested"
                if not names
                else f"unknown specimens {unknown}"
                if unknown
                else f"repeated specimens {repeated}"
            )
            raise InputDataError(
                f"{self.source}: cannot select specimens: {problem}. The measurements hold "
                f"{_listing([repr(s) for s in self.specimens])}; give each wanted name once "
                "(names are case-sensitive)."
            )
        idx = [self.specimens.index(s) for s in names]
        rom = self.rom_deg[idx]
        keep = ~np.all(np.isnan(rom), axis=(0, 1))
        return Measurements(
            specimens=tuple(names),
            moments=self.moments[keep],
            rom_deg=rom[:, :, keep],
            weight=self.weight[idx][:, :, keep],
            idp_mpa=None if self.idp_mpa is None else self.idp_mpa[idx][:, :, keep],
            source=self.source,
        )


# ------------------------------------------------------------- array validation
def _listing(items: Sequence[str], total: int | None = None) -> str:
    total = len(items) if total is None else total
    shown = ", ".join(items[:_MAX_LISTED])
    more = f" (and {total - _MAX_LISTED} more)" if total > _MAX_LISTED else ""
    return shown + more


def _float_array(value: object, name: str, source: str) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputDataError(
            f"{source}: {name} must be an array of numbers; could not convert it ({exc}). "
            "Pass numbers (NaN where not measured)."
        ) from None


def _validated(
    specimens: object,
    moments: object,
    rom_deg: object,
    weight: object,
    idp_mpa: object,
    source: object,
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, str]:
    """Check and normalise the fields of :class:`Measurements` (copies, read-only arrays)."""
    src = str(source)
    if isinstance(specimens, str) or not isinstance(specimens, Iterable):
        raise InputDataError(
            f"{src}: specimens must be a sequence of names; got {type(specimens).__name__}. "
            "Pass a list or tuple of strings."
        )
    names = tuple(specimens)
    if not names:
        raise InputDataError(f"{src}: there are no specimens; give at least one specimen.")
    for pos, name in enumerate(names):
        if not isinstance(name, str):
            raise InputDataError(
                f"{src}: specimen names must be strings; got {name!r} "
                f"({type(name).__name__}) at position {pos}. Convert the names with str()."
            )
        if not name.strip():
            raise InputDataError(
                f"{src}: specimen at position {pos} has an empty name; give every specimen a name."
            )
    repeated = sorted({s for s in names if names.count(s) > 1})
    if repeated:
        raise InputDataError(
            f"{src}: repeated specimen names {repeated}; each specimen must appear once "
            "(merge its data or rename it)."
        )
    n = len(names)

    m_arr = _float_array(moments, "moments", src)
    if m_arr.ndim != 1 or m_arr.size == 0:
        raise InputDataError(
            f"{src}: moments must be a non-empty 1-D array of moments in Nm; got shape "
            f"{m_arr.shape}."
        )
    if not np.all(np.isfinite(m_arr)) or np.any(m_arr <= 0) or np.any(np.diff(m_arr) <= 0):
        raise InputDataError(
            f"{src}: moments must be finite, positive (Nm, the unloaded 0 Nm state is not a "
            f"data point) and strictly increasing; got {m_arr.tolist()}. Sort them, drop 0 "
            "and repeated values and reorder the last axis of the arrays to match."
        )
    m = m_arr.size
    shape = (n, len(LOAD_CASES), m)

    def where(cells: np.ndarray, values: np.ndarray) -> str:
        items = [
            f"specimen {names[i]!r}, {LOAD_CASES[k]}, {m_arr[j]:g} Nm: {float(values[i, k, j])!r}"
            for i, k, j in cells[:_MAX_LISTED]
        ]
        return _listing(items, len(cells))

    def shaped(value: object, name: str) -> np.ndarray:
        arr = _float_array(value, name, src)
        if arr.shape != shape:
            raise InputDataError(
                f"{src}: {name} has shape {arr.shape}; expected (n_specimens, "
                f"{len(LOAD_CASES)} load cases, n_moments) = {shape}, with axis 1 in the order "
                f"{', '.join(LOAD_CASES)}. Reshape the array."
            )
        return arr

    rom = shaped(rom_deg, "rom_deg")
    bad = np.argwhere(np.isinf(rom))
    if bad.size:
        raise InputDataError(
            f"{src}: rom_deg has infinite values at {where(bad, rom)}; use finite degrees, "
            "or NaN where not measured."
        )
    bad = np.argwhere(rom < 0)
    if bad.size:
        raise InputDataError(
            f"{src}: rom_deg has negative values at {where(bad, rom)}. RoM is a magnitude: "
            "give absolute values (the direction is given by the load case)."
        )
    measured = ~np.isnan(rom)

    if weight is None:
        raise InputDataError(
            f"{src}: weight is missing; pass an array of shape {shape} (or use from_arrays, "
            "which defaults to 1.0 where measured)."
        )
    w = shaped(weight, "weight")
    bad = np.argwhere(measured & ~np.isfinite(w))
    if bad.size:
        raise InputDataError(
            f"{src}: weight is missing or infinite at measured points {where(bad, w)}; give "
            "every measured point a finite weight >= 0."
        )
    bad = np.argwhere(measured & (w < 0))
    if bad.size:
        raise InputDataError(
            f"{src}: weight has negative values at {where(bad, w)}; weights must be >= 0 "
            "(0 leaves a point out of the fit)."
        )
    w = np.where(measured, w, 0.0)

    idp: np.ndarray | None = None
    if idp_mpa is not None:
        idp = shaped(idp_mpa, "idp_mpa")
        bad = np.argwhere(measured & ~np.isfinite(idp))
        if bad.size:
            raise InputDataError(
                f"{src}: idp_mpa is missing or infinite at measured points {where(bad, idp)}; "
                "give the IDP of every measured point, or pass idp_mpa=None."
            )
        idp = np.where(measured, idp, np.nan)

    empty = [names[i] for i in range(n) if not measured[i].any()]
    if empty:
        raise InputDataError(
            f"{src}: specimens {empty} have no measured point; give them data or leave them out."
        )
    unweighted = [names[i] for i in range(n) if not np.any(w[i][measured[i]] > 0)]
    if unweighted:
        raise InputDataError(
            f"{src}: all weights of specimens {unweighted} are 0, so they would not take part "
            "in the fit; give at least one point of each a positive weight or leave them out."
        )

    arrays = [m_arr, rom, w] + ([] if idp is None else [idp])
    for arr in arrays:
        arr.setflags(write=False)
    return names, m_arr, rom, w, idp, src


def from_arrays(
    specimens: Sequence[str],
    moments: Sequence[float] | np.ndarray,
    rom_deg: np.ndarray,
    *,
    weight: np.ndarray | None = None,
    idp_mpa: np.ndarray | None = None,
    source: str = "<memory>",
) -> Measurements:
    """Measurements from arrays, validated like the file readers.

    Parameters
    ----------
    specimens : sequence of str, shape (n,)
        Unique, non-empty specimen names.
    moments : array_like, shape (m,)
        Strictly increasing moments in Nm, all > 0.
    rom_deg : array_like, shape (n, 4, m)
        RoM in degrees (>= 0), NaN where not measured; axis 1 in ``LOAD_CASES`` order.
    weight : array_like, shape (n, 4, m), optional
        Weights >= 0 (finite where measured; set to 0 where not measured). Default: 1.0
        where measured.
    idp_mpa : array_like, shape (n, 4, m), optional
        IDP in MPa, finite where measured (set to NaN where not measured).
    source : str, optional
        Name used in messages.

    Returns
    -------
    Measurements

    Raises
    ------
    InputDataError
        A shape or value is invalid, or a specimen has no measured point with weight > 0.
    """
    if weight is None:
        rom = _float_array(rom_deg, "rom_deg", str(source))
        weight = np.where(np.isnan(rom), 0.0, 1.0)
    meas = Measurements(
        specimens=tuple(specimens) if not isinstance(specimens, str) else specimens,
        moments=moments,
        rom_deg=rom_deg,
        weight=weight,
        idp_mpa=idp_mpa,
        source=str(source),
    )
    _warn_missing(meas)
    return meas


def _warn_missing(meas: Measurements) -> None:
    """Log one warning per set of missing load cases, naming the specimens."""
    groups: dict[tuple[str, ...], list[str]] = {}
    for name, lcs in meas.missing_load_cases().items():
        groups.setdefault(tuple(lcs), []).append(name)
    for lcs, names in groups.items():
        logger.warning(
            "%s: specimen%s %s ha%s no measured point in %s; %s calibrated on the other load "
            "cases only.",
            meas.source,
            "s" if len(names) > 1 else "",
            _listing([repr(s) for s in names]),
            "ve" if len(names) > 1 else "s",
            ", ".join(lcs),
            "they are" if len(names) > 1 else "it is",
        )


# ----------------------------------------------------------------- file reading
@dataclass(frozen=True)
class _Point:
    """One measured point read from a file."""

    specimen: str
    load_case: int
    moment: float
    rom: float
    weight: float
    idp: float
    line: int


class _Problems:
    """Collects the problems of one file and raises them together."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.items: list[tuple[int, str]] = []

    def add(self, line: int, text: str) -> None:
        self.items.append((line, text))

    def raise_if_any(self) -> None:
        if not self.items:
            return
        items = sorted(self.items, key=lambda item: item[0])
        shown = "\n".join(f"  - {text}" for _, text in items[:_MAX_LISTED])
        more = f"\n  (and {len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
        noun = "problem" if len(items) == 1 else "problems"
        raise InputDataError(
            f"{self.source}: {len(items)} {noun} in the measurement file:\n{shown}{more}"
        )


def _parse_number(text: str) -> float | None:
    """A finite float, None for a missing-value token, NaN when ``text`` is not a number."""
    if text.lower() in _MISSING_TOKENS:
        return None
    if "_" in text:  # float() accepts 1_000; a measurement file should not
        return math.nan
    try:
        value = float(text)
    except ValueError:
        return math.nan
    return value if math.isfinite(value) else math.nan


def _is_number(text: str) -> bool:
    value = _parse_number(text)
    return value is not None and not math.isnan(value)


def _not_a_number(text: str) -> str:
    hint = " with a decimal point, not a comma" if "," in text else ""
    return f"{text!r} is not a finite number; write a plain number{hint} such as 2.5"


def _read_records(path: Path) -> tuple[int, list[str], list[tuple[int, list[str]]]]:
    """Read a delimited text file.

    Returns
    -------
    header_line : int
        1-based line number of the header (the first non-blank line).
    header : list of str
        Header cells, stripped; trailing empty cells are dropped.
    records : list of (int, list of str)
        Data records after the header with their 1-based line number and stripped cells;
        blank lines are kept as empty lists.
    """
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputDataError(
            f"{path} is not UTF-8 text (a spreadsheet workbook?); save it as a CSV file with "
            "UTF-8 encoding ('CSV UTF-8' in spreadsheet programs)."
        ) from None
    except OSError as exc:
        raise InputDataError(
            f"{path} could not be read ({exc.strerror or exc}); check the path and the file "
            "permissions."
        ) from None
    first = next((line for line in text.splitlines() if line.strip()), None)
    if first is None:
        raise InputDataError(
            f"{path} is empty; it needs a header line and one line per measurement. "
            f"{_LAYOUTS_HELP}."
        )
    delimiter = max((",", ";", "\t"), key=first.count)
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    records: list[tuple[int, list[str]]] = []
    try:
        for cells in reader:
            cells = [c.strip() for c in cells]
            records.append((reader.line_num, [] if not any(cells) else cells))
    except csv.Error as exc:
        raise InputDataError(
            f"{path}, near line {reader.line_num}: not a valid CSV line ({exc}); check the "
            'quotes ("...") around that line.'
        ) from None
    start = next(i for i, (_, cells) in enumerate(records) if cells)
    header_line, header = records[start]
    while header and not header[-1]:
        header = header[:-1]
    return header_line, header, records[start + 1 :]


def _fit_to_header(
    cells: list[str], width: int, line: int, problems: _Problems
) -> list[str] | None:
    """Pad a record to the header width; None (and a problem) when it has extra cells."""
    extra = [c for c in cells[width:] if c]
    if extra:
        problems.add(
            line,
            f"line {line}: {len(cells)} cells but the header has {width} columns (extra "
            f"{_listing([repr(c) for c in extra])}); remove the extra cells, or quote values "
            "that contain the separator.",
        )
        return None
    return (cells + [""] * width)[:width]


def _normalised_header(path: Path, header: list[str], header_line: int) -> list[str]:
    names = [c.lower() for c in header]
    empty = [j + 1 for j, c in enumerate(names) if not c]
    if empty:
        raise InputDataError(
            f"{path}, line {header_line}: header columns {empty} have no name; name every "
            f"column. {_LAYOUTS_HELP}."
        )
    repeated = sorted({c for c in names if names.count(c) > 1})
    if repeated:
        raise InputDataError(
            f"{path}, line {header_line}: repeated columns {repeated} (names are "
            "case-insensitive); keep each column once."
        )
    return names


def _load_case(text: str, line: int, column: str, problems: _Problems) -> int | None:
    name = canonical_load_case(text) if text else None
    if name is None:
        got = "an empty load case" if not text else f"unknown load case {text!r}"
        problems.add(line, f"line {line}, column '{column}': {got}; {_LOAD_CASE_HELP}.")
        return None
    return LOAD_CASES.index(name)


def _specimen(text: str, line: int, column: str, problems: _Problems) -> str | None:
    if not text:
        problems.add(
            line, f"line {line}, column '{column}': empty specimen name; name the specimen."
        )
        return None
    return text


def _assemble(
    source: str,
    points: list[_Point],
    order: list[str],
    rows_of: dict[str, list[int]],
    *,
    with_idp: bool,
    problems: _Problems,
) -> Measurements:
    """Check per-specimen weights, then build the arrays (raises collected problems)."""
    problems.raise_if_any()  # row problems first: a broken row is not an "empty" specimen
    weights: dict[str, list[float]] = {name: [] for name in order}
    for p in points:
        weights[p.specimen].append(p.weight)
    for name in order:
        own = weights[name]
        lines = _listing([str(x) for x in rows_of.get(name, [])])
        line0 = (rows_of.get(name) or [0])[0]
        if not own:
            problems.add(
                line0,
                f"specimen {name!r} (lines {lines}) has no measured value; fill in its values "
                "or delete its rows.",
            )
        elif not any(w > 0 for w in own):
            problems.add(
                line0,
                f"specimen {name!r} (lines {lines}): all weights are 0, so it would not take "
                "part in the fit; give at least one of its points a positive weight or delete "
                "its rows.",
            )
    problems.raise_if_any()
    if not points:
        raise InputDataError(f"{source} holds no measured value; {_LAYOUTS_HELP}.")
    moments = np.unique(np.array([p.moment for p in points]))
    index = {name: i for i, name in enumerate(order)}
    shape = (len(order), len(LOAD_CASES), moments.size)
    rom = np.full(shape, np.nan)
    weight = np.zeros(shape)
    idp = np.full(shape, np.nan) if with_idp else None
    for p in points:
        cell = (index[p.specimen], p.load_case, int(np.searchsorted(moments, p.moment)))
        rom[cell] = p.rom
        weight[cell] = p.weight
        if idp is not None:
            idp[cell] = p.idp
    return Measurements(tuple(order), moments, rom, weight, idp, source)


def _read_long(path: Path, header_line: int, header: list[str], records: list) -> Measurements:
    names = _normalised_header(path, header, header_line)
    lacking = [c for c in LONG_COLUMNS if c not in names]
    if lacking:
        raise InputDataError(
            f"{path}, line {header_line}: missing required column{'s' if len(lacking) > 1 else ''} "
            f"{', '.join(repr(c) for c in lacking)} (the long layout needs "
            f"{', '.join(LONG_COLUMNS)}; optional {', '.join(LONG_OPTIONAL_COLUMNS)}). Add or "
            "rename the column."
        )
    known = set(LONG_COLUMNS) | set(LONG_OPTIONAL_COLUMNS)
    unknown = [h for h, c in zip(header, names) if c not in known]
    if unknown:
        raise InputDataError(
            f"{path}, line {header_line}: unknown columns {unknown}; the long layout accepts "
            f"{', '.join(LONG_COLUMNS)} and optionally {', '.join(LONG_OPTIONAL_COLUMNS)}. "
            "Rename or delete them (a misspelt 'weight' would otherwise be ignored)."
        )
    col = {c: j for j, c in enumerate(names)}
    problems = _Problems(str(path))
    points: list[_Point] = []
    order: list[str] = []
    rows_of: dict[str, list[int]] = {}
    seen: dict[tuple[str, int, float], int] = {}
    for line, raw in records:
        if not raw:
            continue
        cells = _fit_to_header(raw, len(names), line, problems)
        if cells is None:
            continue
        specimen = _specimen(cells[col["specimen"]], line, "specimen", problems)
        if specimen is not None and specimen not in rows_of:
            order.append(specimen)
            rows_of[specimen] = []
        if specimen is not None:
            rows_of[specimen].append(line)
        lc = _load_case(cells[col["load_case"]], line, "load_case", problems)

        values: dict[str, float] = {"weight": 1.0, "idp_mpa": math.nan}
        valid = specimen is not None and lc is not None
        for name in ("moment_nm", "rom_deg", "weight", "idp_mpa"):
            if name not in col:
                continue
            text = cells[col[name]]
            value = _parse_number(text)
            where = f"line {line}, column '{name}'"
            valid = valid and value is not None and not math.isnan(value)
            if value is None:
                problems.add(
                    line,
                    f"{where}: missing value ({text!r}); every row is one measured point, so "
                    "fill in the value or delete the row.",
                )
            elif math.isnan(value):
                problems.add(line, f"{where}: {_not_a_number(text)}.")
            elif name == "moment_nm" and value <= 0:
                valid = False
                problems.add(
                    line,
                    f"{where}: the moment must be positive; got {text}. The unloaded 0 Nm "
                    "state is not a data point (delete the row); give moments as magnitudes "
                    "(absolute values, the direction is the load case).",
                )
            elif name == "rom_deg" and value < 0:
                valid = False
                problems.add(
                    line,
                    f"{where}: negative RoM {text}. RoM is a magnitude: give the absolute "
                    f"value ({abs(value):g}); the direction is given by the load case.",
                )
            elif name == "weight" and value < 0:
                valid = False
                problems.add(
                    line,
                    f"{where}: negative weight {text}; weights must be >= 0 (0 leaves the "
                    "point out of the fit).",
                )
            else:
                values[name] = value
        if not valid:
            continue
        key = (specimen, lc, values["moment_nm"])
        if key in seen:
            problems.add(
                line,
                f"lines {seen[key]} and {line}: the same point twice (specimen {specimen!r}, "
                f"{LOAD_CASES[lc]}, {values['moment_nm']:g} Nm); delete one of the two rows.",
            )
            continue
        seen[key] = line
        points.append(
            _Point(
                specimen,
                lc,
                values["moment_nm"],
                values["rom_deg"],
                values["weight"],
                values["idp_mpa"],
                line,
            )
        )
    if not order and not problems.items:
        raise InputDataError(
            f"{path} has a header (line {header_line}) but no data rows; add one row per "
            "measured point."
        )
    return _assemble(
        str(path), points, order, rows_of, with_idp="idp_mpa" in col, problems=problems
    )


def _moment_columns(
    path: Path, header: Sequence[str], header_line: int, *, hint: str
) -> np.ndarray:
    """Parse moment headers (Nm, >= 0, unique); raises on the first problem."""
    moments = np.empty(len(header))
    for j, text in enumerate(header):
        value = _parse_number(text)
        if value is None or math.isnan(value):
            raise InputDataError(
                f"{path}, line {header_line}: column {text!r} is not a moment in Nm; {hint}"
            )
        if value < 0:
            raise InputDataError(
                f"{path}, line {header_line}: column {text!r} is a negative moment; give "
                "moments as magnitudes in Nm (the direction is the load case)."
            )
        moments[j] = value
    for j in range(len(moments)):
        same = [header[i] for i in range(j) if moments[i] == moments[j]]
        if same:
            raise InputDataError(
                f"{path}, line {header_line}: columns {same[0]!r} and {header[j]!r} are the "
                "same moment; keep one column per moment."
            )
    return moments


def _curve(
    cells: Sequence[str],
    moments: np.ndarray,
    header: Sequence[str],
    line: int,
    problems: _Problems,
) -> np.ndarray:
    """Values of one row of moment columns, NaN where empty; 0 Nm columns checked, dropped.

    Returns
    -------
    ndarray, shape (k,)
        Values at the positive moments (``moments > 0``), NaN where not measured.
    """
    out: list[float] = []
    for text, moment, name in zip(cells, moments, header):
        value = _parse_number(text)
        where = f"line {line}, column {name!r}"
        if value is not None and math.isnan(value):
            problems.add(line, f"{where}: {_not_a_number(text)}, or leave it empty.")
            value = None
        elif value is None or moment == 0:
            if value is not None and abs(value) >= ZERO_MOMENT_ATOL:
                problems.add(
                    line,
                    f"{where}: {text} at 0 Nm; the unloaded state must be 0 (it is not a data "
                    "point). Set it to 0 or delete the column; check that the columns are not "
                    "shifted.",
                )
        elif value < 0:
            problems.add(
                line,
                f"{where}: negative RoM {text}. RoM is a magnitude: give the absolute value "
                f"({abs(value):g}); the direction is given by the load case.",
            )
            value = None
        if moment > 0:
            out.append(math.nan if value is None else value)
    return np.array(out, dtype=np.float64)


def _read_wide(path: Path, header_line: int, header: list[str], records: list) -> Measurements:
    names = _normalised_header(path, header, header_line)
    lacking = [c for c in WIDE_COLUMNS if c not in names]
    if lacking:
        study = ""
        if all(_is_number(c) for c in header):
            study = (
                " If this is one of the study's ROM_Results_<LoadCase>*.csv files, pass the "
                "folder that holds them instead of the file."
            )
        raise InputDataError(
            f"{path}, line {header_line}: missing required column"
            f"{'s' if len(lacking) > 1 else ''} {', '.join(repr(c) for c in lacking)} (the "
            "wide layout needs specimen, load_case, then one column per moment in Nm). Add "
            f"or rename the column.{study}"
        )
    col = {c: j for j, c in enumerate(names)}
    moment_idx = [j for j, c in enumerate(names) if c not in WIDE_COLUMNS]
    moment_header = [header[j] for j in moment_idx]
    moments = _moment_columns(
        path,
        moment_header,
        header_line,
        hint=(
            "in the wide layout every column after specimen and load_case is a moment (e.g. 1 "
            f"or 2.5). Delete or rename the column, or use the long layout ("
            f"{', '.join(LONG_COLUMNS)}, optionally {', '.join(LONG_OPTIONAL_COLUMNS)})."
        ),
    )
    if not np.any(moments > 0):
        raise InputDataError(
            f"{path}, line {header_line}: no column for a positive moment; add one column per "
            "applied moment in Nm (e.g. 1,2,3,4,5)."
        )
    loaded = moments[moments > 0]
    problems = _Problems(str(path))
    points: list[_Point] = []
    order: list[str] = []
    rows_of: dict[str, list[int]] = {}
    seen: dict[tuple[str, int], int] = {}
    for line, raw in records:
        if not raw:
            continue
        cells = _fit_to_header(raw, len(names), line, problems)
        if cells is None:
            continue
        specimen = _specimen(cells[col["specimen"]], line, header[col["specimen"]], problems)
        lc = _load_case(cells[col["load_case"]], line, header[col["load_case"]], problems)
        values = _curve([cells[j] for j in moment_idx], moments, moment_header, line, problems)
        if specimen is None:
            continue
        if specimen not in rows_of:
            order.append(specimen)
            rows_of[specimen] = []
        rows_of[specimen].append(line)
        if lc is None:
            continue
        if (specimen, lc) in seen:
            problems.add(
                line,
                f"lines {seen[specimen, lc]} and {line}: specimen {specimen!r} has two rows for "
                f"{LOAD_CASES[lc]}; keep one row per specimen and load case.",
            )
            continue
        seen[specimen, lc] = line
        points += [
            _Point(specimen, lc, float(mom), float(v), 1.0, math.nan, line)
            for mom, v in zip(loaded, values)
            if not math.isnan(v)
        ]
    if not order and not problems.items:
        raise InputDataError(
            f"{path} has a header (line {header_line}) but no data rows; add one row per "
            "specimen and load case."
        )
    return _assemble(str(path), points, order, rows_of, with_idp=False, problems=problems)


def _failed_tail(values: np.ndarray) -> np.ndarray:
    """Cells in a run of zero-or-missing values that reaches the last moment, shape (r, k)."""
    void = np.isnan(values) | (values == 0.0)
    return np.flip(np.logical_and.accumulate(np.flip(void, axis=1), axis=1), axis=1)


def _study_files(folder: Path) -> dict[int, Path]:
    """The ROM result file of each load case found in ``folder`` (load-case index -> path)."""
    found: dict[int, list[Path]] = {}
    for path in sorted(p for p in folder.iterdir() if p.is_file()):
        match = _STUDY_FILE.match(path.name)
        if not match:
            continue
        rest = match["rest"]
        name = next((lc for lc in LOAD_CASES if rest.lower().startswith(lc.lower())), None)
        name = name or canonical_load_case(rest.split("_")[0])
        if name is None:
            raise InputDataError(
                f"{path}: the file name does not name a known load case after 'ROM_Results_'; "
                f"{_LOAD_CASE_HELP}. Rename the file (e.g. ROM_Results_Flexion_wMoment.csv) or "
                "move it out of the folder."
            )
        found.setdefault(LOAD_CASES.index(name), []).append(path)
    for k, paths in found.items():
        if len(paths) > 1:
            raise InputDataError(
                f"{folder}: several result files for {LOAD_CASES[k]}: "
                f"{[p.name for p in paths]}; keep one ROM_Results_{LOAD_CASES[k]}*.csv file per "
                "load case in the folder."
            )
    if not found:
        raise InputDataError(
            f"{folder} is a folder without ROM_Results_<LoadCase>*.csv files; pass the "
            f"measurement CSV file itself, or the folder of the study's result files. "
            f"{_LAYOUTS_HELP}."
        )
    return {k: paths[0] for k, paths in sorted(found.items())}


def _read_study(folder: Path) -> Measurements:
    points: list[_Point] = []
    rows_of: dict[str, list[int]] = {}
    for k, path in _study_files(folder).items():
        header_line, header, records = _read_records(path)
        moments = _moment_columns(
            path,
            header,
            header_line,
            hint="the header of a study result file lists the applied moments in Nm (0,1,...,5).",
        )
        if not np.any(moments > 0):
            raise InputDataError(
                f"{path}, line {header_line}: no column for a positive moment; the header "
                "lists the applied moments in Nm (0,1,2,3,4,5)."
            )
        loaded = moments[moments > 0]
        while records and not records[-1][1]:  # trailing blank lines
            records.pop()
        if not records:
            raise InputDataError(
                f"{path} has a header (line {header_line}) but no rows; row i holds the RoM of "
                "specimen i."
            )
        problems = _Problems(str(path))
        lines = [line for line, _ in records]
        rows = []
        for line, raw in records:
            cells = _fit_to_header(raw, len(header), line, problems) or [""] * len(header)
            rows.append(_curve(cells, moments, header, line, problems))
        problems.raise_if_any()
        values = np.array(rows).reshape(len(rows), loaded.size)
        tail = _failed_tail(values)
        aborted = int(np.sum(np.any(tail & (values == 0.0), axis=1)))
        if aborted:
            logger.warning(
                "%s: %d rows end in zero RoM (aborted simulations); those points are treated "
                "as not measured.",
                path,
                aborted,
            )
        values = np.where(tail, np.nan, values)
        for i, j in np.argwhere(~np.isnan(values)):
            name = str(i)
            points.append(
                _Point(name, k, float(loaded[j]), float(values[i, j]), 1.0, math.nan, lines[i])
            )
            rows_of.setdefault(name, []).append(lines[i])
    order = sorted(rows_of, key=int)
    n_rows = 1 + max((int(p.specimen) for p in points), default=-1)
    dropped = n_rows - len(order)
    if dropped:
        logger.warning(
            "%s: %d rows hold no result in any load case (aborted simulations); those "
            "specimens are left out.",
            folder,
            dropped,
        )
    return _assemble(
        str(folder), points, order, rows_of, with_idp=False, problems=_Problems(str(folder))
    )


def read_measurements(path: str | Path) -> Measurements:
    """Read and validate a measurement file (or a folder of the study's result files).

    Parameters
    ----------
    path : str or Path
        A long or wide CSV file, or a folder holding ``ROM_Results_<LoadCase>*.csv`` files;
        see the module documentation for the layouts.

    Returns
    -------
    Measurements
        ``source`` is ``str(path)``. A specimen missing whole load cases is logged as a
        warning (see :meth:`Measurements.missing_load_cases`).

    Raises
    ------
    InputDataError
        The file is missing, empty, of an unknown layout or holds invalid values; the message
        names the file, line, column and the fix.
    """
    path = Path(path)
    if path.is_dir():
        meas = _read_study(path)
        layout = "study result files"
    elif not path.exists():
        raise InputDataError(
            f"Measurement file {path} does not exist; check the path (relative paths start at "
            f"the current folder {Path.cwd()})."
        )
    else:
        header_line, header, records = _read_records(path)
        names = {c.lower() for c in header}
        if names & {"moment_nm", "rom_deg"}:
            meas, layout = _read_long(path, header_line, header, records), "long"
        elif any(_is_number(c) for c in header):
            meas, layout = _read_wide(path, header_line, header, records), "wide"
        else:
            raise InputDataError(
                f"{path}, line {header_line}: unrecognised layout; the header is {header}. "
                f"{_LAYOUTS_HELP}. Rename the columns to match one of them."
            )
    logger.info(
        "Read %s (%s layout): %d specimens, %d measured points, moments %s Nm.",
        path,
        layout,
        meas.n_specimens,
        int(meas.mask().sum()),
        ", ".join(f"{x:g}" for x in meas.moments),
    )
    _warn_missing(meas)
    return meas
