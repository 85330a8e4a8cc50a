"""Validated settings: params.yaml, fe/params.yaml and the environment variables femcal reads.

Every error path names the file, the line, the dotted key, what was given and the fix; the
static keyword tables of :mod:`femcal.settings` match the real signatures they describe.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import get_args

import pytest
import yaml
from pydantic import BaseModel

from femcal.config import load_params, section
from femcal.errors import ConfigError
from femcal.settings import (
    CALIBRATOR_OPTIONS,
    InverseKeywords,
    Settings,
    SurrogateKeywords,
    check_environment,
    describe_setting,
    detect_schema,
    load_settings,
    validate_params,
)

ROOT = Path(__file__).resolve().parents[1]
ROOT_TEXT = (ROOT / "params.yaml").read_text()
FE_TEXT = (ROOT / "fe" / "params.yaml").read_text()


def edited(tmp_path: Path, *edits: tuple[str, str], fe: bool = False) -> Path:
    """A copy of the project's params file with each ``(old, new)`` text replaced once."""
    text = FE_TEXT if fe else ROOT_TEXT
    for old, new in edits:
        assert old in text, f"{old!r} is not in the project's params file"
        text = text.replace(old, new, 1)
    path = tmp_path / "params.yaml"
    path.write_text(text)
    return path


def line_of(path: Path, needle: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if needle in line)


# ------------------------------------------------------------------ the project's own files
@pytest.mark.parametrize("name", ["params.yaml", "fe/params.yaml"])
def test_the_project_params_validate_completely(name):
    settings = load_settings(ROOT / name)
    assert isinstance(settings, Settings)
    assert settings.schema == ("fe" if name.startswith("fe/") else "root")
    assert settings.calibrate.method == "pgd"
    assert settings.calibrate.options["pgd"]["n_starts"] == 8
    assert settings.moments.max_log_ratio.above == pytest.approx(0.51)
    assert settings.train.splits["large"].fixed["activation"] == "gelu"
    assert isinstance(settings.train, BaseModel) and settings.data.raw_dir


def test_typed_sections_of_each_file():
    root = load_settings(ROOT / "params.yaml")
    assert root.fe is None and root.validate is None
    assert root.train.splits["holdout"].split == "large"
    assert root.calibrate.datasets["planted"].effects == (
        "neutral_zone",
        "facet_contact",
        "ligament_tension",
    )
    assert root.calibrate.datasets["test"].measurements == "data/raw/Test"
    assert root.train.splits["large"].search_space["learning_rate"]["log"] is True
    fe = load_settings(ROOT / "fe" / "params.yaml")
    assert fe.fe.settings["geometry"] == "coarse" and fe.fe.bounds["Kappa"] == (0.0, 0.33)
    assert fe.validate.idp_literature == {}  # no placeholder band
    standing = [p for p in fe.validate.idp_published if p.condition == "relaxed standing"]
    assert standing[0].idp_mpa == pytest.approx(0.50) and standing[0].kind == "in vivo"
    assert fe.baselines is None


def test_load_params_returns_the_yaml_unchanged():
    params = load_params(ROOT / "params.yaml")
    raw = yaml.safe_load(ROOT_TEXT)
    assert params.settings.calibrate.max_plots == 500  # the typed settings, beside the dict
    assert params.pop("_path") == str(ROOT / "params.yaml")
    assert params == raw
    assert section(params, "calibrate", "max_plots") == 500


def test_schema_detection():
    assert detect_schema(yaml.safe_load(ROOT_TEXT)) == "root"
    assert detect_schema(yaml.safe_load(FE_TEXT)) == "fe"
    assert detect_schema({"validate": {}}) == "fe"
    with pytest.raises(ConfigError, match="fe: not a section of the root params.yaml"):
        validate_params(yaml.safe_load(FE_TEXT), schema="root")
    with pytest.raises(ConfigError, match="schema must be one of root, fe"):
        validate_params({}, schema="other")


# ------------------------------------------------------------------ unknown and retired keys
def test_unknown_key_names_the_closest_valid_key(tmp_path):
    path = edited(tmp_path, ("  max_plots: 500", "  max_plots: 500\n  plot_max: 3"))
    line = line_of(path, "plot_max")
    with pytest.raises(ConfigError) as info:
        load_params(path)
    assert str(info.value) == (
        f"{path}, line {line}: calibrate.plot_max: unknown setting; did you mean "
        "calibrate.max_plots?"
    )


def test_unknown_key_without_a_close_one_lists_the_valid_keys(tmp_path):
    path = edited(tmp_path, ("  max_log_ratio:", "  zzz: 1\n  max_log_ratio:"))
    with pytest.raises(
        ConfigError,
        match=r"moments\.zzz: unknown setting; valid here: "
        r"error_growth, max_log_ratio\.",
    ):
        load_params(path)


def test_unknown_section(tmp_path):
    path = edited(tmp_path, ("\nplant:\n", "\nplnt:\n"))
    with pytest.raises(ConfigError, match=r"plnt: unknown section; did you mean plant\?"):
        load_params(path)


def test_retired_key_names_its_replacement(tmp_path):
    path = edited(tmp_path, ("  max_plots: 500", "  max_plots: 500\n  max_extrapolation: 1.5"))
    with pytest.raises(
        ConfigError,
        match=r"calibrate\.max_extrapolation: retired setting; replaced by "
        r"moments\.max_log_ratio \(and moments\.error_growth\)",
    ):
        load_params(path)


