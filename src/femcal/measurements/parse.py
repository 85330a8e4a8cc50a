"""Parsing the cells of a measurement file: numbers, headers, load cases, curves, and the
problems collected per file."""

from __future__ import annotations

import contextlib
import contextvars
import csv
import io
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from femcal.errors import InputDataError, listed
from femcal.measurements.data import (
    MAX_LISTED,
    Measurements,
    listing,
    repeated_names,
)
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


#: Repeats of one point whose RoM values span more than this many sd of the stated
#: measurement noise conflict: they are still averaged, with a warning naming them.
REPEAT_CONFLICT_SIGMAS = 5.0


#: The same where no noise is stated (degrees: 5 sd of a 0.05 deg noise).
REPEAT_CONFLICT_DEG = 0.25


#: The stated sd of one measurement while a file is read (:func:`stated_noise`).
_NOISE: contextvars.ContextVar[float | None] = contextvars.ContextVar("noise_deg", default=None)


@contextlib.contextmanager
def stated_noise(noise_deg: float | None) -> Iterator[None]:
    """Within the block, the files read state ``noise_deg`` as the sd of one measurement."""
    token = _NOISE.set(noise_deg)
    try:
        yield
    finally:
        _NOISE.reset(token)


_MISSING_TOKENS = frozenset({"", "nan", "na", "n/a", "null", "none", "-nan"})


LOAD_CASE_HELP = (
    f"use one of {', '.join(LOAD_CASES)} (common spellings such as 'lateral bending', "
    "'axial_rotation' or 'Lateral-Bending' are accepted)"
)


LAYOUTS_HELP = (
    "Expected one of: (1) the long layout, columns "
    f"{', '.join(LONG_COLUMNS)} and optionally {', '.join(LONG_OPTIONAL_COLUMNS)}, one row "
    "per measured point; (2) the wide layout, columns specimen, load_case followed by one "
    "column per moment in Nm (e.g. 1,2,3,4,5), one row per specimen and load case; (3) a "
    "folder holding the study's ROM_Results_<LoadCase>*.csv files (header 0,1,2,3,4,5, one "
    "row per specimen)"
)


# ----------------------------------------------------------------- file reading
@dataclass(frozen=True)
class Point:
    """One measured point read from a file."""

    specimen: str
    load_case: int
    moment: float
    rom: float
    weight: float
    idp: float
    line: int


class Problems:
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
        shown = "\n".join(f"  - {text}" for _, text in items[:MAX_LISTED])
        more = f"\n  (and {len(items) - MAX_LISTED} more)" if len(items) > MAX_LISTED else ""
        noun = "problem" if len(items) == 1 else "problems"
        raise InputDataError(
            f"{self.source}: {len(items)} {noun} in the measurement file:\n{shown}{more}"
        )


def parse_number(text: str) -> float | None:
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


def is_number(text: str) -> bool:
    """Whether ``text`` is a number (:func:`parse_number`) and not NaN."""
    value = parse_number(text)
    return value is not None and not math.isnan(value)


def not_a_number(text: str) -> str:
    """The problem's text for a cell ``text`` that is not a finite number, with the fix."""
    hint = " with a decimal point, not a comma" if "," in text else ""
    return f"{text!r} is not a finite number; write a plain number{hint} such as 2.5"


def read_records(path: Path) -> tuple[int, list[str], list[tuple[int, list[str]]]]:
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
            f"{path} is empty; it needs a header line and one line per measurement. {LAYOUTS_HELP}."
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


def fit_to_header(cells: list[str], width: int, line: int, problems: Problems) -> list[str] | None:
    """Pad a record to the header width; None (and a problem) when it has extra cells."""
    extra = [c for c in cells[width:] if c]
    if extra:
        problems.add(
            line,
            f"line {line}: {len(cells)} cells but the header has {width} columns (extra "
            f"{listing([repr(c) for c in extra])}); remove the extra cells, or quote values "
            "that contain the separator.",
        )
        return None
    return (cells + [""] * width)[:width]


