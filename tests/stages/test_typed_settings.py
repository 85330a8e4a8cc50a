"""The stages read params.yaml through the typed settings, each default declared once."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from femcal.config import load_params
from femcal.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
STAGES = ROOT / "src" / "femcal" / "stages"


def test_the_diagnosis_defaults_are_those_of_diagnose_options():
    from femcal.diagnose import DiagnoseOptions
    from femcal.settings import load_settings
    from femcal.settings.root import DiagnoseSettings

    for name in ("min_delta", "alpha", "max_effects", "seed"):
        assert DiagnoseSettings.model_fields[name].default == getattr(DiagnoseOptions, name)
    options = load_settings(ROOT / "params.yaml").diagnose.options()
    assert DiagnoseOptions(**options).min_delta == options["min_delta"]


def test_the_fe_defaults_are_those_of_the_fe_options():
    from femcal.fe.options import AdaptOptions, CampaignOptions, ValidateOptions
    from femcal.settings.fe import AdaptSettings, FeSettings, RefineSettings

    for section, options, names in (
        (AdaptSettings, AdaptOptions, ("rounds", "n_explore", "n_candidates", "seed")),
        (RefineSettings, ValidateOptions, ("max_fe_runs", "tol_deg")),
        (FeSettings, CampaignOptions, ("n_workers",)),
    ):
        for name in names:
            assert section.model_fields[name].default == getattr(options, name), name


def test_the_adapt_stage_passes_the_settings_as_adapt_options():
    from femcal.fe.options import AdaptOptions
    from femcal.settings.fe import AdaptSettings

    fields = {"model_uri": "models/m", "targets": "t", "train": "a", "heldout": "b"}
    fields |= {"out_model": "o", "out_dir": "d", "store": "s.jsonl", "n_explore": 4}
    section = AdaptSettings(**fields, finetune={"max_epochs": 2})
    options = AdaptOptions(**section.options())
    assert options == AdaptOptions(n_explore=4, finetune={"max_epochs": 2}, calibrate_options={})


def test_no_stage_reads_the_raw_mapping():
    for path in STAGES.glob("*.py"):
        text = path.read_text()
        assert "cfg.get(" not in text, path.name
        reads = re.findall(r"\bsection\(params", text)
        # common.moment_settings checks a mapping it is given (tests of the moment policy)
        assert not reads or path.name == "common.py", path.name


def test_a_partial_section_serves_the_keys_a_command_reads(tmp_path):
    from femcal.stages.common import typed

    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"mlflow": {"store_dir": "mlruns", "experiment": "e"}}))
    params = load_params(path)
    assert typed(params, "mlflow", "store_dir", "experiment").experiment == "e"
    with pytest.raises(ConfigError, match=r"p\.yaml: missing setting 'mlflow\.model_name'\."):
        _ = typed(params, "mlflow").model_name  # read where it is missing
    with pytest.raises(ConfigError, match=r"missing setting 'calibrate'\. Add it"):
        typed(params, "calibrate")