def test_misspelt_retired_key_names_itself_and_the_replacement(tmp_path):
    path = edited(tmp_path, ("  max_plots: 500", "  max_plots: 500\n  max_extrapolaton: 1.5"))
    with pytest.raises(ConfigError) as info:
        load_params(path)
    message = str(info.value)
    assert "calibrate.max_extrapolaton: unknown setting" in message
    assert "it looks like calibrate.max_extrapolation, a retired setting" in message
    assert "replaced by moments.max_log_ratio (and moments.error_growth)" in message


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "  measurements: data/planted/measurements.csv\n  out_dir",
            "  measurements: data/planted/measurements.csv\n  metrics_fil: x\n  out_dir",
            r"diagnose\.metrics_fil: unknown setting; did you mean diagnose\.metrics_file\?",
        ),
        (
            "  out_dir: reports/calibration ",
            "  out_dir: reports/calibration\n  effects: [] ",
            r"calibrate\.effects: retired setting; replaced by "
            r"calibrate\.datasets\.<name>\.effects",
        ),
    ],
)
def test_more_unknown_and_retired_keys(tmp_path, old, new, expected):
    with pytest.raises(ConfigError, match=expected):
        load_params(edited(tmp_path, (old, new)))


# ------------------------------------------------------------------ missing keys
def test_misspelt_required_key_is_named_as_the_probable_misspelling(tmp_path):
    path = edited(tmp_path, ("  method: pgd ", "  methd: pgd "))
    expected = (
        r"calibrate\.methd: unknown setting; did you mean calibrate\.method\? calibrate\.method "
        r"is required and missing: methd is probably it, misspelt\."
    )
    with pytest.raises(ConfigError, match=expected):
        load_params(path)
    with pytest.raises(ConfigError, match=expected) as info:
        load_settings(path)
    assert "calibrate.method: missing setting" not in str(info.value)  # one problem, not two


def test_missing_required_key_in_a_complete_file(tmp_path):
    path = edited(
        tmp_path, ("  method: pgd                        # pgd, pgd-study, ga, inverse\n", "")
    )
    load_params(path)  # a command reports it when it reads it (section)
    with pytest.raises(
        ConfigError,
        match=r"calibrate\.method: missing setting; add it \(method: calibration method; "
        r"expected one of 'pgd', 'pgd-study', 'ga', 'inverse', or a plugin's name \(group "
        r"femcal\.calibrators\)\)",
    ):
        load_settings(path)


def test_missing_section_in_a_complete_file(tmp_path):
    data = yaml.safe_load(ROOT_TEXT)
    del data["plant"]
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"plant: missing section; add it"):
        load_settings(tmp_path / "p.yaml")


def test_section_names_a_missing_key_with_its_doc():
    with pytest.raises(
        ConfigError,
        match=r"p\.yaml: missing setting 'data\.prepared_dir'\. Add it .* data\.prepared_dir: "
        r"folder of the tidy tables",
    ):
        section({"_path": "p.yaml", "data": {}}, "data", "prepared_dir")
    assert describe_setting(["calibrate", "max_plots"]).startswith("per-specimen PNGs")
    assert describe_setting(["nope"]) is None


# ------------------------------------------------------------------ types, ranges, choices
def test_wrong_type_says_what_was_given_and_what_is_allowed(tmp_path):
    path = edited(tmp_path, ("  max_plots: 500 ", "  max_plots: ten "))
    with pytest.raises(
        ConfigError,
        match=r"calibrate\.max_plots: Input should be a valid integer, got 'ten' \(str\); "
        r"max_plots: per-specimen PNGs",
    ):
        load_params(path)


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "  chunk_size: 512",
            '  chunk_size: "abc"',
            r"calibrate\.chunk_size: Input should be a valid integer, got 'abc' \(str\)",
        ),
        (
            "  seed: 0\n  chunk_size",
            "  seed: true\n  chunk_size",
            r"calibrate\.seed: Input should be a valid integer, got true \(bool\)",
        ),
        (
            "  plots: true\n  max_plots: 500",
            "  plots: 1\n  max_plots: 500",
            r"calibrate\.plots: Input should be a valid boolean, got 1 \(int\)",
        ),
        (
            "  n_jobs: 1",
            "  n_jobs: 0",
            r"baselines\.n_jobs: expected an integer >= 1, or -1 \(all cores\), got 0 \(int\)",
        ),
        (
            "    above: 0.51",
            "    above: far",
            r"moments\.max_log_ratio\.above: Input should be a valid number, got 'far' \(str\)",
        ),
        (
            "  max_plots: 500",
            "  max_plots: 2.5",
            r"calibrate\.max_plots: Input should be a valid integer, got 2\.5 \(float\)",
        ),
        (
            "  limit_configs: null",
            "  limit_configs: [1]",
            r"data\.limit_configs: Input should be a valid integer, got \[1\] \(list\)",
        ),
    ],
)
def test_wrong_types(tmp_path, old, new, expected):
    with pytest.raises(ConfigError, match=expected):
        load_params(edited(tmp_path, (old, new)))


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "  alpha: 0.01",
            "  alpha: 1.5",
            r"diagnose\.alpha: Input should be less than 1, got 1\.5 \(float\)",
        ),
        (
            "  max_plots: 500",
            "  max_plots: -1",
            r"calibrate\.max_plots: Input should be greater than or equal to 0, got -1 \(int\)",
        ),
        (
            "  val_fraction: 0.15",
            "  val_fraction: 1",
            r"train\.val_fraction: Input should be less than 1, got 1 \(int\)",
        ),
        (
            "    above: 2.99",
            "    above: .nan",
            r"moments\.error_growth\.above: Input should be a finite number, got nan \(float\)",
        ),
        (
            "  moments: [1, 1.5, 2,",
            "  moments: [0, 1.5, 2,",
            r"plant\.moments\[0\]: Input should be greater than 0, got 0 \(int\)",
        ),
    ],
)
def test_out_of_range(tmp_path, old, new, expected):
    with pytest.raises(ConfigError, match=expected):
        load_params(edited(tmp_path, (old, new)))


