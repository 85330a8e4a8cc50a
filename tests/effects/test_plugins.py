"""User effects from outside the package: files loaded by path, and installed plugins."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest
import torch
import yaml

import femcal.effects.base as effects_base
from femcal.calibration import SurrogateCurveModel
from femcal.cli import build_parser, main
from femcal.effects import available_effects, get_effect, load_effect_modules
from femcal.effects.composite import EffectModel
from femcal.errors import ConfigError
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = [1.0, 2.0, 3.0, 4.0, 5.0]

#: A series effect in a user's file: creep, extra rotation growing linearly with the moment.
CREEP = '''
import torch

from femcal.effects import Effect, EffectParameter, register_effect


@register_effect
class Creep(Effect):
    """Viscous creep: ``phi_c = c * M`` in every load case, in series with the disc."""

    name = "{name}"
    kind = "series"
    load_cases = ("Flexion", "Extension", "LateralBending", "AxialRotation")
    parameters = (EffectParameter("creep_deg_per_nm", "deg/Nm", 0.0, 0.5, start=0.0),)

    def rotation(self, moment_nm, p):
        c = p["creep_deg_per_nm"].reshape(-1, *([1] * (moment_nm.ndim - 1)))
        return c * moment_nm
'''


@pytest.fixture(autouse=True)
def _clean(clean_registry):
    """Every test here leaves the effect registry as it found it (conftest.clean_registry)."""


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return path


def creep_file(folder: Path, name: str = "creep", file: str = "my_effects.py") -> Path:
    return write(folder / file, CREEP.format(name=name))


@pytest.fixture(scope="module")
def surrogate() -> NeuralSurrogate:
    table = tidy_table(40, seed=5)
    model = NeuralSurrogate(study_space(), hidden=(24, 24), max_epochs=30, batch_size=16, seed=0)
    return model.fit(table, table["rom_deg"].to_numpy())


# ---------------------------------------------------------------- files by path
def test_a_user_file_registers_its_effect_and_the_model_uses_it(tmp_path, surrogate):
    assert "creep" not in available_effects()
    assert load_effect_modules([creep_file(tmp_path)]) == ["creep"]
    assert "creep" in available_effects()
    assert get_effect("creep").__name__ == "Creep"

    base = SurrogateCurveModel(surrogate, MOMENTS)
    model = EffectModel(base, ["creep"])
    assert model.dim == base.dim + 1
    v = torch.rand(3, 13, generator=torch.Generator().manual_seed(0))
    out = model.curves(torch.cat([v, torch.full((3, 1), 0.5)], 1))
    extra = 0.25 * torch.tensor(MOMENTS)  # c = 0.5 of [0, 0.5] deg/Nm, times the moment
    torch.testing.assert_close(out, base.curves(v) + extra, atol=1e-4, rtol=1e-4)


def test_a_folder_loads_its_files_in_name_order_and_skips_private_ones(tmp_path):
    creep_file(tmp_path / "fx", "creep_b", "b.py")
    creep_file(tmp_path / "fx", "creep_a", "a.py")
    write(tmp_path / "fx" / "_helpers.py", "raise RuntimeError('never imported')\n")
    write(tmp_path / "fx" / "notes.txt", "not python\n")
    assert load_effect_modules([str(tmp_path / "fx")]) == ["creep_a", "creep_b"]


def test_loading_the_same_file_again_is_harmless(tmp_path):
    path = creep_file(tmp_path)
    assert load_effect_modules([path]) == ["creep"]
    cls = get_effect("creep")
    # Again, by another spelling of the same path: not re-executed, the same class.
    assert load_effect_modules([tmp_path / "." / path.name, path]) == ["creep"]
    assert get_effect("creep") is cls
    # After a registry reset the file's classes come back without re-importing it.
    effects_base.effect_registry.unregister("creep")
    assert load_effect_modules([path]) == ["creep"]
    assert get_effect("creep") is cls


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match=r"Effect module .*nope\.py does not exist \(looked"):
        load_effect_modules([tmp_path / "nope.py"])


def test_not_a_python_file(tmp_path):
    path = write(tmp_path / "effects.txt", "x = 1\n")
    with pytest.raises(ConfigError, match=r"effects\.txt is not a Python file \(suffix '\.txt'\)"):
        load_effect_modules([path])


def test_a_folder_without_python_files(tmp_path):
    write(tmp_path / "fx" / "_private.py", "x = 1\n")
    with pytest.raises(ConfigError, match=r"Effect folder .*fx holds no \.py file"):
        load_effect_modules([tmp_path / "fx"])


def test_a_module_raising_on_import_shows_the_exception_and_registers_nothing(tmp_path):
    text = CREEP.format(name="creep") + "\nraise RuntimeError('calibrate me first')\n"
    path = write(tmp_path / "broken.py", text)
    with pytest.raises(
        ConfigError,
        match=r"Effect module .*broken\.py raised RuntimeError on import \(line \d+\): "
        r"calibrate me first\. Fix the module",
    ):
        load_effect_modules([path])
    assert "creep" not in available_effects()  # the half-loaded module left nothing behind
    assert not any(m.startswith("femcal_user_effects_broken") for m in sys.modules)


def test_a_syntax_error_names_its_line(tmp_path):
    path = write(tmp_path / "typo.py", "x = 1\ndef f(:\n")
    with pytest.raises(ConfigError, match=r"typo\.py raised SyntaxError on import \(line 2\)"):
        load_effect_modules([path])


def test_a_module_registering_no_effect(tmp_path):
    path = write(tmp_path / "empty.py", "x = 1\n")
    with pytest.raises(ConfigError, match=r"empty\.py registers no effect; define an Effect"):
        load_effect_modules([path])
    undecorated = CREEP.format(name="creep").replace("@register_effect\n", "")
    path = write(tmp_path / "plain.py", undecorated)
    with pytest.raises(
        ConfigError, match=r"plain\.py registers no effect; it defines Creep but registers none"
    ):
        load_effect_modules([path])


def test_a_name_clash_names_the_file_and_the_fix(tmp_path):
    path = creep_file(tmp_path, name="facet_contact", file="clash.py")
    with pytest.raises(
        ConfigError,
        match=r"Effect module .*clash\.py: An effect named 'facet_contact' is already "
        r"registered \(femcal\.effects\.builtin\.FacetContact\).*Give yours another name",
    ):
        load_effect_modules([path])
    assert get_effect("facet_contact").__module__ == "femcal.effects.builtin"
    # Two files defining the same name: the second is refused, the first stays.
    load_effect_modules([creep_file(tmp_path / "one")])
    with pytest.raises(ConfigError, match=r"my_effects\.py: An effect named 'creep' is already"):
        load_effect_modules([creep_file(tmp_path / "two")])


def test_paths_are_checked_before_anything_is_imported(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_effect_modules([creep_file(tmp_path), tmp_path / "missing.py"])
    assert "creep" not in available_effects()


# ---------------------------------------------------------------- command line
def test_the_parser_accepts_repeated_effects_modules():
    parser = build_parser()
    args = parser.parse_args(
        ["calibrate", "--effects-module", "a.py", "--effects-module", "fx/", "--effects", "a"]
    )
    assert args.effects_module == ["a.py", "fx/"]
    assert parser.parse_args(["diagnose", "--effects-module", "a.py"]).effects_module == ["a.py"]
    assert parser.parse_args(["diagnose"]).effects_module is None


def _project_params(folder: Path, modules: list[str]) -> Path:
    """The project's own settings, with ``effects.modules`` and a store of the test's own."""
    params = yaml.safe_load((Path(__file__).parents[2] / "params.yaml").read_text())
    params["effects"] = {"modules": modules}
    params["mlflow"]["store_dir"] = str(folder / "mlruns")
    # The registry, not the project's model folder (which exists after `make repro`, relative to
    # the working directory): the test's own store has no surrogate, so a command stops there.
    params["calibrate"]["model_uri"] = "models:/ivd-rom-surrogate@champion"
    params["calibrate"]["holdout_uri"] = "models:/ivd-rom-surrogate-holdout@champion"
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    measurements = folder / "one.csv"
    measurements.write_text(
        "specimen,load_case,moment_nm,rom_deg\n"
        + "".join(
            f"s1,{lc},{m},{1.0 + m}\n"
            for lc in ("Flexion", "Extension", "LateralBending", "AxialRotation")
            for m in (1, 2, 3, 4, 5)
        )
    )
    return path


@pytest.mark.parametrize("command", ["calibrate", "diagnose"])
def test_the_cli_loads_files_from_params_and_the_option(tmp_path, capsys, command):
    creep_file(tmp_path / "project", "creep_params", "params_effects.py")
    option = creep_file(tmp_path, "creep_option", "option_effects.py")
    params = _project_params(tmp_path / "project", ["params_effects.py"])  # relative to it
    argv = ["--params", str(params), command, "--effects-module", str(option)]
    argv += ["--measurements", str(tmp_path / "project" / "one.csv")]
    argv += ["--out", str(tmp_path / "out")]
    code = main(argv)
    # Settings, --out and the measurements are checked first; the effects are loaded before
    # the model, and the command then stops: the test's store has no registered surrogate.
    assert code == 2
    assert "ivd-rom-surrogate" in capsys.readouterr().err
    assert {"creep_params", "creep_option"} <= set(available_effects())


@pytest.mark.parametrize(
    "effects",
    [["creep.py"], {"modules": "creep.py"}, {"modules": [1]}, {"module": ["creep.py"]}],
)
def test_a_wrong_effects_section_is_refused(tmp_path, capsys, effects):
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"effects": effects}))
    assert main(["--params", str(params), "diagnose"]) == 2
    err = capsys.readouterr().err
    assert "the effects section must be {modules: [paths]}" in err
    assert "Write e.g. `effects: {modules: [my_effects.py]}`" in err


def test_the_cli_reports_a_broken_effect_file(tmp_path, capsys):
    params = _project_params(tmp_path, ["missing.py"])
    argv = ["--params", str(params), "calibrate", "--measurements", str(tmp_path / "one.csv")]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    assert "Effect module" in capsys.readouterr().err


# ---------------------------------------------------------------- installed plugins
def install_plugin(tmp_path: Path, monkeypatch, entry_points: str, modules: dict[str, str]):
    """A minimal installed distribution on sys.path: dist-info with entry points + modules."""
    site = tmp_path / "site"
    info = site / "femcal_plugin_demo-0.1.dist-info"
    write(info / "METADATA", "Metadata-Version: 2.1\nName: femcal-plugin-demo\nVersion: 0.1\n")
    write(info / "entry_points.txt", "[femcal.effects]\n" + entry_points)
    for name, text in modules.items():
        write(site / f"{name}.py", text)
    monkeypatch.syspath_prepend(str(site))  # also invalidates importlib's caches
    effects_base.effect_registry.rescan_plugins()  # as in a fresh process


def test_an_entry_point_naming_a_module_registers_its_effects(tmp_path, monkeypatch):
    install_plugin(
        tmp_path,
        monkeypatch,
        "creep = femcal_plugin_mod\n",
        {"femcal_plugin_mod": CREEP.format(name="plugin_creep")},
    )
    assert "plugin_creep" in available_effects()
    assert get_effect("plugin_creep").__module__ == "femcal_plugin_mod"


def test_an_entry_point_naming_an_effect_class_registers_it(tmp_path, monkeypatch):
    undecorated = CREEP.format(name="class_creep").replace("@register_effect\n", "")
    install_plugin(
        tmp_path,
        monkeypatch,
        "creep = femcal_plugin_cls:Creep\n",
        {"femcal_plugin_cls": undecorated},
    )
    assert get_effect("class_creep").__qualname__ == "Creep"


def test_a_broken_plugin_names_the_entry_point_and_its_error(tmp_path, monkeypatch):
    install_plugin(tmp_path, monkeypatch, "broken = femcal_plugin_missing\n", {})
    with pytest.raises(
        ConfigError,
        match=r"plugin 'broken = femcal_plugin_missing' \(entry point group femcal\.effects, "
        r"distribution femcal-plugin-demo 0\.1\) failed to load: ModuleNotFoundError: .*"
        r"pip uninstall femcal-plugin-demo",
    ):
        available_effects()
    with pytest.raises(ConfigError, match="failed to load"):  # every use, until fixed
        get_effect("facet_contact")


def test_a_plugin_naming_neither_module_nor_effect(tmp_path, monkeypatch):
    install_plugin(
        tmp_path,
        monkeypatch,
        "thing = femcal_plugin_fn:make\n",
        {"femcal_plugin_fn": "def make():\n    return None\n"},
    )
    with pytest.raises(ConfigError, match=r"names <function make .*>, a function; an entry"):
        available_effects()
