"""Where the measurement noise comes from, said on every run of calibrate and diagnose.

``--noise-deg`` wins; else params.yaml's value (named with its file and key); else diagnose
estimates it from the disc-alone residuals, with its uncertainty. params.yaml's
``diagnose.noise_deg`` applied to another file than ``diagnose.measurements`` is warned about.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from femcal.cli import build_parser
from femcal.config import load_params
from femcal.diagnose.result import Diagnosis
from femcal.errors import ConfigError
from femcal.jobs.diagnose import ESTIMATED_NOISE
from femcal.stages.calibrate import CalibrateSettings, noise_line
from femcal.stages.diagnose import DiagnoseSettings, describe

ROOT = Path(__file__).resolve().parents[2]
LONG = "specimen,load_case,moment_nm,rom_deg\n" + "".join(
    f"s1,{lc},{m},{1.0 + m}\n"
    for lc in ("Flexion", "Extension", "LateralBending", "AxialRotation")
    for m in (1, 2, 3, 4, 5)
)


def _project(folder: Path, *, diagnose_noise: float | None) -> dict:
    """The project's params.yaml in ``folder`` (the planted cohort's noise, or none), its
    measurement files ``planted.csv`` and ``mine.csv``, loaded."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["diagnose"]["measurements"] = "planted.csv"
    params["diagnose"]["noise_deg"] = diagnose_noise
    params["calibrate"]["datasets"] = {
        "planted": {"measurements": "planted.csv", "effects": [], "noise_deg": 0.05}
    }
    (folder / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for name in ("planted.csv", "mine.csv"):
        (folder / name).write_text(LONG)
    return load_params(folder / "params.yaml")


def _args(folder: Path, **given) -> dict:
    return {"out": str(folder / "out"), **given}


def test_diagnose_names_params_yaml_and_its_key(tmp_path, caplog):
    params = _project(tmp_path, diagnose_noise=0.05)
    with caplog.at_level(logging.WARNING, logger="femcal.stages.diagnose"):
        s = DiagnoseSettings.from_params(params, _args(tmp_path))
    assert s.noise_deg == 0.05
    assert s.noise_source == f"diagnose.noise_deg in {(tmp_path / 'params.yaml').resolve()}"
    assert not caplog.records  # its own file: no warning


def test_diagnose_warns_when_params_yamls_noise_meets_another_file(tmp_path, caplog):
    params = _project(tmp_path, diagnose_noise=0.05)
    mine = tmp_path / "mine.csv"
    with caplog.at_level(logging.WARNING, logger="femcal.stages.diagnose"):
        s = DiagnoseSettings.from_params(params, _args(tmp_path, measurements=str(mine)))
    assert s.noise_deg == 0.05  # still used, and said
    (record,) = caplog.records
    assert record.levelno == logging.WARNING
    assert record.getMessage() == (
        f"The measurement noise 0.05 deg is diagnose.noise_deg in "
        f"{(tmp_path / 'params.yaml').resolve()}, stated for {tmp_path / 'planted.csv'}, not for "
        f"{mine}: give --noise-deg SD, the sd of one measurement of this file, or set "
        "diagnose.noise_deg: null to estimate it from the disc-alone residuals."
    )


def test_the_option_wins_without_a_warning(tmp_path, caplog):
    params = _project(tmp_path, diagnose_noise=0.05)
    args = _args(tmp_path, measurements=str(tmp_path / "mine.csv"), noise_deg=0.2)
    with caplog.at_level(logging.WARNING, logger="femcal.stages.diagnose"):
        s = DiagnoseSettings.from_params(params, args)
    assert (s.noise_deg, s.noise_source) == (0.2, "--noise-deg") and not caplog.records


def test_without_a_value_diagnose_estimates_it(tmp_path):
    s = DiagnoseSettings.from_params(_project(tmp_path, diagnose_noise=None), _args(tmp_path))
    assert s.noise_deg is None and s.noise_source == ESTIMATED_NOISE


@pytest.mark.parametrize("value", [-1.0, 0.0, float("nan")])
def test_a_noise_that_is_no_sd_is_refused_before_any_work(tmp_path, value):
    params = _project(tmp_path, diagnose_noise=None)
    with pytest.raises(ConfigError, match=r"--noise-deg: the measurement noise sd must be a "):
        DiagnoseSettings.from_params(params, _args(tmp_path, noise_deg=value))


def _printed(noise: float, noise_sd: float, source: str) -> list[str]:
    diag = Diagnosis(
        specimens=[],
        sigma_deg=noise,
        noise_deg=noise,
        noise_sd_deg=noise_sd,
        surrogate_error_deg=0.0,
        moments=np.array([1.0, 2.5, 5.0]),
        seconds=1.0,
    )
    figures = {
        "diagnosis": diag,
        "n_specimens": 0,
        "user_effects": [],
        "user_effect_paths": [],
        "noise_source": source,
    }
    return describe(figures)


def test_diagnose_prints_the_source_every_run():
    lines = _printed(0.05, 0.0, "diagnose.noise_deg in /p/params.yaml")
    assert "measurement noise 0.05 deg: diagnose.noise_deg in /p/params.yaml" in lines
    lines = _printed(0.0312, 0.0011, ESTIMATED_NOISE)
    (line,) = [x for x in lines if x.startswith("measurement noise")]
    assert line.startswith(
        "measurement noise 0.0312 ± 0.0011 deg, estimated from the disc-alone residuals (pooled"
    )


def test_calibrate_names_the_datasets_key_and_not_for_another_file(tmp_path):
    params = _project(tmp_path, diagnose_noise=None)
    s = CalibrateSettings.from_params(params, {"dataset": "planted"})
    where = (tmp_path / "params.yaml").resolve()
    assert (s.noise_deg, s.noise_source) == (
        0.05,
        f"calibrate.datasets.planted.noise_deg in {where}",
    )
    assert noise_line({"noise_deg": 0.05, "noise_source": s.noise_source}) == [
        f"measurement noise 0.05 deg: calibrate.datasets.planted.noise_deg in {where}"
    ]
    other = CalibrateSettings.from_params(
        params, {"measurements": str(tmp_path / "mine.csv"), "out": str(tmp_path / "o")}
    )
    assert other.noise_deg is None and noise_line({"noise_deg": None}) == []
    given = CalibrateSettings.from_params(params, {"dataset": "planted", "noise_deg": 0.1})
    assert (given.noise_deg, given.noise_source) == (0.1, "--noise-deg")


def test_the_help_says_where_the_default_comes_from(capsys):
    parser = build_parser()
    for command in ("diagnose", "calibrate"):
        with pytest.raises(SystemExit):
            parser.parse_args([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "(default: estimated)" not in text
        assert "the output names the source" in text
        if command == "diagnose":
            assert "default: diagnose.noise_deg in params.yaml when set, else estimated" in text