def test_search_entries_of_each_type():
    space = {
        "batch_size": {"type": "int", "low": 16, "high": 64, "log": True},
        "width": {"type": "categorical", "choices": [64, 128]},
        "dropout": {"type": "float", "low": 0, "high": 0.5},
        "log_target": {"type": "categorical", "choices": [True, False]},
    }
    validate_params({"train": {"large": {"search_space": space}}})
    with pytest.raises(ConfigError, match=r"batch_size\.low: an int entry needs integer bounds"):
        validate_params(
            {
                "train": {
                    "large": {"search_space": {"batch_size": {**space["batch_size"], "low": 16.5}}}
                }
            }
        )
    with pytest.raises(
        ConfigError,
        match=r"search_space\.dropout\.high: Input should be less than 1, got 1 \(int\)",
    ):
        validate_params(
            {"train": {"large": {"search_space": {"dropout": {**space["dropout"], "high": 1}}}}}
        )
    for bad in (["float"], {"float": 1}):  # an unhashable type is worded, not a TypeError
        with pytest.raises(
            ConfigError,
            match=r"dropout\.type: expected one of 'float', 'int', 'categorical', got (\[|\{)",
        ):
            entry = {**space["dropout"], "type": bad}
            validate_params({"train": {"large": {"search_space": {"dropout": entry}}}})
    with pytest.raises(ConfigError, match=r"hidden\.type: hidden is .* search width and depth"):
        validate_params(
            {"inverse": {"search_space": {"hidden": {"type": "categorical", "choices": [1, 2]}}}}
        )


def test_yaml_ints_are_accepted_for_numbers(tmp_path):
    path = edited(tmp_path, ("    above: 2.99", "    above: 3"))
    assert load_params(path)["moments"]["error_growth"]["above"] == 3  # the dict is unchanged
    value = load_settings(path).moments.error_growth.above
    assert value == 3.0 and isinstance(value, float)


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "  method: pgd ",
            "  method: pgdd ",
            r"calibrate\.method: expected one of 'pgd', 'pgd-study', 'ga', 'inverse', got 'pgdd' "
            r"\(str\); did you mean 'pgd'\?",
        ),
        (
            "models: [linear, poly2,",
            "models: [linear, poly6,",
            r"baselines\.models\[1\]: expected one of .*got 'poly6' \(str\); did you mean 'poly",
        ),
        (
            "  models: [linear, poly2,",
            "  models: [linear, linear,",
            r"baselines\.models: 'linear' is listed twice",
        ),
    ],
)
def test_wrong_choice(tmp_path, old, new, expected):
    with pytest.raises(ConfigError, match=expected):
        load_params(edited(tmp_path, (old, new)))


def test_every_problem_in_one_message_in_line_order(tmp_path):
    path = edited(
        tmp_path,
        ("  max_plots: 100", "  max_plots: 100\n  plot_max: 3"),
        ("  max_plots: 500 ", "  max_plots: ten "),
        ("  alpha: 0.01", "  alpha: 1.5"),
    )
    with pytest.raises(ConfigError) as info:
        load_params(path)
    lines = str(info.value).splitlines()
    assert lines[0] == f"{path}: 3 invalid settings; fix each and rerun:"
    assert [line.split(":")[1].strip() for line in lines[1:]] == [
        "calibrate.max_plots",
        "diagnose.alpha",
        "diagnose.plot_max",
    ]
    assert lines[1].startswith(f"  line {line_of(path, 'max_plots: ten')}: ")


