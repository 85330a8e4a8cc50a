"""Tests of femcal.measurements: reading and validating users' measurement files."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from femcal.errors import InputDataError
from femcal.measurements import from_arrays, read_measurements
from femcal.schema import LOAD_CASES

STUDY_TEST = [
    p
    for p in (
        Path(__file__).resolve().parents[1] / "data" / "raw" / "Test",
        Path("/work/shared/data/ivd-calibnn/Test"),
    )
    if (p / "ROM_Results_Flexion_TestData_64_wMoment.csv").is_file()
]

#: Long layout in canonical order (specimen, LOAD_CASES, moment), so to_long() gives it back.
LONG = """\
specimen,load_case,moment_nm,rom_deg,weight,idp_mpa
S1,Flexion,1.0,1.5,1.0,0.1
S1,Flexion,2.5,2.75,0.5,0.25
S1,Extension,1.0,1.25,1.0,0.125
S1,LateralBending,1.0,2.0,1.0,-0.05
S1,AxialRotation,2.5,0.875,2.0,0.0
S2,Flexion,2.5,3.0,1.0,0.3
S2,LateralBending,1.0,1.75,0.0,0.2
"""

#: The same RoM in both layouts (wide: empty cell = not measured; 0 column ignored).
WIDE_SAME = """\
specimen,load_case,0,1,2,3
S1,Flexion,0,1.0,2.0,3.0
S1,Extension,0.0,1.5,,2.5
S2,AxialRotation,0,0.5,1.0,
"""
LONG_SAME = """\
specimen,load_case,moment_nm,rom_deg
S1,Flexion,1,1.0
S1,Flexion,2,2.0
S1,Flexion,3,3.0
S1,Extension,1,1.5
S1,Extension,3,2.5
S2,AxialRotation,1,0.5
S2,AxialRotation,2,1.0
"""
HEADER = "specimen,load_case,moment_nm,rom_deg"


def write(tmp_path: Path, text: str, name: str = "meas.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def long_file(tmp_path: Path, *rows: str, header: str = HEADER) -> Path:
    """A long-layout file: header on line 1, ``rows`` on lines 2, 3, ..."""
    return write(tmp_path, "\n".join([header, *rows]) + "\n")


def study_folder(tmp_path: Path, tables: dict[str, list[str]]) -> Path:
    """A folder in the study's layout: one ROM_Results_<LC> file per key, header 0..5."""
    folder = tmp_path / "study"
    folder.mkdir()
    for lc, rows in tables.items():
        text = "\r\n".join(["0,1,2,3,4,5", *rows]) + "\r\n"
        (folder / f"ROM_Results_{lc}_TestData_3_wMoment.csv").write_text(text, newline="")
    return folder


# ------------------------------------------------------------------ long layout
def test_long_round_trip(tmp_path: Path) -> None:
    path = write(tmp_path, LONG)
    meas = read_measurements(path)
    assert meas.specimens == ("S1", "S2")
    assert meas.source == str(path)
    np.testing.assert_array_equal(meas.moments, [1.0, 2.5])
    assert meas.rom_deg.shape == meas.weight.shape == meas.idp_mpa.shape == (2, 4, 2)
    expected = pd.read_csv(
        path, dtype={"specimen": str, "load_case": str}, float_precision="round_trip"
    )
    pd.testing.assert_frame_equal(meas.to_long(), expected)


