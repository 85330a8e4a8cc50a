"""Each option is declared once, and the command line is built from the same declarations.

The options dataclasses (``DiagnoseOptions``, ``PgdOptions``, ``GaOptions``, ...) declare each
option's type, bounds, default and doc; the settings sections and keyword tables are built
from them, and ``femcal diagnose`` / ``femcal calibrate`` take every setting of their section
as ``--<key>``, merged into params.yaml before it is validated.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from femcal.calibration.ga_options import GaOptions
from femcal.calibration.pgd_options import PgdOptions
from femcal.calibration.pgd_study_options import PgdStudyOptions
from femcal.cli import SETTINGS_OF, build_parser, setting_overrides
from femcal.config import load_params
from femcal.diagnose.options import DiagnoseOptions
from femcal.errors import ConfigError
from femcal.fe.calculix_settings import GeometryKeywords
from femcal.fe.options import AdaptOptions, CampaignOptions, GeometryOptions, ValidateOptions
from femcal.settings import SECTIONS, keys_of
from femcal.settings.fe import AdaptSettings, FeSettings, RefineSettings
from femcal.settings.keywords import GaKeywords, PgdKeywords, PgdStudyKeywords
from femcal.settings.root import DiagnoseSettings
from femcal.settings.values import option_fields

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "femcal"
#: Where settings, stages and options are declared.
DECLARING = [
    *sorted((SRC / "settings").glob("*.py")),
    *sorted((SRC / "stages").glob("*.py")),
    SRC / "diagnose" / "options.py",
    SRC / "calibration" / "pgd_options.py",
    SRC / "calibration" / "pgd_study_options.py",
    SRC / "calibration" / "ga_options.py",
    SRC / "fe" / "options.py",
    SRC / "fe" / "calculix_settings.py",
    SRC / "training" / "search_space.py",
]
#: Each options dataclass, the model of params.yaml that holds its options, and its module.
OPTIONS = [
    (DiagnoseOptions, DiagnoseSettings, "diagnose/options.py"),
    (PgdOptions, PgdKeywords, "calibration/pgd_options.py"),
    (PgdStudyOptions, PgdStudyKeywords, "calibration/pgd_study_options.py"),
    (GaOptions, GaKeywords, "calibration/ga_options.py"),
    (CampaignOptions, FeSettings, "fe/options.py"),
    (AdaptOptions, AdaptSettings, "fe/options.py"),
    (ValidateOptions, RefineSettings, "fe/options.py"),
    (GeometryOptions, GeometryKeywords, "fe/options.py"),
]
#: The stage that passes each dataclass its options (calibrate passes the method's mapping,
#: its noise_deg is the measurement's, not pgd's error scale; simulate resolves fe.scratch_dir
#: against the project root).
STAGES = {
    "DiagnoseOptions": "stages/diagnose.py",
    "AdaptOptions": "stages/adapt.py",
    "ValidateOptions": "stages/validate.py",
}


def _declared_fields() -> dict[tuple[str, str], list[str]]:
    """(file, class) -> the names its body declares (``name: type`` at class level)."""
    out = {}
    for path in DECLARING:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                names = [
                    s.target.id
                    for s in node.body
                    if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)
                ]
                out[(str(path.relative_to(SRC)), node.name)] = names
    return out


@pytest.mark.parametrize(("options", "model", "home"), OPTIONS)
def test_each_option_is_declared_once(options, model, home):
    """An option of diagnose, pgd, ga, fe or the disc geometry is declared in its dataclass and
    nowhere else: neither the classes its settings model is built on nor its stage's settings
    declare it again."""
    names = set(option_fields(options))
    bases = {cls.__name__ for cls in model.__mro__}
    for (file, cls), declared in _declared_fields().items():
        again = names & set(declared)
        if file == home and cls == options.__name__:
            assert names <= set(declared)
        elif cls in bases or file == STAGES.get(options.__name__):
            assert not again, f"{file}:{cls} declares {sorted(again)} again"
    for name, (_, default, doc) in option_fields(options).items():
        field = model.model_fields[name]
        assert field.description == doc, name
        assert field.default in (None, default), name


def test_every_diagnose_and_calibrate_setting_is_an_option():
    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    assert set(SETTINGS_OF["diagnose"]) >= {"diagnose", "moments"}
    assert set(SETTINGS_OF["calibrate"]) >= {"calibrate", "moments"}
    for command, sections in SETTINGS_OF.items():
        flags = commands[command]._option_string_actions
        for section, keys in sections.items():
            for key in keys or keys_of(SECTIONS[section][0]):
                assert "--" + key.replace("_", "-") in flags, f"femcal {command}: no --{key}"


def test_diagnose_options_are_settings_and_options():
    assert set(option_fields(DiagnoseOptions)) <= set(keys_of(DiagnoseSettings))
    assert {"--alpha", "--max-effects", "--candidates", "--seed", "--plots"} <= set(
        build_parser()._subparsers._group_actions[0].choices["diagnose"]._option_string_actions
    )


def _params(argv: list[str]):
    args = build_parser().parse_args(argv)
    return load_params(ROOT / "params.yaml", overrides=setting_overrides(args))


def test_a_setting_on_the_command_line_is_merged_before_validation():
    params = _params(["diagnose", "--alpha", "0.05", "--candidates", "facet_contact,neutral_zone"])
    diagnose = params.settings.diagnose
    assert diagnose.alpha == 0.05 and diagnose.candidates == ("facet_contact", "neutral_zone")
    assert DiagnoseOptions(**diagnose.options()).alpha == 0.05
    assert params.settings.moments.error_growth.below > 0  # the file's, untouched
    moments = _params(["diagnose", "--max-log-ratio", "0.5"]).settings.moments
    assert moments.max_log_ratio.pair() == (0.5, 0.5)
    calibrate = _params(["calibrate", "--seed", "3", "--options", "{pgd: {n_starts: 16}}"])
    pgd = calibrate.settings.calibrate.method_options("pgd")
    assert calibrate.settings.calibrate.seed == 3 and pgd["n_starts"] == 16
    assert len(pgd) > 1  # merged into the file's pgd options, not replacing them


def test_a_bad_value_on_the_command_line_names_the_option():
    with pytest.raises(
        ConfigError,
        match=r"--alpha \(command line\): diagnose\.alpha: Input should be less than 1, got 1\.5 "
        r"\(float\)",
    ):
        _params(["diagnose", "--alpha", "1.5"])
    with pytest.raises(
        ConfigError, match=r"--options \(command line\): calibrate\.options\.ga\.population: "
    ):
        _params(["calibrate", "--options", "{ga: {population: 30}}"])


def test_the_help_gives_an_example_and_the_files_written(capsys):
    for command, files in (("diagnose", "diagnosis.json"), ("calibrate", "parameters.csv")):
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        text = capsys.readouterr().out
        assert f"example:\n  femcal {command} " in text and files in text


def test_plugin_solvers_and_baselines_are_settings_choices():
    """The FE solvers and the baselines are open registries: a name registered there (as an
    installed plugin's entry point registers it) is a valid setting; its settings pass."""
    from femcal.fe.base import solver_registry
    from femcal.settings import validate_params
    from femcal.surrogates.base import baseline_registry

    state = (solver_registry.snapshot(), baseline_registry.snapshot())
    try:
        solver_registry.register("toy-solver", object)
        methods = {m: None for m in ("fit", "predict", "save", "load")}
        baseline_registry.register("toy-baseline", type("Toy", (), methods))
        fe = {"solver": "toy-solver", "settings": {"mesh_size": 2}}
        settings = validate_params({"fe": fe, "baselines": {"models": ["toy-baseline"]}})
        assert settings.baselines is None  # partial (seed, n_jobs missing): checked, not typed
        with pytest.raises(ConfigError, match=r"baselines\.models\[0\]: expected one of .*'nn'"):
            validate_params({"baselines": {"models": ["nn"]}})
    finally:
        solver_registry.restore(state[0])
        baseline_registry.restore(state[1])


def test_diagnose_has_one_output_folder_option_under_both_names():
    diagnose = build_parser()._subparsers._group_actions[0].choices["diagnose"]
    assert diagnose._option_string_actions["--out"] is diagnose._option_string_actions["--out-dir"]
    args = build_parser().parse_args(["diagnose", "--out-dir", "X"])
    assert args.out == "X" and not setting_overrides(args)