# ------------------------------------------------------------------ open maps
@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        # model hyper-parameters (NeuralSurrogate keywords)
        (
            "      width: 64\n",
            "      widht: 64\n",
            r"train\.small\.fixed\.widht: unknown NeuralSurrogate keyword; did you mean "
            r"train\.small\.fixed\.width\?",
        ),
        (
            "      width: 64\n",
            "      width: 64\n      n_members: 3\n",
            r"train\.small\.fixed\.n_members: not settable here; the ensemble size is "
            r"train\.<split>\.final_members",
        ),
        (
            "      width: 64\n",
            "      width: 64\n      hidden: [8, 8]\n",
            r"train\.small\.fixed\.hidden: give either hidden or width and depth",
        ),
        (
            "      activation: gelu\n      log_target: true\n      log_params: true\n"
            "      loss: l1\n      width: 64",
            "      activation: swish\n      log_target: true\n      log_params: true\n"
            "      loss: l1\n      width: 64",
            r"train\.small\.fixed\.activation: Input should be 'silu', 'gelu', .* got 'swish' "
            r"\(str\); activation: hidden activation",
        ),
        # a section of train that is not a mapping is a misspelt setting, not a split
        (
            "  val_fraction: 0.15",
            "  val_fracton: 0.15",
            r"train\.val_fracton: unknown setting; did you mean train\.val_fraction\? \(the other "
            r"keys of train are splits",
        ),
        (
            "    split: large\n",
            "",
            r"train\.holdout: holdout is not a prepared split \(large, small, test\); add split: "
            r"large",
        ),
        # search-space entries
        (
            "learning_rate: {type: float, low: 0.001, high: 0.01, log: true}",
            "learning_rate: {type: float, low: 0.01, high: 0.001, log: true}",
            r"train\.large\.search_space\.learning_rate\.high: high must be > low; got low 0\.01, "
            r"high 0\.001",
        ),
        (
            "learning_rate: {type: float, low: 0.001, high: 0.01, log: true}",
            "learning_rate: {type: float, low: 0, high: 0.01}",
            r"train\.large\.search_space\.learning_rate\.low: Input should be greater than 0, "
            r"got 0 \(int\)",
        ),
        (
            "learning_rate: {type: float, low: 0.001, high: 0.01, log: true}",
            "learning_rate: {type: flaot, low: 0.001, high: 0.01}",
            r"learning_rate\.type: expected one of 'float', 'int', 'categorical', got 'flaot' "
            r"\(str\); did you mean 'float'\?",
        ),
        (
            "learning_rate: {type: float, low: 0.001, high: 0.01, log: true}",
            "learning_rate: {type: float, low: 0.001}",
            r"learning_rate\.high: missing: a float entry needs low and high",
        ),
        (
            "activation: {type: categorical, choices: [gelu, silu]}",
            "activation: {type: categorical, low: 1, high: 2}",
            r"activation\.choices: missing: a categorical entry needs choices",
        ),
        (
            "activation: {type: categorical, choices: [gelu, silu]}",
            "batch_size: {type: float, low: 16, high: 64}",
            r"batch_size\.type: batch_size is an integer >= 1, so type float does not fit; use "
            r"int or categorical",
        ),
        (
            "activation: {type: categorical, choices: [gelu, silu]}",
            "activation: {type: categorical, choices: [gelu, swish]}",
            r"search_space\.activation\.choices\[1\]: Input should be 'silu', .* got 'swish'",
        ),
        (
            "activation: {type: categorical, choices: [gelu, silu]}",
            "activaton: {type: categorical, choices: [gelu, silu]}",
            r"search_space\.activaton: unknown NeuralSurrogate keyword; did you mean "
            r"train\.large\.search_space\.activation\?",
        ),
        (
            "activation: {type: categorical, choices: [gelu, silu]}",
            "activation: {type: categorical, choices: [gelu], step: 2}",
            r"activation\.step: unknown setting",
        ),
        # the inverse model's hyper-parameters (InverseModel keywords)
        (
            "    learning_rate: 0.0010615360772719654\n  search_space:",
            "    learning_rate: 0.0010615360772719654\n    seed: 3\n  search_space:",
            r"inverse\.fixed\.seed: not settable here; set inverse\.seed",
        ),
        (
            "    learning_rate: 0.0010615360772719654\n  search_space:",
            "    learning_rate: 0.0010615360772719654\n    scheduler_factor: 1.5\n  search_space:",
            r"inverse\.fixed\.scheduler_factor: Input should be less than 1, got 1\.5",
        ),
        # calibrator options (the calibrators' keyword arguments)
        (
            "    ga: {}",
            "    gaa: {}",
            r"calibrate\.options\.gaa: unknown calibration method; did you mean "
            r"calibrate\.options\.ga\?",
        ),
        (
            "pgd: {n_starts: 8,",
            "pgd: {n_start: 8,",
            r"calibrate\.options\.pgd\.n_start: unknown pgd calibrator keyword; did you mean "
            r"calibrate\.options\.pgd\.n_starts\?",
        ),
        (
            "pgd: {n_starts: 8,",
            "pgd: {n_starts: -8,",
            r"calibrate\.options\.pgd\.n_starts: Input should be greater than or equal to 0, "
            r"got -8 \(int\); n_starts: starts per specimen",
        ),
        (
            "pgd: {n_starts: 8,",
            "pgd: {retry_alpha: 1, n_starts: 8,",
            r"calibrate\.options\.pgd\.retry_alpha: Input should be less than 1, got 1 "
            r"\(int\); retry_alpha: with a noise_deg: fit again from 4x the starts",
        ),
        (
            "pgd: {n_starts: 8,",
            "pgd: {start_bank: [[1, 2]], n_starts: 8,",
            r"calibrate\.options\.pgd\.start_bank: not settable here; set calibrate\.start_bank",
        ),
        (
            "    ga: {}",
            "    ga: {population: 30}",
            r"calibrate\.options\.ga\.population: n_selected \+ n_crossover \+ n_mutation \+ "
            r"n_immigrants = 6 \+ 4 \+ 4 \+ 6 = 20 must equal population = 30",
        ),
        (
            "pgd-study: {n_starts: 500, steps: 2250, lr: 0.0971}",
            "pgd-study: {n_starts: 500, steps: 2250, lr: 0.0971, projection: clamp}",
            r"options\.pgd-study\.projection: Input should be 'clip' or 'average', got 'clamp' "
            r"\(str\); did you mean 'clip'\?",
        ),
        (
            "inverse: {model_uri: models/inverse}",
            'inverse: {model_uri: "models:/ivd-inverse"}',
            r"calibrate\.options\.inverse\.model_uri: expected an MLflow model URI .* expected "
            r"models:/NAME@ALIAS or models:/NAME/VERSION",
        ),
        # datasets
        (
            "    test: {measurements: data/raw/Test, effects: []}",
            "    test: {measurments: data/raw/Test, effects: []}",
            r"calibrate\.datasets\.test\.measurments: unknown setting; did you mean "
            r"calibrate\.datasets\.test\.measurements\? .* is required and missing",
        ),
        (
            "    test: {measurements: data/raw/Test, effects: []}",
            "    my test: {measurements: data/raw/Test, effects: []}",
            r"calibrate\.datasets\.my test: dataset name 'my test' must start with a letter",
        ),
        (
            "    test: {measurements: data/raw/Test, effects: []}",
            "    test: 3",
            r"calibrate\.datasets\.test: expected a path or \{measurements: path, effects: "
            r"\[names\], noise_deg: sd\}, got 3 \(int\)",
        ),
        (
            "    test: {measurements: data/raw/Test, effects: []}",
            "    test: {measurements: data/raw/Test, effects: [], noise_deg: 0}",
            r"calibrate\.datasets\.test\.noise_deg: Input should be greater than 0, got 0 \(int\)",
        ),
        # URLs and URIs in the file
        (
            "storage: sqlite:///mlruns/optuna.db",
            "storage: postgres://u@db/optuna",
            r"train\.storage: expected a SQLAlchemy database URL, got 'postgres://u@db/optuna': "
            r"SQLAlchemy names this dialect postgresql; write postgresql://u@db/optuna",
        ),
        (
            "storage: sqlite:///mlruns/optuna.db",
            "storage: mlruns/optuna.db",
            r"train\.storage: .* not a SQLAlchemy URL; for a SQLite file write "
            r"sqlite:///mlruns/optuna\.db",
        ),
        (
            "  model_uri: models/surrogate-large",
            "  model_uri: ivd-rom-surrogate@champion",
            r"calibrate\.model_uri: .* did you mean models:/ivd-rom-surrogate@champion\?",
        ),
    ],
)
def test_open_maps_are_validated(tmp_path, old, new, expected):
    with pytest.raises(ConfigError, match=expected):
        load_params(edited(tmp_path, (old, new)))