class DataRows:
    """The data rows of one file and what a reader collects from them.

    Parameters
    ----------
    path : Path
        The file (named in the problems).
    records : list of (int, list of str)
        ``(line, cells)`` after the header (see :func:`read_records`).
    width : int
        Columns of the header.

    Attributes
    ----------
    problems : Problems
        The problems of the file's rows.
    points : list of Point
        The measured points read (the reader appends them).
    order : list of str
        Specimens in order of first appearance.
    rows_of : dict of str to list of int
        Each specimen's lines.
    """

    def __init__(self, path: Path, records: list[tuple[int, list[str]]], width: int) -> None:
        self.path = path
        self.records = records
        self.width = width
        self.problems = Problems(str(path))
        self.points: list[Point] = []
        self.order: list[str] = []
        self.rows_of: dict[str, list[int]] = {}

    def __iter__(self) -> Iterator[tuple[int, list[str]]]:
        """``(line, cells)`` of every non-empty row padded to the header; a row with extra
        cells is a problem and skipped."""
        for line, raw in self.records:
            if not raw:
                continue
            cells = fit_to_header(raw, self.width, line, self.problems)
            if cells is not None:
                yield line, cells

    def add_row(self, specimen: str, line: int) -> None:
        """Count ``line`` as a row of ``specimen`` (a new specimen goes last in ``order``)."""
        if specimen not in self.rows_of:
            self.order.append(specimen)
            self.rows_of[specimen] = []
        self.rows_of[specimen].append(line)

    def measurements(self, header_line: int, *, one_row_per: str, with_idp: bool) -> Measurements:
        """The points as :class:`Measurements` (see :func:`assemble_points`).

        Raises
        ------
        InputDataError
            The file has no data rows (``one_row_per`` says what a row holds), or the problems
            collected.
        """
        if not self.order and not self.problems.items:
            raise InputDataError(
                f"{self.path} has a header (line {header_line}) but no data rows; add one row "
                f"per {one_row_per}."
            )
        return assemble_points(
            str(self.path),
            self.points,
            self.order,
            self.rows_of,
            with_idp=with_idp,
            problems=self.problems,
        )


def normalised_header(path: Path, header: list[str], header_line: int) -> list[str]:
    """The header's column names in lower case, checked to be named and distinct.

    Parameters
    ----------
    path : Path
        The file, for the message.
    header : list of str
        Header cells, stripped.
    header_line : int
        1-based line of the header, for the message.

    Returns
    -------
    list of str
        One lower-case name per column.

    Raises
    ------
    InputDataError
        A column has no name, or two columns have the same name.
    """
    names = [c.lower() for c in header]
    empty = [j + 1 for j, c in enumerate(names) if not c]
    if empty:
        raise InputDataError(
            f"{path}, line {header_line}: header columns {empty} have no name; name every "
            f"column. {LAYOUTS_HELP}."
        )
    repeated = repeated_names(names)
    if repeated:
        raise InputDataError(
            f"{path}, line {header_line}: repeated columns {repeated} (names are "
            "case-insensitive); keep each column once."
        )
    return names


def parse_load_case(text: str, line: int, column: str, problems: Problems) -> int | None:
    """The index in :data:`~femcal.schema.LOAD_CASES` of the load case named ``text``.

    Parameters
    ----------
    text : str
        The cell, any spelling :func:`~femcal.schema.canonical_load_case` accepts.
    line : int
        1-based line of the cell, for the message.
    column : str
        Column name, for the message.
    problems : Problems
        Collects the problem when the name is empty or unknown.

    Returns
    -------
    int or None
        0..3, or None after adding a problem.
    """
    name = canonical_load_case(text) if text else None
    if name is None:
        got = "an empty load case" if not text else f"unknown load case {text!r}"
        problems.add(line, f"line {line}, column '{column}': {got}; {LOAD_CASE_HELP}.")
        return None
    return LOAD_CASES.index(name)


def parse_specimen(text: str, line: int, column: str, problems: Problems) -> str | None:
    """The specimen name ``text``, or None after adding a problem to ``problems`` when empty.

    ``line`` (1-based) and ``column`` place the cell in the message.
    """
    if not text:
        problems.add(
            line, f"line {line}, column '{column}': empty specimen name; name the specimen."
        )
        return None
    return text


def assemble_points(
    source: str,
    points: list[Point],
    order: list[str],
    rows_of: dict[str, list[int]],
    *,
    with_idp: bool,
    problems: Problems,
) -> Measurements:
    """Check per-specimen weights, then build the arrays (raises collected problems)."""
    problems.raise_if_any()  # row problems first: a broken row is not an "empty" specimen
    weights: dict[str, list[float]] = {name: [] for name in order}
    for p in points:
        weights[p.specimen].append(p.weight)
    for name in order:
        own = weights[name]
        lines = listing([str(x) for x in rows_of.get(name, [])])
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
        raise InputDataError(f"{source} holds no measured value; {LAYOUTS_HELP}.")
    moments = np.unique(np.array([p.moment for p in points]))
    index = {name: i for i, name in enumerate(order)}
    shape = (len(order), len(LOAD_CASES), moments.size)
    rom = np.full(shape, np.nan)
    weight = np.zeros(shape)
    idp = np.full(shape, np.nan) if with_idp else None
    cells: dict[tuple[int, int, int], list[Point]] = {}
    for p in points:
        cell = (index[p.specimen], p.load_case, int(np.searchsorted(moments, p.moment)))
        cells.setdefault(cell, []).append(p)
    for cell, group in cells.items():
        rom[cell], weight[cell], idp_mean = _combined(group)
        if idp is not None:
            idp[cell] = idp_mean
    _log_repeats(source, [g for g in cells.values() if len(g) > 1])
    return Measurements(tuple(order), moments, rom, weight, idp, source)


