"""A calibrator installed as a plugin: chosen in params.yaml and on the command line, its
options checked against its signature, and run by the calibrate stage.

The plugin is real: a dist-info folder with an ``entry_points.txt`` (group
``femcal.calibrators``) on a temporary ``sys.path`` entry, found by
:func:`importlib.metadata.entry_points` as an installed package would be.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from dists import install

from femcal.calibration import calibrate
from femcal.calibration.base import calibrator_registry
from femcal.cli import build_parser
from femcal.errors import ConfigError
from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.settings import validate_params
from femcal.stages.calibrate import plugin_options

from synth import long_csv

PLUGIN = '''
import numpy as np

from femcal.calibration import register_calibrator
from femcal.calibration.base import Solution


@register_calibrator("centre")
def centre(problem, *, rng, shift: float = 0.0):
    """Every specimen at the box's centre, moved by ``shift`` of the box towards its top."""
    space = problem.model.space
    unit = np.full((problem.n_specimens, len(space.names)), 0.5 + shift)
    x = space.clip(problem.model.linear_unit_to_physical(unit))
    n = problem.n_specimens
    return Solution(x=x, nit=0, success=np.ones(n, dtype=bool), message="box centre")
'''


def _install(site, entry_points: str, modules: dict[str, str]) -> None:
    """The distribution ``regtest-calib`` with ``entry_points`` of ``femcal.calibrators``."""
    install(site, entry_points, modules, group="femcal.calibrators", name="regtest-calib")


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A folder on sys.path for plugins; the registry and the modules restored afterwards."""
    folder = tmp_path / "site"
    folder.mkdir()
    state = calibrator_registry.snapshot()
    monkeypatch.syspath_prepend(str(folder))
    yield folder
    calibrator_registry.restore(state)
    for name in [m for m in sys.modules if m.startswith("regtest_")]:
        del sys.modules[name]


@pytest.fixture
def plugin(site):
    """The calibrator ``centre`` of the installed distribution ``regtest-calib``."""
    _install(site, "centre = regtest_calib\n", {"regtest_calib": PLUGIN})
    calibrator_registry.rescan_plugins()
    return "centre"


def test_params_choose_a_plugin_calibrator_and_pass_its_options(plugin):
    settings = validate_params(
        {"calibrate": {"method": plugin, "options": {plugin: {"shift": 0.1}, "pgd": {}}}}
    )
    section = settings.require("calibrate", "method", "options")  # a partial section
    assert section.method == plugin and section.method_options() == {"shift": 0.1}


def test_a_misspelt_method_names_the_plugins_too(plugin):
    with pytest.raises(
        ConfigError,
        match=r"calibrate\.method: expected one of 'pgd', 'pgd-study', 'ga', 'inverse', "
        r"'centre', got 'centr' \(str\); did you mean 'centre'\?",
    ):
        validate_params({"calibrate": {"method": "centr"}})


def test_a_plugins_options_must_be_a_mapping(plugin):
    with pytest.raises(
        ConfigError,
        match=r"calibrate\.options\.centre: expected a mapping of the centre calibrator's "
        r"keyword options, got 3 \(int\)",
    ):
        validate_params({"calibrate": {"options": {plugin: 3}}})
    with pytest.raises(ConfigError, match=r"calibrate\.options\.centr: unknown calibration"):
        validate_params({"calibrate": {"options": {"centr": {}}}})


def test_options_the_plugin_does_not_take_are_refused_with_what_it_takes(plugin):
    plugin_options(plugin, {"shift": 0.2}, "params.yaml")  # a keyword it takes
    with pytest.raises(
        ConfigError,
        match=r"params\.yaml: calibrate\.options\.centre\.shfit: not a keyword of the centre "
        r"calibrator \(did you mean shift\?\); calibrate\.options\.centre\.rng: not a keyword "
        r"of the centre calibrator \(set calibrate\.seed\)\. It takes: shift; fix or remove",
    ):
        plugin_options(plugin, {"shfit": 0.2, "rng": 1}, "params.yaml")


def test_the_command_line_takes_a_plugin_method(plugin):
    args = build_parser().parse_args(["calibrate", "--method", plugin])
    assert args.method == plugin


def test_the_calibrate_stage_runs_a_plugin_calibrator(plugin, registry, truth, curve_model):
    result = calibrate(curve_model, truth[1], method=plugin, options={"shift": 0.0})
    centre = curve_model.space.clip(curve_model.linear_unit_to_physical(np.full((1, 13), 0.5)))
    np.testing.assert_allclose(result.x, np.repeat(centre, len(truth[1]), axis=0))
    settings = CalibrationJob(
        measurements=long_csv(registry / "meas.csv", truth[1][:3]),
        out_dir=registry / "out",
        method=plugin,
        model_uri="models:/ivd-rom-surrogate@champion",
        holdout_uri=None,
        start_bank=None,
        options={"shift": 0.1},
        seed=0,
        error_growth=3.2,
        max_log_ratio=0.51,
        plots="none",
    )
    _, figures = run_calibration(settings)
    assert figures["method"] == plugin and figures["n_specimens"] == 3


def test_a_broken_plugin_is_named_where_it_is_used_not_in_the_settings(site):
    """The settings read entry-point names and load nothing: the registry, where the stage
    looks the calibrator up, names the plugin that fails and the fix."""
    _install(site, "broken = regtest_broken\n", {"regtest_broken": "raise ImportError('no')\n"})
    calibrator_registry.rescan_plugins()
    assert validate_params({"calibrate": {"method": "broken"}}).require("calibrate").method == (
        "broken"
    )
    with pytest.raises(ConfigError, match=r"plugin 'broken = regtest_broken'.*failed to load"):
        calibrator_registry.get("broken")


def test_a_calibrator_registered_in_this_process_is_a_method(site):
    from femcal.calibration import register_calibrator

    register_calibrator("inline")(lambda problem, *, rng: None)
    assert validate_params({"calibrate": {"method": "inline"}}).require("calibrate").method == (
        "inline"
    )