@pytest.mark.parametrize(
    ("effects", "expected"),
    [
        (["creep.py"], r"effects: expected a mapping of settings \(modules\), got \['creep\.py'\]"),
        (
            {"modules": "creep.py"},
            r"effects\.modules: Input should be a list, got 'creep\.py' \(str\)",
        ),
        (
            {"modules": [1]},
            r"effects\.modules\[0\]: expected a path \(a non-empty string\), "
            r"got 1 \(int\)",
        ),
        (
            {"module": ["creep.py"]},
            r"effects\.module: unknown setting; did you mean "
            r"effects\.modules\?",
        ),
    ],
)
def test_the_effects_section_says_its_form(tmp_path, effects, expected):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"effects": effects}))
    with pytest.raises(ConfigError, match=expected) as info:
        load_params(path)
    assert "the effects section must be {modules: [paths]}" in str(info.value)


# ------------------------------------------------------------------ fe/params.yaml
@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "    Kappa: [0.0, 0.33]",
            "    Kapa: [0.0, 0.33]",
            r"fe\.bounds\.Kapa: unknown parameter; did you mean fe\.bounds\.Kappa\?",
        ),
        (
            "    Kappa: [0.0, 0.33]",
            "    Kappa: [0.33, 0.0]",
            r"fe\.bounds\.Kappa: expected \[lower, upper\] with lower < upper, got \[0\.33, 0\.0\]",
        ),
        (
            "    max_attempts: 3",
            "    max_attempt: 3",
            r"fe\.settings\.max_attempt: unknown CalculixDisc keyword; did you mean "
            r"fe\.settings\.max_attempts\?",
        ),
        (
            "    geometry: coarse",
            "    geometry: corse",
            r"fe\.settings\.geometry: expected one of 'coarse', 'default', 'fine', got 'corse' "
            r"\(str\); did you mean 'coarse'\?",
        ),
        (
            "    geometry: coarse",
            "    geometry: {preset: coarse, n_regions: 2}",
            r"fe\.settings\.geometry\.n_regions: Input should be greater than or equal to 3, got 2",
        ),
        (
            "    timeout_s: 90",
            "    timeout_s: -1",
            r"fe\.settings\.timeout_s: Input should be greater than 0, got -1 \(int\)",
        ),
        (
            "  scheduler_address: null",
            "  scheduler_address: login-node:8786",
            r"fe\.scheduler_address: expected a Dask scheduler address tcp://host:port, "
            r"got 'login-node:8786': no protocol; write tcp://login-node:8786",
        ),
        (
            "splits: {large: 512,",
            "splits: {larg: 512,",
            r"fe\.splits\.larg: unknown split; did you mean fe\.splits\.large\?",
        ),
        (
            "    max_fe_runs: 5",
            "    max_fe_runs: 0",
            r"validate\.refine\.max_fe_runs: Input should be greater than or equal to 1, got 0",
        ),
        (
            "    tol_deg: 0.05",
            "    tol_deg: 0",
            r"validate\.refine\.tol_deg: Input should be greater than 0, got 0",
        ),
        (
            "  solver: calculix ",
            "  solver: abaqus ",
            r"fe\.solver: expected one of 'calculix', got 'abaqus'",
        ),
        (
            "load_cases: [Flexion, Extension, LateralBending, AxialRotation]",
            "load_cases: [Flexion, Extension, LateralBending]",
            r"fe\.load_cases: a dataset in the study's layout needs all four load cases",
        ),
        (
            "load_cases: [Flexion, Extension,",
            "load_cases: [Flexion, extension,",
            r"fe\.load_cases\[1\]: Input should be 'Flexion', .* got 'extension' \(str\); did you "
            r"mean 'Extension'\?",
        ),
        (
            "  idp_literature: {}",
            "  idp_literature:\n    300: {low: 0.48, mean: 0.30, high: 0.42}",
            r"validate\.idp_literature\.300\.mean: need low <= mean <= high; got 0\.48, 0\.3, "
            r"0\.42",
        ),
        (
            "  idp_literature: {}",
            "  idp_literature:\n    300: {low: 0.18, high: 0.42}",
            r"validate\.idp_literature\.300\.mean: missing setting",
        ),
        (
            "condition: relaxed standing, idp_mpa: 0.50,",
            "condition: relaxed standing, idp_mpa: -0.50,",
            r"validate\.idp_published\[4\]\.idp_mpa: Input should be greater than 0",
        ),
        (
            "condition: relaxed standing, idp_mpa: 0.50, kind: in vivo,",
            "condition: relaxed standing, idp_mpa: 0.50, kind: invivo,",
            r"validate\.idp_published\[4\]\.kind: Input should be 'in vivo' or 'in vitro', got "
            r"'invivo' \(str\); did you mean 'in vivo'\?",
        ),
        (
            "  holdout_uri: null",
            "  holdout_uri: model:/x@champion",
            r"calibrate\.holdout_uri: .* did you mean models:/x@champion\?",
        ),
    ],
)
def test_fe_params_errors(tmp_path, old, new, expected):
    with pytest.raises(ConfigError, match=expected):
        load_params(edited(tmp_path, (old, new), fe=True))


