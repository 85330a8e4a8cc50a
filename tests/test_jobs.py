"""The library's jobs read params.yaml as the stages do, and the stages add only their own.

:meth:`CalibrationJob.from_params` and :meth:`DiagnosisJob.from_params` fill a job from a
loaded params.yaml, the caller's keywords winning; ``femcal calibrate`` and ``femcal
diagnose`` build the same job from the same file (their settings are a job plus the stage's
own fields). The runs themselves are tested in tests/calibration/test_stage.py and
tests/stages/test_moment_policy_stages.py.
"""

from __future__ import annotations

import sys
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from femcal.config import load_params
from femcal.errors import ConfigError
from femcal.jobs.calibrate import CalibrationJob
from femcal.jobs.diagnose import ESTIMATED_NOISE, DiagnosisJob
from femcal.stages.calibrate import CalibrateSettings
from femcal.stages.common import STAGE_ONLY
from femcal.stages.diagnose import DiagnoseSettings

ROOT = Path(__file__).resolve().parents[1]
LONG = "specimen,load_case,moment_nm,rom_deg\n" + "".join(
    f"s1,{lc},{m},{1.0 + m}\n"
    for lc in ("Flexion", "Extension", "LateralBending", "AxialRotation")
    for m in (1, 2, 3, 4, 5)
)


@pytest.fixture
def params(tmp_path: Path) -> dict:
    """The project's params.yaml in ``tmp_path`` with one measurement file, loaded."""
    data = yaml.safe_load((ROOT / "params.yaml").read_text())
    data["diagnose"]["measurements"] = "meas.csv"
    data["calibrate"]["datasets"] = {"mine": {"measurements": "meas.csv", "effects": []}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    (tmp_path / "meas.csv").write_text(LONG)
    return load_params(tmp_path / "params.yaml")


def _job_fields(settings, job_type) -> dict:
    return {f.name: getattr(settings, f.name) for f in fields(job_type)}


def test_the_calibration_job_reads_params_and_the_caller_wins(params, tmp_path):
    job = CalibrationJob.from_params(params, measurements=tmp_path / "meas.csv", out_dir=tmp_path)
    assert job.method == params["calibrate"]["method"]
    # relative folders are under params.yaml's folder
    assert job.model_uri == str(tmp_path / params["calibrate"]["model_uri"])
    growth = params["moments"]["error_growth"]
    assert job.error_growth == (growth["below"], growth["above"])
    assert job.effects == () and job.noise_deg is None and job.holdout_uri is not None
    mine = CalibrationJob.from_params(
        params,
        measurements=tmp_path / "meas.csv",
        out_dir=tmp_path,
        holdout_uri=None,
        effects=("facet_contact:split",),
        seed=7,
    )
    assert (mine.holdout_uri, mine.effects, mine.seed) == (None, ("facet_contact:split",), 7)


def test_femcal_calibrate_builds_the_same_job(params, tmp_path):
    settings = CalibrateSettings.from_params(params, {"dataset": "mine", "plots": "none"})
    job = CalibrationJob.from_params(
        params,
        measurements=tmp_path / "meas.csv",
        out_dir=tmp_path / params["calibrate"]["out_dir"] / "mine",
        plots="none",
    )
    assert _job_fields(settings, CalibrationJob) == _job_fields(job, CalibrationJob)
    own = {f.name for f in fields(CalibrateSettings)} - {f.name for f in fields(CalibrationJob)}
    assert own == set(STAGE_ONLY)


def test_the_diagnosis_job_reads_params_and_the_caller_wins(params, tmp_path):
    job = DiagnosisJob.from_params(params, out_dir=tmp_path / "d")
    assert job.measurements == tmp_path / "meas.csv"
    assert job.noise_deg == params["diagnose"]["noise_deg"]
    assert job.noise_source.startswith("diagnose.noise_deg in ")
    assert job.options["max_effects"] == params["diagnose"]["max_effects"]
    given = DiagnosisJob.from_params(params, out_dir=tmp_path / "d", noise_deg=0.1)
    assert (given.noise_deg, given.noise_source) == (0.1, "given by the caller")
    data = yaml.safe_load(Path(params["_path"]).read_text())
    data["diagnose"]["noise_deg"] = None
    Path(params["_path"]).write_text(yaml.safe_dump(data, sort_keys=False))
    estimated = DiagnosisJob.from_params(load_params(params["_path"]), out_dir=tmp_path / "d")
    assert estimated.noise_source == ESTIMATED_NOISE


def test_femcal_diagnose_builds_the_same_job(params, tmp_path):
    settings = DiagnoseSettings.from_params(params, {"out": str(tmp_path / "d")})
    job = DiagnosisJob.from_params(params, out_dir=tmp_path / "d")
    assert _job_fields(settings, DiagnosisJob) == _job_fields(job, DiagnosisJob)
    own = {f.name for f in fields(DiagnoseSettings)} - {f.name for f in fields(DiagnosisJob)}
    assert own == set(STAGE_ONLY)


def test_a_keyword_that_is_not_a_field_is_named(params, tmp_path):
    with pytest.raises(ConfigError, match=r"noise is not a field of DiagnosisJob; its fields"):
        DiagnosisJob.from_params(params, out_dir=tmp_path, noise=0.1)
    with pytest.raises(ConfigError, match=r"effect is not a field of CalibrationJob"):
        CalibrationJob.from_params(params, measurements=tmp_path, out_dir=tmp_path, effect=())


def test_importing_the_jobs_is_light():
    """The stages import the jobs before MLflow's child process forks: nothing heavy yet."""
    import subprocess

    code = (
        "import sys, femcal.jobs.calibrate, femcal.jobs.diagnose\n"
        "print(sorted(m for m in ('torch', 'mlflow', 'femcal.calibration', 'femcal.diagnose')"
        " if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"