def _combined(group: list[Point]) -> tuple[float, float, float]:
    """One point from repeated measurements of it: (RoM, weight, IDP), their weighted means
    (plain means when every weight is 0) and the sum of their weights."""
    w = np.array([p.weight for p in group])
    total = float(w.sum())
    share = w / total if total > 0 else np.full(len(group), 1.0 / len(group))
    return (
        float(share @ np.array([p.rom for p in group])),
        total,
        float(share @ np.array([p.idp for p in group])),
    )


def _log_repeats(source: str, repeats: list[list[Point]]) -> None:
    """Say which points were measured more than once (combined), and warn where two rows
    repeat one point with the same values (a copied row counts as a second measurement)."""
    if not repeats:
        return
    shown = [
        f"{g[0].specimen!r} {LOAD_CASES[g[0].load_case]} {g[0].moment:g} Nm "
        f"({len(g)} rows: lines {listing([str(p.line) for p in g])})"
        for g in repeats
    ]
    # Their scatter measures the noise without any model: the pooled sd of the rows about
    # their point's plain mean (weights aside)
    values = [np.array([p.rom for p in g]) for g in repeats]
    dof = sum(len(v) - 1 for v in values)
    ss = sum(float(np.sum((v - v.mean()) ** 2)) for v in values)
    logger.info(
        "%s: %d point%s measured more than once, each combined into the weighted mean of its "
        "rows (weight: the sum of theirs): %s. The repeats scatter by %.3g deg (pooled sd, "
        "%d degrees of freedom): a measure of the noise that needs no model.",
        source,
        len(repeats),
        "s" if len(repeats) > 1 else "",
        listing(shown),
        float(np.sqrt(ss / dof)),
        dof,
    )
    _warn_conflicts(source, repeats)
    copies = []
    for g in repeats:
        seen: dict[tuple[float, float, float], int] = {}
        for p in g:
            key = (p.rom, p.weight, p.idp if not math.isnan(p.idp) else -1.0)
            if key in seen:
                copies.append(f"lines {seen[key]} and {p.line}")
            else:
                seen[key] = p.line
    if copies:
        logger.warning(
            "%s: %s repeat a point with the same values; each counts as a measurement of its "
            "own. If one is a copy, delete it.",
            source,
            listing(copies),
        )


def _warn_conflicts(source: str, repeats: list[list[Point]]) -> None:
    """Warn where the repeats of one point span more than :data:`REPEAT_CONFLICT_SIGMAS` sd
    of the stated noise (:func:`stated_noise`; none stated: :data:`REPEAT_CONFLICT_DEG`),
    naming each point (specimen, load case, moment), its values and lines."""
    noise = _NOISE.get()
    if noise:
        limit = REPEAT_CONFLICT_SIGMAS * noise
        why = f"{REPEAT_CONFLICT_SIGMAS:g} sd of the stated {noise:g} deg noise"
    else:
        limit = REPEAT_CONFLICT_DEG
        why = f"no noise stated: {REPEAT_CONFLICT_SIGMAS:g} sd of a 0.05 deg noise"
    conflicts: list[str] = []
    for g in repeats:
        rom = [p.rom for p in g]
        if max(rom) - min(rom) > limit:
            conflicts.append(
                f"specimen {g[0].specimen!r} {LOAD_CASES[g[0].load_case]} {g[0].moment:g} Nm: "
                f"{', '.join(f'{r:g}' for r in rom)} deg (lines "
                f"{listing([str(p.line) for p in g])})"
            )
    if conflicts:
        logger.warning(
            "%s: the repeats of %d point%s differ by more than %.3g deg (%s) and were averaged: "
            "%s. Repeats of one point should agree within the noise: check "
            "those rows for a typo, another specimen or another load case, and correct or "
            "delete the wrong one.",
            source,
            len(conflicts),
            "s" if len(conflicts) > 1 else "",
            limit,
            why,
            listed(conflicts, most=MAX_LISTED, sep="; "),
        )


def moment_columns(path: Path, header: Sequence[str], header_line: int, *, hint: str) -> np.ndarray:
    """Parse moment headers (Nm, >= 0, unique); raises on the first problem."""
    moments = np.empty(len(header))
    for j, text in enumerate(header):
        value = parse_number(text)
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


def curve_points(
    cells: Sequence[str],
    moments: np.ndarray,
    header: Sequence[str],
    line: int,
    problems: Problems,
) -> np.ndarray:
    """Values of one row of moment columns, NaN where empty; 0 Nm columns checked, dropped.

    Returns
    -------
    ndarray, shape (k,)
        Values at the positive moments (``moments > 0``), NaN where not measured.
    """
    out: list[float] = []
    for text, moment, name in zip(cells, moments, header):
        value = parse_number(text)
        where = f"line {line}, column {name!r}"
        if value is not None and math.isnan(value):
            problems.add(line, f"{where}: {not_a_number(text)}, or leave it empty.")
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