# ------------------------------------------------------------------ environment variables
@pytest.mark.parametrize(
    ("name", "value", "command", "expected"),
    [
        (
            "FEMCAL_DATA_MIRROR",
            "{tmp}/nope",
            "fetch",
            r"FEMCAL_DATA_MIRROR='.*nope': .*nope does not exist\. FEMCAL_DATA_MIRROR is a local "
            r"folder holding the study's Large/, Small/ and Test/ .* or unset it to download",
        ),
        ("FEMCAL_DATA_MIRROR", "{tmp}/file.txt", "fetch", r"is a file, not a folder"),
        ("FEMCAL_DATA_MIRROR", "{tmp}", "fetch", r"holds none of Large/, Small/, Test/"),
        (
            "FEMCAL_OPTUNA_STORAGE",
            "postgres://u@db/optuna",
            "train",
            r"FEMCAL_OPTUNA_STORAGE='postgres://u@db/optuna': SQLAlchemy names this dialect "
            r"postgresql; write postgresql://u@db/optuna\. FEMCAL_OPTUNA_STORAGE is the Optuna "
            r"storage",
        ),
        (
            "FEMCAL_OPTUNA_STORAGE",
            "optuna.db",
            "train-inverse",
            r"not a SQLAlchemy URL; for a SQLite file write sqlite:///optuna\.db",
        ),
        (
            "FEMCAL_OPTUNA_STORAGE",
            "sqlite://optuna.db",
            "train",
            r"three slashes before a relative path: sqlite:///optuna\.db",
        ),
        ("FEMCAL_OPTUNA_STORAGE", "sqlite://", "train", r"in-memory SQLite database forgets"),
        (
            "FEMCAL_OPTUNA_STORAGE",
            "postgressql://h/db",
            "train",
            r"unknown database dialect 'postgressql'; did you mean postgresql://h/db\?",
        ),
        (
            "FEMCAL_DASK_ADDRESS",
            "login-node:8786",
            "simulate",
            r"FEMCAL_DASK_ADDRESS='login-node:8786': no protocol; write tcp://login-node:8786",
        ),
        (
            "FEMCAL_DASK_ADDRESS",
            "tcp://login-node",
            "validate",
            r"no port; write tcp://login-node:8786",
        ),
        (
            "FEMCAL_DASK_ADDRESS",
            "http://login-node:8786",
            "simulate",
            r"unknown protocol http://; use one of tcp://",
        ),
        ("FEMCAL_DASK_ADDRESS", "tcp://login-node:99999", "simulate", r"port 99999 is not in"),
        (
            "MLFLOW_TRACKING_URI",
            "localhost:5000",
            "calibrate",
            r"MLFLOW_TRACKING_URI='localhost:5000': no scheme, so MLflow would read it as a "
            r"folder; write http://localhost:5000",
        ),
        (
            "MLFLOW_TRACKING_URI",
            "htp://server:5000",
            "train",
            r"unknown scheme htp://; did you mean http://\?",
        ),
        ("MLFLOW_TRACKING_URI", "http://", "diagnose", r"no host; write http://host:5000"),
        (
            "MLFLOW_TRACKING_URI",
            "sqlite://mlflow.db",
            "evaluate",
            r"three slashes before a relative path",
        ),
    ],
)
def test_bad_environment_variables(tmp_path, name, value, command, expected):
    (tmp_path / "file.txt").write_text("x")
    value = value.format(tmp=tmp_path)
    with pytest.raises(ConfigError, match=rf"^Environment variable {name}=") as info:
        check_environment(command, {name: value})
    assert re.search(expected, str(info.value)), str(info.value)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("FEMCAL_OPTUNA_STORAGE", "sqlite:///mlruns/optuna.db"),
        ("FEMCAL_OPTUNA_STORAGE", "sqlite:////abs/optuna.db"),
        ("FEMCAL_OPTUNA_STORAGE", "postgresql+psycopg2://user:pw@db:5432/optuna"),
        ("FEMCAL_DASK_ADDRESS", "tcp://login-node:8786"),
        ("FEMCAL_DASK_ADDRESS", "tls://10.0.0.1:8786"),
        ("FEMCAL_DASK_ADDRESS", "inproc://10.0.0.1/123/1"),
        ("MLFLOW_TRACKING_URI", "http://mlflow:5000"),
        ("MLFLOW_TRACKING_URI", "sqlite:///mlruns/mlflow.db"),
        ("MLFLOW_TRACKING_URI", "file:///tmp/mlruns"),
        ("MLFLOW_TRACKING_URI", "databricks"),
        ("MLFLOW_TRACKING_URI", "./mlruns"),
    ],
)
def test_good_environment_variables(name, value):
    assert check_environment(None, {name: value}) == {name: value}