def test_long_arrays_and_defaults(tmp_path: Path) -> None:
    # Column names are case-insensitive and padded; load-case aliases are accepted.
    path = long_file(
        tmp_path,
        "S1 , lateral bending, 2, 1.0",
        "S1,Axial_Rotation,1,0.5",
        "",  # blank lines are ignored
        "S1,FLEXION,1,0.25",
        header=" Specimen , LOAD_CASE ,Moment_Nm,rom_deg ",
    )
    meas = read_measurements(path)
    assert meas.n_specimens == 1 and meas.idp_mpa is None
    k = {lc: i for i, lc in enumerate(LOAD_CASES)}
    assert meas.rom_deg[0, k["LateralBending"], 1] == 1.0
    assert meas.rom_deg[0, k["AxialRotation"], 0] == 0.5
    assert meas.rom_deg[0, k["Flexion"], 0] == 0.25
    assert np.isnan(meas.rom_deg[0, k["Flexion"], 1])
    np.testing.assert_array_equal(meas.weight, np.where(meas.mask(), 1.0, 0.0))
    assert meas.missing_load_cases() == {"S1": ["Extension"]}
    assert not meas.rom_deg.flags.writeable


def test_semicolon_separated(tmp_path: Path) -> None:
    path = write(tmp_path, "specimen;load_case;moment_nm;rom_deg\nS1;Flexion;1;1.5\n")
    assert read_measurements(path).rom_deg[0, 0, 0] == 1.5


def test_missing_load_cases_are_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = long_file(
        tmp_path,
        *[f"S1,{lc},1,1.0" for lc in LOAD_CASES],
        "S2,Flexion,1,1.0",
        "S2,AxialRotation,1,1.0",
    )
    with caplog.at_level(logging.WARNING, logger="femcal.measurements"):
        meas = read_measurements(path)
    assert meas.missing_load_cases() == {"S2": ["Extension", "LateralBending"]}
    assert "specimen 'S2' has no measured point in Extension, LateralBending" in caplog.text
    assert "'S1'" not in caplog.text


