"""Stage ``validate``: the figures it copies from the predict and adapt stages."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from femcal.errors import ConfigError, FemcalError
from femcal.fe.runtime import FeRuntime
from femcal.stages.validate import ValidateSettings, _read_report, honest_figures


def _settings(tmp_path: Path, targets: Path | None) -> ValidateSettings:
    return ValidateSettings(
        calibration_dir=tmp_path / "calibration",
        measurements=tmp_path / "data" / "Test",
        fe=FeRuntime(solver="calculix", settings={}, store=None),
        forces=(),
        literature={},
        out_dir=tmp_path / "out",
        target_noise_deg=0.0,
        adapt_targets=targets,
    )


SUMMARY = {"fe_runs_per_specimen_max": 5}
PREDICTIVE = {
    "fe_predictive_mae_deg": 0.04,
    "fe_predictive_mae_deg_noisy": 0.07,
    "clean": {"idp_mae_mpa": 0.01},
}


def test_adapt_rounds_at_the_validated_specimens_count_in_the_fe_runs(tmp_path):
    settings = _settings(tmp_path, tmp_path / "data" / "Test")
    out = honest_figures(SUMMARY, settings, PREDICTIVE, {"n_rounds": 3})
    assert out["fe_runs_per_specimen_max"] == 8
    assert out["fe_runs_per_specimen_max_validate"] == 5
    assert out["fe_runs_per_specimen_adapt"] == 3
    assert out["fe_predictive_mae_deg"] == 0.04 and out["fe_predictive_mae_deg_noisy"] == 0.07
    assert out["fe_predictive_idp_mae_mpa"] == 0.01 and out["target_noise_deg"] == 0.0


def test_adapt_rounds_at_other_targets_do_not_count(tmp_path):
    settings = _settings(tmp_path, tmp_path / "data" / "Other")
    out = honest_figures(SUMMARY, settings, None, {"n_rounds": 3})
    assert out["fe_runs_per_specimen_max"] == 5 and out["fe_runs_per_specimen_adapt"] == 0
    assert out["fe_predictive_mae_deg"] is None and out["fe_predictive"] is None


def test_a_missing_report_names_the_setting_and_the_fix(tmp_path):
    with pytest.raises(ConfigError, match=r"validate.predictive_report: .* does not exist") as e:
        _read_report(tmp_path / "predictive.json", "predictive_report")
    assert isinstance(e.value, FemcalError)
    bad = tmp_path / "adapt.json"
    bad.write_text("{")
    with pytest.raises(ConfigError, match=r"validate.adapt_report: .* is not valid JSON"):
        _read_report(bad, "adapt_report")
    bad.write_text(json.dumps({"n_rounds": 1}))
    assert _read_report(bad, "adapt_report") == {"n_rounds": 1}