def test_environment_mirror_and_scope(tmp_path):
    (tmp_path / "Large").mkdir()
    assert check_environment("fetch", {"FEMCAL_DATA_MIRROR": str(tmp_path)}) == {
        "FEMCAL_DATA_MIRROR": str(tmp_path)
    }
    bad = {"FEMCAL_DATA_MIRROR": str(tmp_path / "nope"), "FEMCAL_DASK_ADDRESS": "x"}
    # Only the variables a command reads are checked; blank ones count as unset.
    assert check_environment("calibrate", bad) == {}
    assert check_environment("fetch", {"FEMCAL_DATA_MIRROR": "  "}) == {}
    with pytest.raises(
        ConfigError,
        match=r"^Invalid environment variables:\n  "
        r"FEMCAL_DATA_MIRROR=.*\n  FEMCAL_DASK_ADDRESS='x'",
    ):
        check_environment(None, bad)


# ------------------------------------------------------------------ the command line
def test_cli_stops_on_a_bad_setting_before_any_work(tmp_path, capsys):
    from femcal.cli import main

    path = edited(tmp_path, ("  max_plots: 500", "  max_plots: 500\n  plot_max: 3"))
    t0 = time.perf_counter()
    code = main(["--params", str(path), "calibrate", "--measurements", "nope.csv"])
    # Seconds at most even on a loaded machine: nothing is loaded or calibrated.
    assert code == 2 and time.perf_counter() - t0 < 10.0
    err = capsys.readouterr().err
    assert err.startswith(f"femcal calibrate: error: {path}, line ")
    assert "calibrate.plot_max: unknown setting; did you mean calibrate.max_plots?" in err