# ------------------------------------------------------------------ wide layout
def test_wide_equals_long(tmp_path: Path) -> None:
    wide = read_measurements(write(tmp_path, WIDE_SAME, "wide.csv"))
    long = read_measurements(write(tmp_path, LONG_SAME, "long.csv"))
    assert wide.specimens == long.specimens == ("S1", "S2")
    np.testing.assert_array_equal(wide.moments, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(wide.moments, long.moments)
    np.testing.assert_array_equal(wide.rom_deg, long.rom_deg)
    np.testing.assert_array_equal(wide.weight, long.weight)
    assert wide.idp_mpa is None and long.idp_mpa is None
    pd.testing.assert_frame_equal(wide.to_long(), long.to_long())


def test_wide_decimal_moment_headers(tmp_path: Path) -> None:
    path = write(tmp_path, "Specimen,Load_Case,1.0,2.5\nS1,Extension,0.5,\n")
    meas = read_measurements(path)
    np.testing.assert_array_equal(meas.moments, [1.0])  # 2.5 Nm was not measured
    assert meas.rom_deg[0, 1, 0] == 0.5


# ------------------------------------------------------------- study directory
def test_study_folder(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = study_folder(
        tmp_path,
        {
            "Flexion": [
                "1e-18,1.0,2.0,3.0,4.0,5.0",
                "0.0,1.5,2.5,3.5,4.5,5.5",
                "0.0,0.5,1.0,0.0,0.0,0.0",  # aborted at 3 Nm: the zero tail is not measured
            ],
            "AxialRotation": ["0,0.25,0.5,0.75,1.0,1.25", "0,0.3,0.6,0.9,1.2,1.5"],
        },
    )
    (folder / "IDP_Results_Flexion_TestData_3_wMoment.csv").write_text("0,1\n0,9\n")
    with caplog.at_level(logging.WARNING, logger="femcal.measurements"):
        meas = read_measurements(folder)
    assert meas.specimens == ("0", "1", "2")
    np.testing.assert_array_equal(meas.moments, [1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(meas.rom_deg[1, 0], [1.5, 2.5, 3.5, 4.5, 5.5])
    np.testing.assert_array_equal(meas.rom_deg[2, 0], [0.5, 1.0, np.nan, np.nan, np.nan])
    np.testing.assert_array_equal(meas.rom_deg[0, 3], [0.25, 0.5, 0.75, 1.0, 1.25])
    assert np.all(np.isnan(meas.rom_deg[:, 1:3]))
    assert meas.idp_mpa is None
    assert meas.missing_load_cases() == {
        "0": ["Extension", "LateralBending"],
        "1": ["Extension", "LateralBending"],
        "2": ["Extension", "LateralBending", "AxialRotation"],
    }
    assert "1 rows end in zero RoM (aborted simulations)" in caplog.text
    assert "specimens '0', '1' have no measured point in Extension, LateralBending" in caplog.text


@pytest.mark.skipif(not STUDY_TEST, reason="the study's Test split is not available")
def test_study_test_split() -> None:
    folder = STUDY_TEST[0]
    meas = read_measurements(folder)
    assert meas.n_specimens == 64 and meas.missing_load_cases() == {}
    np.testing.assert_array_equal(meas.moments, [1.0, 2.0, 3.0, 4.0, 5.0])
    for k, lc in enumerate(LOAD_CASES):
        raw = pd.read_csv(
            folder / f"ROM_Results_{lc}_TestData_64_wMoment.csv", float_precision="round_trip"
        )
        np.testing.assert_array_equal(meas.rom_deg[:, k], raw.to_numpy()[:, 1:])


@pytest.mark.parametrize(
    ("files", "match"),
    [
        ({}, r"study is a folder without ROM_Results_<LoadCase>\*\.csv files"),
        (
            {"ROM_Results_Twist_wMoment.csv": "0,1\n0,1\n"},
            r"ROM_Results_Twist_wMoment\.csv: the file name does not name a known load case.*"
            "Flexion, Extension, LateralBending, AxialRotation",
        ),
        (
            {"ROM_Results_Flexion_wMoment.csv": "0,1\n0,1\n", "ROM_Results_Flexion_b.csv": "0,1\n"},
            r"several result files for Flexion",
        ),
        (
            {"ROM_Results_Flexion_wMoment.csv": "0,1,2\n0,1,2\n0,1,-2\n"},
            r"(?s)Flexion_wMoment\.csv: 1 problem.*line 3, column '2': negative RoM -2\. RoM is a "
            r"magnitude: give the absolute value \(2\)",
        ),
        (
            {"ROM_Results_Flexion_wMoment.csv": "0,1,2\n0.5,1,2\n"},
            r"line 2, column '0': 0\.5 at 0 Nm; the unloaded state must be 0",
        ),
        (
            {"ROM_Results_Flexion_wMoment.csv": "a,b\n0,1\n"},
            r"line 1: column 'a' is not a moment in Nm; the header of a study result file",
        ),
    ],
)
def test_study_folder_errors(tmp_path: Path, files: dict[str, str], match: str) -> None:
    folder = tmp_path / "study"
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text)
    with pytest.raises(InputDataError, match=match):
        read_measurements(folder)


# ------------------------------------------------------------- file-level errors
def test_not_text(tmp_path: Path) -> None:
    path = tmp_path / "meas.xlsx"
    path.write_bytes(b"PK\x03\x04\xff\xfe\x00binary")
    with pytest.raises(InputDataError, match=r"meas\.xlsx is not UTF-8 text.*save it as a CSV"):
        read_measurements(path)


def test_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match=r"nope\.csv does not exist; check the path"):
        read_measurements(tmp_path / "nope.csv")


@pytest.mark.parametrize("text", ["", "\n  \n\n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    with pytest.raises(InputDataError, match=r"meas\.csv is empty; it needs a header line"):
        read_measurements(write(tmp_path, text))


@pytest.mark.parametrize(
    ("header", "match"),
    [
        (HEADER, "has a header \\(line 1\\) but no data rows; add one row per measured point"),
        ("specimen,load_case,1,2", "but no data rows; add one row per specimen and load case"),
    ],
)
def test_header_without_rows(tmp_path: Path, header: str, match: str) -> None:
    with pytest.raises(InputDataError, match=match):
        read_measurements(write(tmp_path, header + "\n"))


def test_unrecognised_layout(tmp_path: Path) -> None:
    with pytest.raises(
        InputDataError,
        match=r"line 1: unrecognised layout; the header is \['name', 'case', 'value'\]\. "
        r"Expected one of: \(1\) the long layout, columns specimen, load_case, moment_nm, "
        r"rom_deg and optionally weight, idp_mpa.*\(2\) the wide layout.*\(3\) a folder "
        r"holding the study's ROM_Results_<LoadCase>\*\.csv files",
    ):
        read_measurements(write(tmp_path, "name,case,value\nS1,Flexion,1\n"))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("specimen,load_case,moment_nm\nS1,Flexion,1\n", r"missing required column 'rom_deg'"),
        (
            "load_case,rom_deg\nFlexion,1\n",
            r"missing required columns 'specimen', 'moment_nm' \(the long layout needs",
        ),
        ("specimen,1,2\nS1,1,2\n", r"missing required column 'load_case' \(the wide layout"),
        ("0,1,2\n0,1,2\n", r"missing required columns.*pass the folder that holds them"),
        (
            HEADER + ",wieght\nS1,Flexion,1,1,1\n",
            r"unknown columns \['wieght'\]; the long layout accepts",
        ),
        (HEADER + ",Rom_Deg\nS1,Flexion,1,1,1\n", r"repeated columns \['rom_deg'\]"),
        (
            "specimen,load_case,1,notes\nS1,Flexion,1,x\n",
            r"line 1: column 'notes' is not a moment in Nm; in the wide layout every column",
        ),
        ("specimen,load_case,1,1.0\nS1,Flexion,1,1\n", r"columns '1' and '1\.0' are the same"),
        ("specimen,load_case,-1,1\nS1,Flexion,1,1\n", r"column '-1' is a negative moment"),
        ("specimen,load_case,0\nS1,Flexion,0\n", r"no column for a positive moment"),
    ],
)
def test_header_errors(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(InputDataError, match=match):
        read_measurements(write(tmp_path, text))


# --------------------------------------------------------------- row errors
LC_HELP = (
    r"use one of Flexion, Extension, LateralBending, AxialRotation \(common spellings such "
    r"as 'lateral bending'"
)


def test_repeated_rows_are_combined_into_their_weighted_mean(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """What to measure next asks for repeated measurements at one point: rows at the same
    point are combined (weighted mean, weights summed), not refused, and the log says so."""
    path = long_file(
        tmp_path,
        "S1,Flexion,1,1.0",
        "S1,Extension,6,2.0",
        "S1,extension,6.0,2.4",
        "S1,Extension,6,2.2",
        header="specimen,load_case,moment_nm,rom_deg",
    )
    with caplog.at_level(logging.INFO, logger="femcal.measurements"):
        meas = read_measurements(path)
    j = int(np.searchsorted(meas.moments, 6.0))
    ext = LOAD_CASES.index("Extension")
    assert meas.rom_deg[0, ext, j] == pytest.approx(2.2)
    assert meas.weight[0, ext, j] == 3.0
    assert meas.weight[0, 0, 0] == 1.0
    assert len(meas.to_long()) == 2
    assert "'S1' Extension 6 Nm (3 rows: lines 3, 4, 5)" in caplog.text
    # 2.0, 2.4, 2.2 about their mean 2.2: sd 0.2 on 2 degrees of freedom
    assert "The repeats scatter by 0.2 deg (pooled sd, 2 degrees of freedom)" in caplog.text
    assert "same values" not in caplog.text


def test_repeated_rows_weighted(tmp_path: Path) -> None:
    path = long_file(
        tmp_path,
        "S1,Flexion,1,1.0,1,0.1",
        "S1,Flexion,1,2.0,3,0.5",
        header="specimen,load_case,moment_nm,rom_deg,weight,idp_mpa",
    )
    meas = read_measurements(path)
    assert meas.rom_deg[0, 0, 0] == pytest.approx(1.75)
    assert meas.weight[0, 0, 0] == 4.0
    assert meas.idp_mpa[0, 0, 0] == pytest.approx(0.4)


def test_repeated_rows_of_weight_zero_keep_their_plain_mean(tmp_path: Path) -> None:
    path = long_file(
        tmp_path,
        "S1,Flexion,1,1.0,0",
        "S1,Flexion,1,2.0,0",
        "S1,Flexion,2,2.0,1",
        header="specimen,load_case,moment_nm,rom_deg,weight",
    )
    meas = read_measurements(path)
    assert meas.rom_deg[0, 0, 0] == pytest.approx(1.5)
    assert meas.weight[0, 0, 0] == 0.0


def test_repeats_that_differ_beyond_the_noise_are_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two rows at one point 1 deg apart (20 sd of a 0.05 deg noise): averaged, with a
    warning naming the specimen, load case, moment, values and lines."""
    path = long_file(tmp_path, "S1,Flexion,2,3.1", "S1,Flexion,1,1.0", "S1,Flexion,2,4.1")
    with caplog.at_level(logging.INFO, logger="femcal.measurements"):
        meas = read_measurements(path)
    assert meas.rom_deg[0, 0, 1] == pytest.approx(3.6)
    (warned,) = [r for r in caplog.records if "differ by" in r.getMessage()]
    assert warned.levelno == logging.WARNING
    assert (
        "the repeats of 1 point differ by more than 0.25 deg (no noise stated: 5 sd of a 0.05 "
        "deg noise) and were averaged: specimen 'S1' Flexion 2 Nm: 3.1, 4.1 deg (lines 2, 4)"
        in warned.getMessage()
    )
    caplog.clear()
    write(tmp_path, f"{HEADER}\nS1,Flexion,2,3.1\nS1,Flexion,2,3.2\n", name="close.csv")
    with caplog.at_level(logging.INFO, logger="femcal.measurements"):
        read_measurements(tmp_path / "close.csv")
    assert not [r for r in caplog.records if "differ by" in r.getMessage()]
    # With a stated noise: 5 sd of it (0.1 deg apart is 10 sd of 0.01 deg).
    with caplog.at_level(logging.INFO, logger="femcal.measurements"):
        read_measurements(tmp_path / "close.csv", noise_deg=0.01)
    (warned,) = [r for r in caplog.records if "differ by" in r.getMessage()]
    assert "more than 0.05 deg (5 sd of the stated 0.01 deg noise)" in warned.getMessage()


def test_a_copied_row_is_warned_about(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = long_file(tmp_path, "S1,Flexion,1,1.0", "S1,Flexion,1.0,1.0")
    with caplog.at_level(logging.INFO, logger="femcal.measurements"):
        meas = read_measurements(path)
    assert meas.weight[0, 0, 0] == 2.0
    warned = [r for r in caplog.records if "repeat" in r.getMessage() and r.levelno >= 30]
    assert len(warned) == 1
    assert "lines 2 and 3 repeat a point with the same values" in warned[0].getMessage()
    assert "If one is a copy, delete it" in warned[0].getMessage()


@pytest.mark.parametrize(
    ("row", "match"),
    [
        ("S1,Twist,1,1", r"line 3, column 'load_case': unknown load case 'Twist'; " + LC_HELP),
        ("S1,,1,1", r"line 3, column 'load_case': an empty load case; " + LC_HELP),
        ("S1,Flexion,1,", r"line 3, column 'rom_deg': missing value \(''\); every row is one"),
        ("S1,Flexion,1,NaN", r"line 3, column 'rom_deg': missing value \('NaN'\)"),
        ("S1,Flexion,1,abc", r"line 3, column 'rom_deg': 'abc' is not a finite number"),
        ("S1,Flexion,1,inf", r"line 3, column 'rom_deg': 'inf' is not a finite number"),
        ("S1,Flexion,,1", r"line 3, column 'moment_nm': missing value"),
        ("S1,Flexion,1 Nm,1", r"line 3, column 'moment_nm': '1 Nm' is not a finite number"),
        (
            "S1,Flexion,1,-1.5",
            r"line 3, column 'rom_deg': negative RoM -1\.5\. RoM is a magnitude: give the "
            r"absolute value \(1\.5\)",
        ),
        ("S1,Flexion,0,1", r"line 3, column 'moment_nm': the moment must be positive; got 0\."),
        ("S1,Flexion,-2,1", r"column 'moment_nm': the moment must be positive; got -2\."),
        (",Flexion,2,1", r"line 3, column 'specimen': empty specimen name; name the specimen"),
        ("S1,Flexion,2,1,7", r"line 3: 5 cells but the header has 4 columns \(extra '7'\)"),
    ],
)
def test_long_row_errors(tmp_path: Path, row: str, match: str) -> None:
    path = long_file(tmp_path, "S1,Flexion,1,1.0", row)
    with pytest.raises(InputDataError, match=r"meas\.csv: 1 problem in the measurement file"):
        read_measurements(path)
    with pytest.raises(InputDataError, match=match):
        read_measurements(path)


@pytest.mark.parametrize(
    ("cells", "match"),
    [
        ("", r"line 2, column 'weight': missing value"),
        ("heavy", r"line 2, column 'weight': 'heavy' is not a finite number"),
        ("-1", r"line 2, column 'weight': negative weight -1; weights must be >= 0"),
        ("0", r"specimen 'S1' \(lines 2, 3\): all weights are 0, so it would not take part"),
    ],
)
def test_weight_errors(tmp_path: Path, cells: str, match: str) -> None:
    path = long_file(
        tmp_path,
        f"S1,Flexion,1,1,{cells}",
        "S1,Flexion,2,2,0",
        "S2,Flexion,1,1,1",
        header=HEADER + ",weight",
    )
    with pytest.raises(InputDataError, match=match):
        read_measurements(path)


@pytest.mark.parametrize(
    ("cell", "match"),
    [
        ("", r"line 2, column 'idp_mpa': missing value"),
        ("n/a", r"line 2, column 'idp_mpa': missing value \('n/a'\)"),
        ("high", r"line 2, column 'idp_mpa': 'high' is not a finite number"),
    ],
)
def test_idp_errors(tmp_path: Path, cell: str, match: str) -> None:
    path = long_file(tmp_path, f"S1,Flexion,1,1,{cell}", header=HEADER + ",idp_mpa")
    with pytest.raises(InputDataError, match=match):
        read_measurements(path)


def test_decimal_comma_hint(tmp_path: Path) -> None:
    path = write(tmp_path, "specimen;load_case;moment_nm;rom_deg\nS1;Flexion;1;1,5\n")
    with pytest.raises(InputDataError, match=r"'1,5' is not a finite number.*decimal point"):
        read_measurements(path)


def test_line_numbers_count_blank_lines_and_problems_are_listed(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "\n"
        + HEADER
        + "\n\nS1,Flexion,1,1\n"
        + "".join(f"S1,Flexion,{m},-1\n" for m in range(2, 9)),
    )
    with pytest.raises(InputDataError) as info:
        read_measurements(path)
    message = str(info.value)
    assert "7 problems in the measurement file" in message
    assert message.count("negative RoM") == 5 and "(and 2 more)" in message
    assert "line 5, column 'rom_deg'" in message  # header on line 2, blank line 3


def test_a_repeated_wide_row_is_a_repeated_curve(tmp_path: Path) -> None:
    path = write(tmp_path, "specimen,load_case,0,2,3\nS1,Flexion,,1,2\nS1,flexion,,3,\n")
    meas = read_measurements(path)
    np.testing.assert_allclose(meas.rom_deg[0, 0], [2.0, 2.0])  # (1 + 3) / 2, and 2 alone
    np.testing.assert_allclose(meas.weight[0, 0], [2.0, 1.0])


@pytest.mark.parametrize(
    ("rows", "match"),
    [
        (
            ["S1,Flexion,,x,1"],
            r"line 2, column '2': 'x' is not a finite number.*, or leave it empty",
        ),
        (["S1,Flexion,,1,-2"], r"line 2, column '3': negative RoM -2\. RoM is a magnitude"),
        (["S1,Flexion,0.1,1,2"], r"line 2, column '0': 0\.1 at 0 Nm; the unloaded state"),
        (["S1,Bend,,1,2"], r"line 2, column 'load_case': unknown load case 'Bend'"),
        ([",Flexion,,1,2"], r"line 2, column 'specimen': empty specimen name"),
        (
            ["S1,Flexion,,1,2", "S2,Flexion,,,", "S2,Extension,,,"],
            r"specimen 'S2' \(lines 3, 4\) has no measured value; fill in its values",
        ),
    ],
)
def test_wide_row_errors(tmp_path: Path, rows: list[str], match: str) -> None:
    path = write(tmp_path, "\n".join(["specimen,load_case,0,2,3", *rows]) + "\n")
    with pytest.raises(InputDataError, match=match):
        read_measurements(path)


# ------------------------------------------------------------------ from_arrays
def test_from_arrays_defaults_and_subset() -> None:
    rom = np.full((3, 4, 3), np.nan)
    rom[0, 0] = [1.0, 2.0, 3.0]
    rom[1, :, 0] = 0.5
    rom[2, 2, 2] = 4.0
    weight = np.full((3, 4, 3), 7.0)  # forced to 0 where not measured
    meas = from_arrays(["a", "b", "c"], [1, 2, 3], rom, weight=weight, source="lab")
    assert meas.n_specimens == 3 and meas.source == "lab"
    np.testing.assert_array_equal(meas.weight, np.where(meas.mask(), 7.0, 0.0))
    assert meas.missing_load_cases() == {
        "a": ["Extension", "LateralBending", "AxialRotation"],
        "c": ["Flexion", "Extension", "AxialRotation"],
    }
    default = from_arrays(["a", "b", "c"], [1, 2, 3], rom)
    np.testing.assert_array_equal(default.weight, meas.mask().astype(float))

    sub = meas.subset(["b", "c"])
    assert sub.specimens == ("b", "c")
    np.testing.assert_array_equal(sub.moments, [1.0, 3.0])  # 2 Nm only measured by "a"
    np.testing.assert_array_equal(sub.rom_deg, rom[[1, 2]][:, :, [0, 2]])
    with pytest.raises(InputDataError, match=r"lab: cannot select specimens: unknown .*\['x'\]"):
        meas.subset(["a", "x"])
    with pytest.raises(InputDataError, match=r"repeated specimens \['a'\]"):
        meas.subset(["a", "a"])
    long = meas.to_long()
    assert list(long.columns) == ["specimen", "load_case", "moment_nm", "rom_deg", "weight"]
    assert len(long) == int(meas.mask().sum())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"rom_deg": np.ones((2, 3, 3))}, r"rom_deg has shape \(2, 3, 3\); expected .*\(2, 4, 3\)"),
        ({"moments": [1.0, 3.0, 2.0]}, r"moments must be finite, positive .* strictly increasing"),
        ({"moments": [0.0, 1.0, 2.0]}, r"moments must be finite, positive"),
        ({"specimens": ["A", "A"]}, r"repeated specimen names \['A'\]"),
        ({"specimens": ["A", " "]}, r"specimen at position 1 has an empty name"),
        ({"specimens": ["A", 2]}, r"specimen names must be strings; got 2 \(int\)"),
        ({"rom_deg": -np.ones((2, 4, 3))}, r"rom_deg has negative values at specimen 'A'"),
        ({"weight": -np.ones((2, 4, 3))}, r"weight has negative values"),
        ({"weight": np.full((2, 4, 3), np.nan)}, r"weight is missing or infinite at measured"),
        ({"weight": np.zeros((2, 4, 3))}, r"all weights of specimens \['A', 'B'\] are 0"),
        ({"idp_mpa": np.full((2, 4, 3), np.nan)}, r"idp_mpa is missing or infinite"),
        ({"rom_deg": np.full((2, 4, 3), np.nan)}, r"specimens \['A', 'B'\] have no measured"),
        ({"rom_deg": [["x"]]}, r"rom_deg must be an array of numbers"),
    ],
)
def test_from_arrays_errors(kwargs: dict, match: str) -> None:
    args = {"specimens": ["A", "B"], "moments": [1.0, 2.0, 3.0], "rom_deg": np.ones((2, 4, 3))}
    args.update(kwargs)
    with pytest.raises(InputDataError, match=rf"^src: {match}"):
        from_arrays(
            args.pop("specimens"), args.pop("moments"), args.pop("rom_deg"), source="src", **args
        )


def test_data_rows_collects_rows_and_specimens(tmp_path: Path) -> None:
    from femcal.measurements.parse import DataRows

    records = [(2, ["a", "x"]), (3, []), (4, ["b", "y", "extra"]), (5, ["a"])]
    rows = DataRows(tmp_path / "m.csv", records, 2)
    assert list(rows) == [(2, ["a", "x"]), (5, ["a", ""])]  # empty skipped, short padded
    assert [line for line, _ in rows.problems.items] == [4]  # the row with an extra cell
    for specimen, line in [("b", 7), ("a", 8), ("b", 9)]:
        rows.add_row(specimen, line)
    assert rows.order == ["b", "a"]
    assert rows.rows_of == {"b": [7, 9], "a": [8]}


def test_data_rows_without_rows(tmp_path: Path) -> None:
    from femcal.measurements.parse import DataRows

    rows = DataRows(tmp_path / "m.csv", [(2, [])], 2)
    assert list(rows) == []
    with pytest.raises(InputDataError, match=r"m\.csv has a header \(line 1\) .* per thing\.$"):
        rows.measurements(1, one_row_per="thing", with_idp=False)


# ------------------------------------------------------------------- leaving points out
def _three_moments() -> object:
    rom = np.arange(2 * 4 * 3, dtype=float).reshape(2, 4, 3) + 1.0
    idp = rom / 10.0
    return from_arrays(["A", "B"], [0.25, 1.0, 2.0], rom, idp_mpa=idp, source="w.csv")


def test_without_drops_points_then_empty_moments_and_specimens() -> None:
    meas = _three_moments()
    drop = np.zeros((2, 4, 3), dtype=bool)
    drop[:, :, 0] = True  # every point at 0.25 Nm
    drop[1] = True  # all of B
    out = meas.without(drop)
    assert out.specimens == ("A",) and out.moments.tolist() == [1.0, 2.0]
    np.testing.assert_array_equal(out.rom_deg, meas.rom_deg[:1, :, 1:])
    np.testing.assert_array_equal(out.idp_mpa, meas.idp_mpa[:1, :, 1:])
    assert out.source == "w.csv"
    one = np.zeros((2, 4, 3), dtype=bool)
    one[0, 2, 1] = True  # one point: the grid stays, the point is not measured
    kept = meas.without(one)
    assert kept.moments.tolist() == [0.25, 1.0, 2.0] and np.isnan(kept.rom_deg[0, 2, 1])
    assert kept.weight[0, 2, 1] == 0.0 and int(kept.mask().sum()) == 23


def test_without_every_point_is_refused() -> None:
    with pytest.raises(
        InputDataError,
        match=r"^w\.csv: dropping those points leaves no measured point; keep at least one point",
    ):
        _three_moments().without(np.ones((2, 4, 3), dtype=bool))


def test_without_needs_one_flag_per_point() -> None:
    with pytest.raises(
        InputDataError,
        match=r"w\.csv: the points to drop have shape \(2, 4\); expected \(2, 4, 3\) .*one flag",
    ):
        _three_moments().without(np.zeros((2, 4), dtype=bool))
