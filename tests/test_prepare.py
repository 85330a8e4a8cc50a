"""Tests of femcal.prepare: raw study files -> tidy tables."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from femcal.errors import ConfigError, InputDataError
from femcal.prepare import SPLITS, prepare_dataset, read_split
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.space import ParameterSpace
from femcal.tidy import load_tidy, tidy_columns, to_wide, wide_rom

N = 5  # configurations in the default synthetic split
ROM_FLEX = "ROM_Results_Flexion_wMoment.csv"
IDP_FLEX = "IDP_Results_Flexion_wMoment.csv"
CONFIG = "MaterialConfigurations.csv"


def _lines(path: Path) -> tuple[list[str], str]:
    raw = path.read_bytes().decode()
    newline = "\r\n" if "\r\n" in raw else "\n"
    return raw.split(newline)[:-1], newline


def set_row(path: Path, row: int, text: str) -> None:
    """Replace data row ``row`` (0-based, below the header) of a CSV file."""
    lines, newline = _lines(path)
    lines[row + 1] = text
    path.write_bytes("".join(line + newline for line in lines).encode())


def set_cell(path: Path, row: int, col: int, text: str) -> None:
    """Replace one cell of data row ``row`` (0-based) of a CSV file."""
    lines, _ = _lines(path)
    cells = lines[row + 1].split(",")
    cells[col] = text
    set_row(path, row, ",".join(cells))


def set_header(path: Path, text: str) -> None:
    set_row(path, -1, text)


def raw_values(path: Path) -> np.ndarray:
    return pd.read_csv(path, float_precision="round_trip").to_numpy()


@pytest.fixture
def large(synthetic_study: Callable[..., Path]) -> Path:
    """A synthetic Large split folder with N configurations."""
    return synthetic_study("large", n_configs=N, seed=1)


# --------------------------------------------------------------------- layout
def test_split_layout() -> None:
    assert set(SPLITS) == {"large", "small", "test"}
    assert SPLITS["large"].configurations == "MaterialConfigurations.csv"
    assert SPLITS["small"].configurations == "MaterialConfigurations_Small_128.csv"
    assert SPLITS["test"].configurations == "MaterialConfigurations_TestData_64.csv"
    assert SPLITS["large"].results("ROM", "Flexion") == ROM_FLEX
    assert (
        SPLITS["small"].results("IDP", "AxialRotation")
        == "IDP_Results_AxialRotation_Small_128_wMoment.csv"
    )
    assert (
        SPLITS["test"].results("ROM", "LateralBending")
        == "ROM_Results_LateralBending_TestData_64_wMoment.csv"
    )
    assert [SPLITS[s].folder for s in ("large", "small", "test")] == ["Large", "Small", "Test"]
    assert all(len(layout.relpaths()) == 10 for layout in SPLITS.values())


# ------------------------------------------------------------------ read_split
@pytest.mark.parametrize("split", ["large", "small", "test"])
def test_read_split_tidy_layout(synthetic_study: Callable[..., Path], split: str) -> None:
    folder = synthetic_study(split, n_configs=4, seed=7)
    df = read_split(folder.parent, split)
    space = ParameterSpace.from_bounds_csv(folder / "ParameterBounds.csv")
    assert list(df.columns) == tidy_columns(space)
    assert list(df.columns[3:16]) == list(PARAMETER_NAMES)
    assert len(df) == 4 * 4 * 5
    assert df["config_id"].dtype == np.int64
    for col in ("moment_nm", "rom_deg", "idp_mpa", *PARAMETER_NAMES):
        assert df[col].dtype == np.float64
    assert (df["status"] == "ok").all()
    # order: configuration, then load case in LOAD_CASES order, then moment
    assert df["config_id"].tolist() == list(np.repeat(np.arange(4), 20))
    assert df["load_case"].tolist()[:20] == list(np.repeat(LOAD_CASES, 5))
    assert df["moment_nm"].tolist()[:5] == [1.0, 2.0, 3.0, 4.0, 5.0]
    # values are the published numbers, exactly
    layout = SPLITS[split]
    config = raw_values(folder / layout.configurations)
    np.testing.assert_array_equal(df[list(PARAMETER_NAMES)].to_numpy()[::20], config)
    for k, lc in enumerate(LOAD_CASES):
        for quantity, col in (("ROM", "rom_deg"), ("IDP", "idp_mpa")):
            raw = raw_values(folder / layout.results(quantity, lc))[:, 1:]
            got = df.loc[df["load_case"] == lc, col].to_numpy().reshape(4, 5)
            np.testing.assert_array_equal(got, raw, err_msg=f"{quantity} {lc} (k={k})")


def test_read_split_given_space_and_unknown_split(large: Path) -> None:
    space = ParameterSpace.from_bounds_csv(large / "ParameterBounds.csv")
    pd.testing.assert_frame_equal(
        read_split(large.parent, "Large", space), read_split(large.parent, "large")
    )
    with pytest.raises(ConfigError, match=r"Unknown split 'medium'"):
        read_split(large.parent, "medium")


def test_negative_idp_is_data(large: Path) -> None:
    set_row(large / "IDP_Results_Extension_wMoment.csv", 0, "0,0.01,0.0,-0.02,-0.05,-0.1")
    df = read_split(large.parent, "large")
    rows = df[(df["config_id"] == 0) & (df["load_case"] == "Extension")]
    assert rows["idp_mpa"].tolist() == [0.01, 0.0, -0.02, -0.05, -0.1]
    assert (rows["status"] == "ok").all()


# ------------------------------------------------------------- failed tails
@pytest.mark.parametrize(
    ("row_text", "n_ok"),
    [
        ("0,1.2,2.3,0,0,0", 2),
        ("0,1.2,2.3,3.1,4.0,", 4),
        ("0,1.2,2.3,nan,NaN,", 2),
        ("0,1.2,2.3,0,,0", 2),
        ("0,1.2", 1),  # short row: the rest is missing
        ("0,0,0,0,0,0", 0),
        (",,,,,", 0),
        ("", 0),  # blank line in the middle of the file
    ],
)
def test_failed_tail(
    large: Path, caplog: pytest.LogCaptureFixture, row_text: str, n_ok: int
) -> None:
    set_row(large / ROM_FLEX, 2, row_text)
    with caplog.at_level(logging.WARNING, logger="femcal.prepare"):
        df = read_split(large.parent, "large")
    assert len(df) == N * 20
    rows = df[(df["config_id"] == 2) & (df["load_case"] == "Flexion")]
    assert rows["status"].tolist() == ["ok"] * n_ok + ["failed"] * (5 - n_ok)
    failed = rows[rows["status"] == "failed"]
    assert failed["rom_deg"].isna().all() and failed["idp_mpa"].isna().all()
    assert rows["rom_deg"].iloc[:n_ok].gt(0).all()
    assert rows["idp_mpa"].iloc[:n_ok].notna().all()
    # every other row is untouched and ok
    assert (df.drop(rows.index)["status"] == "ok").all()
    assert f"{5 - n_ok} of {N * 20} rows failed" in caplog.text


def test_failed_last_configuration(large: Path) -> None:
    set_row(large / ROM_FLEX, N - 1, ",,,,,")
    df = read_split(large.parent, "large")
    assert len(df) == N * 20
    assert (df[df["status"] == "failed"]["config_id"] == N - 1).all()
    assert (df["status"] == "failed").sum() == 5


def test_idp_tail_missing_keeps_status(large: Path) -> None:
    set_row(large / IDP_FLEX, 1, "0,0.05,0.1,0,0,0")
    df = read_split(large.parent, "large")
    rows = df[(df["config_id"] == 1) & (df["load_case"] == "Flexion")]
    assert (rows["status"] == "ok").all()
    assert rows["rom_deg"].notna().all()
    assert rows["idp_mpa"].isna().tolist() == [False, False, True, True, True]


def test_trailing_blank_lines_are_ignored(large: Path) -> None:
    for name in (ROM_FLEX, CONFIG):
        with open(large / name, "ab") as fh:
            fh.write(b"\r\n\r\n")
    assert (read_split(large.parent, "large")["status"] == "ok").all()


# --------------------------------------------------------------------- errors
def test_error_missing_result_file(large: Path) -> None:
    (large / IDP_FLEX).unlink()
    with pytest.raises(InputDataError, match=rf"{IDP_FLEX} does not exist; run the 'fetch'"):
        read_split(large.parent, "large")


def test_error_missing_configuration_file(large: Path) -> None:
    (large / CONFIG).unlink()
    with pytest.raises(InputDataError, match=rf"{CONFIG} does not exist"):
        read_split(large.parent, "large")


@pytest.mark.parametrize("text", ["", "nan", "NaN"])
def test_error_missing_parameter(large: Path, text: str) -> None:
    set_cell(large / CONFIG, 3, 4, text)
    with pytest.raises(
        InputDataError,
        match=rf"{CONFIG}: missing \(empty or NaN\) parameter values at column 'K2Annulus', "
        r"row 3 \(line 5\).*fill them in",
    ):
        read_split(large.parent, "large")


@pytest.mark.parametrize("text", ["abc", "1.2.3", "inf"])
def test_error_non_numeric_parameter(large: Path, text: str) -> None:
    set_cell(large / CONFIG, 0, 0, text)
    with pytest.raises(
        InputDataError,
        match=rf"{CONFIG}: parameter values must be finite numbers; .*column 'C10Nucleus', "
        rf"row 0 \(line 2\): '{text}'.*Replace them",
    ):
        read_split(large.parent, "large")


def test_error_parameter_out_of_bounds(large: Path) -> None:
    set_cell(large / CONFIG, 2, 10, "60.5")
    with pytest.raises(
        InputDataError,
        match=rf"{CONFIG}: parameter values outside the bounds of .*ParameterBounds\.csv: "
        r"column 'FiberAngle', row 2 \(line 4\): 60\.5 not in \[7\.5, 52\.5\]",
    ):
        read_split(large.parent, "large")


def test_error_unknown_and_missing_columns(large: Path) -> None:
    header = ",".join(PARAMETER_NAMES).replace("Kappa", "Kapa")
    set_header(large / CONFIG, header)
    with pytest.raises(
        InputDataError,
        match=r"do not match the bounds file .*ParameterBounds\.csv\. Unknown columns \(not in "
        r"the bounds file\): \['Kapa'\]; missing columns \(in the bounds file, not here\): "
        r"\['Kappa'\]",
    ):
        read_split(large.parent, "large")


def test_columns_matched_by_name(large: Path) -> None:
    """A configuration file with reordered columns is read by name."""
    path = large / CONFIG
    table = pd.read_csv(path, float_precision="round_trip")
    before = read_split(large.parent, "large")
    table[list(reversed(table.columns))].to_csv(path, index=False)
    pd.testing.assert_frame_equal(read_split(large.parent, "large"), before)


def test_error_row_count_mismatch(large: Path) -> None:
    lines, newline = _lines(large / ROM_FLEX)
    (large / ROM_FLEX).write_bytes("".join(x + newline for x in lines[:-1]).encode())
    with pytest.raises(
        InputDataError,
        match=rf"{ROM_FLEX} has {N - 1} rows but the configuration file .*{CONFIG} has {N}",
    ):
        read_split(large.parent, "large")


def test_error_extra_result_row(large: Path) -> None:
    with open(large / ROM_FLEX, "ab") as fh:
        fh.write(b"0,1,2,3,4,5\r\n")
    with pytest.raises(InputDataError, match=rf"has {N + 1} rows but .* has {N}"):
        read_split(large.parent, "large")


@pytest.mark.parametrize(
    ("header", "match"),
    [
        ("a,b,c,d,e,f", r"header must list the applied moments in Nm as numbers"),
        ("0,1,2,2,4,5", r"header must be strictly increasing moments starting at 0 Nm"),
        ("1,2,3,4,5,6", r"header must be strictly increasing moments starting at 0 Nm"),
    ],
)
def test_error_result_header(large: Path, header: str, match: str) -> None:
    set_header(large / ROM_FLEX, header)
    with pytest.raises(InputDataError, match=rf"{ROM_FLEX}: the {match}"):
        read_split(large.parent, "large")


def test_error_moments_differ_between_files(large: Path) -> None:
    set_header(large / IDP_FLEX, "0,1,2,3,4,6")
    with pytest.raises(InputDataError, match=rf"{IDP_FLEX}: moments .* differ from .*{ROM_FLEX}"):
        read_split(large.parent, "large")


def test_error_unloaded_column_not_zero(large: Path) -> None:
    set_cell(large / ROM_FLEX, 1, 0, "0.5")
    with pytest.raises(
        InputDataError,
        match=rf"{ROM_FLEX}: column '0' \(the unloaded 0 Nm state\) must be 0 .*row 1 "
        r"\(line 3\): 0\.5",
    ):
        read_split(large.parent, "large")


@pytest.mark.parametrize(
    ("row_text", "match"),
    [
        ("0,1.2,-2.3,3,4,5", r"row 2 \(line 4\), column '2': -2\.3"),
        ("0,1.2,0,3,4,5", r"row 2 \(line 4\), column '2': 0\.0"),
        ("0,0,0,0,0,5", r"row 2 \(line 4\), column '1': 0\.0"),
    ],
)
def test_error_non_positive_rom(large: Path, row_text: str, match: str) -> None:
    set_row(large / ROM_FLEX, 2, row_text)
    with pytest.raises(
        InputDataError, match=rf"{ROM_FLEX}: RoM must be positive; non-positive .*{match}"
    ):
        read_split(large.parent, "large")


@pytest.mark.parametrize("name", [ROM_FLEX, IDP_FLEX])
def test_error_gap_before_values(large: Path, name: str) -> None:
    set_row(large / name, 0, "0,1.2,,3,4,5")
    with pytest.raises(
        InputDataError,
        match=rf"{name}: missing (RoM|IDP) values followed by values at later moments, at "
        r"row 0 \(line 2\), column '2'",
    ):
        read_split(large.parent, "large")


def test_error_non_numeric_result(large: Path) -> None:
    set_cell(large / ROM_FLEX, 4, 3, "3,1")  # a decimal comma splits the row
    with pytest.raises(InputDataError, match=rf"{ROM_FLEX} is not a readable CSV table"):
        read_split(large.parent, "large")
    set_row(large / ROM_FLEX, 4, "0,1,2,x,4,5")
    with pytest.raises(
        InputDataError, match=rf"{ROM_FLEX}: results must be finite .*column '3', row 4.*'x'"
    ):
        read_split(large.parent, "large")


def test_error_inverted_bounds(large: Path) -> None:
    set_cell(large / "ParameterBounds.csv", 0, 5, "0.5")  # Kappa min 0.5 > max 0.33
    with pytest.raises(
        InputDataError, match=r"ParameterBounds\.csv: Inverted or empty bounds for Kappa"
    ):
        read_split(large.parent, "large")


# ------------------------------------------------------------ prepare_dataset
def test_prepare_dataset_round_trip(synthetic_raw_root: Path, tmp_path: Path) -> None:
    root = synthetic_raw_root
    set_row(root / "Small" / "ROM_Results_Extension_Small_128_wMoment.csv", 1, "0.0,2.5,0,0,0,0")
    set_row(root / "Small" / "IDP_Results_Flexion_Small_128_wMoment.csv", 0, "0.0,0.1,,,,")
    out = tmp_path / "prepared"
    written = prepare_dataset(root, out)
    assert written == {
        "large": out / "large.csv",
        "small": out / "small.csv",
        "test": out / "test.csv",
        "parameter_space": out / "parameter_space.json",
    }
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in written.values())
    space = ParameterSpace.from_json(written["parameter_space"])
    assert space == ParameterSpace.from_bounds_csv(root / "Large" / "ParameterBounds.csv")
    for split, n in (("large", 6), ("small", 4), ("test", 3)):
        expected = read_split(root, split, space)
        got = load_tidy(written[split], space)
        assert len(got) == n * 20
        pd.testing.assert_frame_equal(got, expected, check_exact=True)
    small = load_tidy(written["small"], space)
    assert (small["status"] == "failed").sum() == 4
    assert small["idp_mpa"].isna().sum() == 4 + 4


def test_prepare_dataset_bounds_differ(synthetic_raw_root: Path, tmp_path: Path) -> None:
    set_cell(synthetic_raw_root / "Test" / "ParameterBounds.csv", 1, 0, "0.25")
    with pytest.raises(
        InputDataError,
        match=r"Test/ParameterBounds\.csv differs from .*Large/ParameterBounds\.csv.*upper "
        r"\[0\.25,.* vs \[0\.21",
    ):
        prepare_dataset(synthetic_raw_root, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_prepare_dataset_subset_and_failure_leaves_no_output(
    synthetic_raw_root: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    written = prepare_dataset(synthetic_raw_root, out, splits=("test",))
    assert set(written) == {"test", "parameter_space"}
    (synthetic_raw_root / "Small" / "MaterialConfigurations_Small_128.csv").unlink()
    with pytest.raises(InputDataError, match="MaterialConfigurations_Small_128.csv does not"):
        prepare_dataset(synthetic_raw_root, out)
    assert sorted(p.name for p in out.iterdir()) == ["parameter_space.json", "test.csv"]


# ------------------------------------------------------------------ load_tidy
@pytest.fixture
def prepared(large: Path, tmp_path: Path) -> tuple[Path, ParameterSpace]:
    written = prepare_dataset(large.parent, tmp_path / "out", splits=("large",))
    return written["large"], ParameterSpace.from_json(written["parameter_space"])


def test_load_tidy_missing_file(tmp_path: Path) -> None:
    space = ParameterSpace(["a"], [0], [1])
    with pytest.raises(InputDataError, match=r"large\.csv does not exist; run `dvc repro prepare`"):
        load_tidy(tmp_path / "large.csv", space)


def test_load_tidy_missing_columns(prepared: tuple[Path, ParameterSpace]) -> None:
    path, space = prepared
    pd.read_csv(path).drop(columns=["Kappa", "status"]).to_csv(path, index=False)
    with pytest.raises(
        InputDataError,
        match=r"large\.csv: missing columns \['Kappa', 'status'\]; unknown columns none.*"
        r"run `dvc repro prepare`",
    ):
        load_tidy(path, space)


def test_load_tidy_unknown_columns(prepared: tuple[Path, ParameterSpace]) -> None:
    path, space = prepared
    pd.read_csv(path).rename(columns={"rom_deg": "rom"}).to_csv(path, index=False)
    with pytest.raises(
        InputDataError, match=r"missing columns \['rom_deg'\]; unknown columns \['rom'\]"
    ):
        load_tidy(path, space)


@pytest.mark.parametrize(
    ("column", "value", "match"),
    [
        ("status", "maybe", r"column 'status' has unknown values \['maybe'\]"),
        ("load_case", "Twist", r"column 'load_case' has unknown values \['Twist'\]"),
        ("config_id", 0.5, r"column 'config_id' must hold integers"),
        ("rom_deg", "abc", r"column 'rom_deg' must be numeric"),
        ("rom_deg", np.nan, r"column 'rom_deg' is missing in rows with status 'ok'"),
        ("Kappa", np.nan, r"column 'Kappa' has missing or infinite values"),
        ("Kappa", 9.0, r"parameter values outside the bounds .* rows \[3\]"),
    ],
)
def test_load_tidy_bad_values(
    prepared: tuple[Path, ParameterSpace], column: str, value: object, match: str
) -> None:
    path, space = prepared
    df = pd.read_csv(path, float_precision="round_trip")
    df[column] = df[column].astype(object)
    df.loc[3, column] = value
    df.to_csv(path, index=False)
    with pytest.raises(InputDataError, match=rf"large\.csv: {match}.*dvc repro prepare"):
        load_tidy(path, space)


def test_load_tidy_wrong_space(prepared: tuple[Path, ParameterSpace]) -> None:
    path, space = prepared
    other = ParameterSpace(list(space.names)[:-1], space.lower[:-1], space.upper[:-1])
    with pytest.raises(InputDataError, match=r"unknown columns \['FiberAngleRad'\]"):
        load_tidy(path, other)


# ---------------------------------------------------------------------- wide
def test_wide_rom(large: Path) -> None:
    set_row(large / ROM_FLEX, 1, "0,1.5,0,0,0,0")
    df = read_split(large.parent, "large")
    ids, moments, values = wide_rom(df)
    np.testing.assert_array_equal(ids, np.arange(N))
    np.testing.assert_array_equal(moments, [1.0, 2.0, 3.0, 4.0, 5.0])
    assert values.shape == (N, 4, 5)
    np.testing.assert_array_equal(values.reshape(-1), df["rom_deg"].to_numpy())
    assert np.isnan(values[1, 0, 1:]).all() and values[1, 0, 0] == 1.5
    _, _, idp = to_wide(df.sample(frac=1.0, random_state=0), value="idp_mpa")
    np.testing.assert_array_equal(idp.reshape(-1), df["idp_mpa"].to_numpy())
    ids2, _, sub = wide_rom(df[df["config_id"].isin([3, 1])])
    np.testing.assert_array_equal(ids2, [1, 3])
    np.testing.assert_array_equal(sub, values[[1, 3]])


def test_wide_incomplete_grid(large: Path) -> None:
    df = read_split(large.parent, "large")
    with pytest.raises(InputDataError, match=r"not a complete .* grid: 1 combinations missing"):
        wide_rom(df.drop(index=7))
    with pytest.raises(InputDataError, match=r"0 combinations missing, 1 repeated"):
        wide_rom(pd.concat([df, df.iloc[[0]]]))


# ------------------------------------------------------------ the real mirror
def test_real_mirror_large(tmp_path: Path) -> None:
    import os

    from femcal.fetch import mirror_from_env

    mirror = mirror_from_env(os.environ)
    if mirror is None:
        pytest.skip("FEMCAL_DATA_MIRROR is not set")
    df = read_split(mirror, "large")
    assert len(df) == 1024 * 20
    assert (df["status"] == "ok").all()
    assert df["rom_deg"].gt(0).all() and df["idp_mpa"].notna().all()
    written = prepare_dataset(mirror, tmp_path / "out")  # CRLF (Large) vs LF (Test) bounds
    assert (
        len(load_tidy(written["test"], ParameterSpace.from_json(written["parameter_space"])))
        == 64 * 20
    )


def test_prepare_dataset_limit_configs(synthetic_raw_root: Path, tmp_path: Path) -> None:
    written = prepare_dataset(synthetic_raw_root, tmp_path / "out", limit_configs=2)
    space = ParameterSpace.from_json(written["parameter_space"])
    large = load_tidy(written["large"], space)
    assert sorted(large["config_id"].unique()) == [0, 1]
    assert len(large) == 2 * 4 * 5


def test_prepare_dataset_limit_configs_error(synthetic_raw_root: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="limit_configs must be a positive number"):
        prepare_dataset(synthetic_raw_root, tmp_path / "out", limit_configs=0)
