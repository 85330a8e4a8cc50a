"""The command line: settings errors are clear, and exit with status 2."""

import pytest
import yaml

from femcal.cli import build_parser, main
from femcal.config import load_params, section
from femcal.errors import ConfigError


def test_missing_params_file(tmp_path, capsys):
    assert main(["--params", str(tmp_path / "nope.yaml"), "prepare"]) == 2
    err = capsys.readouterr().err
    assert "nope.yaml does not exist; run from the project root or pass --params" in err


def test_missing_setting_names_key_and_file(tmp_path, capsys):
    p = tmp_path / "params.yaml"
    p.write_text("data: {raw_dir: raw}\n")
    assert main(["--params", str(p), "prepare"]) == 2
    assert "missing setting 'data.prepared_dir'" in capsys.readouterr().err


def test_invalid_yaml(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("data: [unclosed\n")
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load_params(p)


def test_non_mapping_yaml(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="must hold a mapping of sections; got list"):
        load_params(p)


def test_section_lookup(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("train: {large: {n_trials: 3}}\n")
    params = load_params(p)
    assert section(params, "train", "large", "n_trials") == 3
    with pytest.raises(ConfigError, match="missing setting 'train.small'"):
        section(params, "train", "small", "n_trials")


def test_subcommands_exist():
    parser = build_parser()
    for cmd in (
        ["fetch"],
        ["prepare"],
        ["train", "--split", "large"],
        ["baselines", "--split", "small"],
        ["interpolate"],
        ["evaluate"],
        ["train-inverse"],
        ["calibrate", "--measurements", "m.csv", "--method", "ga", "--model-version", "2"],
    ):
        assert parser.parse_args(cmd).command == cmd[0]
    with pytest.raises(SystemExit):
        parser.parse_args(["train"])  # --split is required


def test_unknown_training_section_names_the_setting(tmp_path, capsys, monkeypatch):
    import mlflow

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    params = {
        "mlflow": {"store_dir": str(tmp_path / "mlruns"), "experiment": "t"},
        "train": {"storage": f"sqlite:///{tmp_path}/o.db"},
    }
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(params))
    try:
        code = main(["--params", str(tmp_path / "p.yaml"), "train", "--split", "medium"])
    finally:
        mlflow.set_tracking_uri(None)  # the command pointed MLflow at the temporary store
    assert code == 2
    assert "missing setting 'train.medium'" in capsys.readouterr().err


def test_fetch_and_prepare_from_a_mirror(tmp_path, monkeypatch, capsys, synthetic_raw_root):
    """fetch refuses a mirror whose files are not the study's (checksums), naming the fix."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("FEMCAL_DATA_MIRROR", str(synthetic_raw_root))
    (tmp_path / "params.yaml").write_text(
        "data: {raw_dir: data/raw, prepared_dir: data/prepared}\n"
    )
    assert main(["fetch"]) == 2
    err = capsys.readouterr().err
    assert "SHA-256" in err
    assert not (tmp_path / "data" / "raw" / "Large" / "MaterialConfigurations.csv").exists()