def test_cli_stops_on_a_bad_environment_variable(tmp_path, capsys, monkeypatch):
    from femcal.cli import main

    monkeypatch.setenv("FEMCAL_DATA_MIRROR", str(tmp_path / "nope"))
    assert main(["--params", str(ROOT / "params.yaml"), "fetch", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "femcal fetch: error: Environment variable FEMCAL_DATA_MIRROR=" in err
    assert "does not exist" in err and not any(tmp_path.iterdir())


def test_cli_validates_without_heavy_imports(tmp_path):
    """A fresh `femcal calibrate` with a bad setting stops before torch, Lightning, MLflow or
    scikit-learn are imported."""
    path = edited(tmp_path, ("  max_plots: 500 ", "  max_plots: ten "))
    code = (
        "import sys\n"
        "from femcal.cli import main\n"
        f"rc = main(['--params', {str(path)!r}, 'calibrate'])\n"
        "heavy = [m for m in ('torch', 'pytorch_lightning', 'lightning', 'mlflow', 'optuna',"
        " 'sklearn')"
        " if m in sys.modules]\n"
        "print(rc, heavy)\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert proc.stdout.strip() == "2 []", proc.stdout + proc.stderr
    assert "calibrate.max_plots: Input should be a valid integer, got 'ten' (str)" in proc.stderr


# ------------------------------------------------------------------ the tables match the code
def _keywords(fn) -> dict[str, inspect.Parameter]:
    return {
        name: p
        for name, p in inspect.signature(fn).parameters.items()
        if p.kind is p.KEYWORD_ONLY
        or (p.kind is p.POSITIONAL_OR_KEYWORD and p.default is not p.empty)
    }


def _yaml_default(value):
    return list(value) if isinstance(value, tuple) else value


def _choices(model, name):
    return get_args(model.model_fields[name].annotation)


def test_hyperparameter_tables_match_the_estimators():
    from femcal.inverse import InverseModel
    from femcal.surrogates.nn import ACTIVATIONS, LOSSES, LR_SCHEDULES, NeuralSurrogate
    from femcal.train import surrogate_kwargs

    init = set(_keywords(NeuralSurrogate.__init__)) | {"space"}
    table = set(SurrogateKeywords.model_fields) - {"width", "depth"}
    refused = set(SurrogateKeywords._reasons)
    assert table | refused == init and not table & refused
    assert _choices(SurrogateKeywords, "activation") == tuple(ACTIVATIONS)
    assert _choices(SurrogateKeywords, "loss") == LOSSES
    assert _choices(SurrogateKeywords, "lr_schedule") == LR_SCHEDULES
    # The estimator's own defaults are valid settings, and width/depth are understood.
    defaults = {
        k: _yaml_default(p.default)
        for k, p in _keywords(NeuralSurrogate.__init__).items()
        if k in table
    }
    validate_params({"train": {"large": {"fixed": defaults}}})
    assert surrogate_kwargs({"width": 8, "depth": 2}) == {"hidden": (8, 8)}

    inv = set(InverseModel._SETTINGS)
    inv_table = set(InverseKeywords.model_fields) - {"width", "depth"}
    assert inv_table | {"seed"} == inv and set(InverseKeywords._reasons) == {"seed", "space"}
    assert set(_keywords(InverseModel.__init__)) == inv | {"space"}
    defaults = {
        k: _yaml_default(p.default)
        for k, p in _keywords(InverseModel.__init__).items()
        if k in inv_table
    }
    validate_params({"inverse": {"fixed": defaults}})


def test_calibrator_tables_match_the_calibrators():
    from femcal.calibration import available_calibrators, get_calibrator
    from femcal.calibration import pgd as pgd_module
    from femcal.calibration import pgd_study_options as study_module
    from femcal.calibration.ga_options import GaOptions
    from femcal.settings import CALIBRATORS

    assert sorted(CALIBRATORS) == available_calibrators() == sorted(CALIBRATOR_OPTIONS)
    for method, keywords in CALIBRATOR_OPTIONS.items():
        params = _keywords(get_calibrator(method))
        assert set(keywords.model_fields) | set(keywords._reasons) == set(params), method
        # Every default that YAML can hold is a valid option value.
        defaults = {
            k: _yaml_default(p.default)
            for k, p in params.items()
            if k in keywords.model_fields and p.default is not None
        }
        validate_params({"calibrate": {"options": {method: defaults}}})
    pgd = CALIBRATOR_OPTIONS["pgd"]
    assert _choices(pgd, "optimizer") == pgd_module.OPTIMIZERS
    assert set(_choices(pgd, "loss")) == set(pgd_module.LOSSES)
    assert _choices(pgd, "select") == pgd_module.SELECT
    study = CALIBRATOR_OPTIONS["pgd-study"]
    assert _choices(study, "projection") == study_module.PROJECTIONS
    assert _choices(study, "optimizer") == study_module.OPTIMIZERS
    ga = _keywords(get_calibrator("ga"))
    names = ("population", "n_selected", "n_crossover", "n_mutation")
    population = {k: getattr(GaOptions, k) for k in names}
    assert {k: ga[k].default for k in population} == population


def test_registry_tables_match_the_registries():
    from femcal.fe import available_solvers
    from femcal.fe.calculix import CalculixDisc
    from femcal.fe.calculix_settings import GeometryKeywords
    from femcal.fe.design import SPLIT_SAMPLING
    from femcal.fe.geometry import MESH_PRESETS, DiscGeometry
    from femcal.prepare import SPLITS as PREPARED
    from femcal.settings import BASELINE_MODELS, SOLVER_SETTINGS, SOLVERS, SPLITS
    from femcal.settings import MESH_PRESETS as PRESETS
    from femcal.surrogates import available_baselines, available_surrogates

    assert sorted(BASELINE_MODELS) == available_baselines()
    assert set(available_baselines()) == set(available_surrogates()) - {"nn"}
    assert sorted(SOLVERS) == available_solvers() == sorted(SOLVER_SETTINGS)
    calculix = set(SOLVER_SETTINGS["calculix"].model_fields)
    assert calculix == set(_keywords(CalculixDisc.__init__))
    fields = {f.name for f in dataclasses.fields(DiscGeometry)} | {"preset"}
    assert set(GeometryKeywords.model_fields) == fields
    assert PRESETS == tuple(MESH_PRESETS)
    assert set(SPLITS) == set(PREPARED) == set(SPLIT_SAMPLING)


def test_builtin_effects_table_matches_the_registry():
    """`femcal calibrate --help` lists BUILTIN_EFFECTS without importing torch."""
    from femcal.effects import available_effects, get_effect
    from femcal.settings import BUILTIN_EFFECTS

    builtin = [n for n in available_effects() if get_effect(n).__module__.startswith("femcal.")]
    assert sorted(BUILTIN_EFFECTS) == builtin
