"""Read and validate measured range of motion (RoM) for calibration.

A user's measurements are read into :class:`Measurements`: per specimen, load case and
applied moment, the measured RoM in degrees, a weight for the fit and, optionally, the
intradiscal pressure (IDP) in MPa. :func:`read_measurements` detects one of three layouts:

1. **Long CSV**, one row per measured point, columns ``specimen, load_case, moment_nm,
   rom_deg`` and optionally ``idp_mpa`` and ``weight`` (names are case-insensitive,
   surrounding spaces are ignored). Every cell must be filled in. Rows at the same point
   (specimen, load case, moment) are repeated measurements: they are combined into their
   weighted mean, whose weight is the sum of theirs (a weight is a relative inverse noise
   variance: the mean of ``k`` measurements of weight 1 weighs ``k``), and logged.
2. **Wide CSV** (the study's layout with a specimen and load-case column in front): columns
   ``specimen, load_case`` then one column per moment in Nm (``1,2,3,4,5`` or ``1.0,2.5``),
   one row per specimen and load case (a second row for one is a repeated curve, combined
   point by point like repeated rows of the long layout). An empty cell means "not measured".
   A ``0`` column (the unloaded state) is allowed and ignored when all its values are 0.
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

import logging
import math
import re
from pathlib import Path

import numpy as np

from femcal.errors import InputDataError
from femcal.measurements.data import Measurements, from_arrays, warn_missing
from femcal.measurements.parse import (
    LAYOUTS_HELP,
    LOAD_CASE_HELP,
    LONG_COLUMNS,
    LONG_OPTIONAL_COLUMNS,
    WIDE_COLUMNS,
    DataRows,
    Point,
    Problems,
    assemble_points,
    curve_points,
    fit_to_header,
    is_number,
    moment_columns,
    normalised_header,
    not_a_number,
    parse_load_case,
    parse_number,
    parse_specimen,
    read_records,
    stated_noise,
)
from femcal.schema import LOAD_CASES, canonical_load_case

__all__ = ["Measurements", "from_arrays", "read_measurements"]


logger = logging.getLogger(__name__)


_STUDY_FILE = re.compile(r"^ROM_Results_(?P<rest>.+)\.csv$", re.IGNORECASE)


def _read_long(path: Path, header_line: int, header: list[str], records: list) -> Measurements:
    names = normalised_header(path, header, header_line)
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
    rows = DataRows(path, records, len(names))
    problems = rows.problems
    for line, cells in rows:
        specimen = parse_specimen(cells[col["specimen"]], line, "specimen", problems)
        if specimen is not None:
            rows.add_row(specimen, line)
        lc = parse_load_case(cells[col["load_case"]], line, "load_case", problems)

        values: dict[str, float] = {"weight": 1.0, "idp_mpa": math.nan}
        valid = specimen is not None and lc is not None
        for name in ("moment_nm", "rom_deg", "weight", "idp_mpa"):
            if name not in col:
                continue
            text = cells[col[name]]
            value = parse_number(text)
            where = f"line {line}, column '{name}'"
            valid = valid and value is not None and not math.isnan(value)
            if value is None:
                problems.add(
                    line,
                    f"{where}: missing value ({text!r}); every row is one measured point, so "
                    "fill in the value or delete the row.",
                )
            elif math.isnan(value):
                problems.add(line, f"{where}: {not_a_number(text)}.")
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
        rows.points.append(
            Point(
                specimen,
                lc,
                values["moment_nm"],
                values["rom_deg"],
                values["weight"],
                values["idp_mpa"],
                line,
            )
        )
    return rows.measurements(header_line, one_row_per="measured point", with_idp="idp_mpa" in col)


def _read_wide(path: Path, header_line: int, header: list[str], records: list) -> Measurements:
    names = normalised_header(path, header, header_line)
    lacking = [c for c in WIDE_COLUMNS if c not in names]
    if lacking:
        study = ""
        if all(is_number(c) for c in header):
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
    moments = moment_columns(
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
    rows = DataRows(path, records, len(names))
    problems = rows.problems
    for line, cells in rows:
        specimen = parse_specimen(cells[col["specimen"]], line, header[col["specimen"]], problems)
        lc = parse_load_case(cells[col["load_case"]], line, header[col["load_case"]], problems)
        values = curve_points(
            [cells[j] for j in moment_idx], moments, moment_header, line, problems
        )
        if specimen is None:
            continue
        rows.add_row(specimen, line)
        if lc is None:
            continue
        # a second row of one specimen and load case: a repeated curve, combined point by
        # point with the first (as repeated rows of the long layout)
        rows.points += [
            Point(specimen, lc, float(mom), float(v), 1.0, math.nan, line)
            for mom, v in zip(loaded, values)
            if not math.isnan(v)
        ]
    return rows.measurements(header_line, one_row_per="specimen and load case", with_idp=False)


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
                f"{LOAD_CASE_HELP}. Rename the file (e.g. ROM_Results_Flexion_wMoment.csv) or "
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
            f"{LAYOUTS_HELP}."
        )
    return {k: paths[0] for k, paths in sorted(found.items())}


def _read_study(folder: Path) -> Measurements:
    points: list[Point] = []
    rows_of: dict[str, list[int]] = {}
    for k, path in _study_files(folder).items():
        header_line, header, records = read_records(path)
        moments = moment_columns(
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
        problems = Problems(str(path))
        lines = [line for line, _ in records]
        rows = []
        for line, raw in records:
            cells = fit_to_header(raw, len(header), line, problems) or [""] * len(header)
            rows.append(curve_points(cells, moments, header, line, problems))
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
                Point(name, k, float(loaded[j]), float(values[i, j]), 1.0, math.nan, lines[i])
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
    return assemble_points(
        str(folder), points, order, rows_of, with_idp=False, problems=Problems(str(folder))
    )


def read_measurements(path: str | Path, *, noise_deg: float | None = None) -> Measurements:
    """Read and validate a measurement file (or a folder of the study's result files).

    Parameters
    ----------
    path : str or Path
        A long or wide CSV file, or a folder holding ``ROM_Results_<LoadCase>*.csv`` files;
        see the module documentation for the layouts.
    noise_deg : float, optional
        The stated sd of one measurement: repeats of one point further apart than
        :data:`~femcal.measurements.parse.REPEAT_CONFLICT_SIGMAS` of it are warned about
        (without it, further apart than :data:`~femcal.measurements.parse.REPEAT_CONFLICT_DEG`).

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
    with stated_noise(noise_deg):
        meas, layout = _read(Path(path))
    logger.info(
        "Read %s (%s layout): %d specimens, %d measured points, moments %s Nm.",
        path,
        layout,
        meas.n_specimens,
        int(meas.mask().sum()),
        ", ".join(f"{x:g}" for x in meas.moments),
    )
    warn_missing(meas)
    return meas


def _read(path: Path) -> tuple[Measurements, str]:
    """The measurements of ``path`` and the name of its layout."""
    if path.is_dir():
        meas = _read_study(path)
        layout = "study result files"
    elif not path.exists():
        raise InputDataError(
            f"Measurement file {path} does not exist; check the path (relative paths start at "
            f"the current folder {Path.cwd()})."
        )
    else:
        header_line, header, records = read_records(path)
        names = {c.lower() for c in header}
        if names & {"moment_nm", "rom_deg"}:
            meas, layout = _read_long(path, header_line, header, records), "long"
        elif any(is_number(c) for c in header):
            meas, layout = _read_wide(path, header_line, header, records), "wide"
        else:
            raise InputDataError(
                f"{path}, line {header_line}: unrecognised layout; the header is {header}. "
                f"{LAYOUTS_HELP}. Rename the columns to match one of them."
            )
    return meas, layout
