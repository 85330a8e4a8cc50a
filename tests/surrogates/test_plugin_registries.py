"""The FE solvers and the baselines as open registries: a plugin installed through an entry
point is a valid setting, runs where the built-ins run, and an unknown name's message lists
the names and says how to register one.

The plugins are real: a dist-info folder with an ``entry_points.txt`` on a temporary
``sys.path`` entry (:func:`dists.install`), found by :func:`importlib.metadata.entry_points`
as an installed package would be.
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
import pytest
from dists import install

from femcal.errors import ConfigError
from femcal.fe import FEJob, make_solver, simulate, solver_registry
from femcal.settings import BASELINE_MODELS, describe, validate_params
from femcal.settings.keywords import BASELINE, SOLVER
from femcal.surrogates import (
    Baseline,
    available_baselines,
    baseline_registry,
    get_baseline,
    make_baseline,
    register_baseline,
)

BASELINE_PLUGIN = '''
import json
from pathlib import Path

import numpy as np

from femcal.surrogates import register_baseline


@register_baseline("mean")
class MeanBaseline:
    """The training mean RoM (deg) of each load case."""

    def __init__(self, space, *, seed=0, n_jobs=1):
        self.space, self.seed, self.n_jobs = space, seed, n_jobs

    def fit(self, X, y):
        cases = X["load_case"].to_numpy()
        self.means_ = {c: float(np.mean(y[cases == c])) for c in sorted(set(cases))}
        return self

    def predict(self, X):
        return np.array([self.means_[c] for c in X["load_case"]])

    def save(self, path):
        Path(path).mkdir(parents=True, exist_ok=True)
        (Path(path) / "means.json").write_text(json.dumps(self.means_))

    @classmethod
    def load(cls, path):
        model = cls(None)
        model.means_ = json.loads((Path(path) / "means.json").read_text())
        return model
'''

SOLVER_PLUGIN = '''
import numpy as np

from femcal.fe import FEResult, PreparedRun, RunOutcome, register_solver


@register_solver("linear-disc")
class LinearDisc:
    """RoM = stiffness_deg_per_nm * level (deg), no IDP: an adapter without a solver."""

    name = "linear-disc"
    max_attempts = 1

    def __init__(self, stiffness_deg_per_nm=0.5):
        self.stiffness_deg_per_nm = stiffness_deg_per_nm

    def version(self):
        return "linear-disc 1"

    def prepare(self, job, workdir, attempt=0):
        workdir.mkdir(parents=True, exist_ok=True)
        deck = workdir / "deck.txt"
        deck.write_text(repr(job))
        return PreparedRun(job, workdir, deck, deck_hash="0", attempt=attempt)

    def run(self, prepared):
        return RunOutcome(returncode=0, log_tail="", cpu_seconds=0.0, wall_seconds=0.0)

    def parse(self, prepared, outcome):
        levels = np.asarray(prepared.job.levels, dtype=float)
        rom = self.stiffness_deg_per_nm * levels
        return FEResult(prepared.job, "ok", "", rom, np.full_like(rom, np.nan), self.version())
'''


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A folder on sys.path for plugins; the registries and the modules restored afterwards."""
    folder = tmp_path / "site"
    folder.mkdir()
    state = (baseline_registry.snapshot(), solver_registry.snapshot())
    monkeypatch.syspath_prepend(str(folder))
    yield folder
    baseline_registry.restore(state[0])
    solver_registry.restore(state[1])
    for name in [m for m in sys.modules if m.startswith("regtest_")]:
        del sys.modules[name]


@pytest.fixture
def baseline_plugin(site):
    """The baseline ``mean`` of the installed distribution ``regtest-baseline``."""
    install(
        site,
        "mean = regtest_baseline\n",
        {"regtest_baseline": BASELINE_PLUGIN},
        group="femcal.baselines",
        name="regtest-baseline",
    )
    baseline_registry.rescan_plugins()
    return "mean"


@pytest.fixture
def solver_plugin(site):
    """The solver ``linear-disc`` of the installed distribution ``regtest-solver``."""
    install(
        site,
        "linear-disc = regtest_solver\n",
        {"regtest_solver": SOLVER_PLUGIN},
        group="femcal.solvers",
        name="regtest-solver",
    )
    solver_registry.rescan_plugins()
    return "linear-disc"


def _table(n: int = 8) -> tuple[pd.DataFrame, np.ndarray]:
    """``n`` rows per load case (two cases), RoM 1 deg in Flexion and 3 deg in Extension."""
    X = pd.DataFrame({"load_case": ["Flexion"] * n + ["Extension"] * n, "moment_nm": 1.0})
    return X, np.r_[np.full(n, 1.0), np.full(n, 3.0)]


def test_the_baseline_registry_holds_the_studys_zoo_and_not_the_network():
    from femcal.surrogates.baselines import LightGBMSurrogate

    assert available_baselines() == sorted(BASELINE_MODELS)
    assert "nn" not in available_baselines()
    assert get_baseline("lightgbm") is LightGBMSurrogate
    assert baseline_registry.group == "femcal.baselines"
    assert issubclass(LightGBMSurrogate, Baseline)  # the protocol's methods


def test_a_baseline_without_save_and_load_is_refused():
    class FitOnly:
        def fit(self, X, y):
            return self

        def predict(self, X):
            return np.zeros(len(X))

    with pytest.raises(ConfigError, match=r"'fit-only', without save, load\. Register such"):
        register_baseline("fit-only")(FitOnly)
    assert "fit-only" not in baseline_registry


def test_a_taken_baseline_name_is_refused(site):
    impostor = type("Impostor", (), {m: None for m in ("fit", "predict", "save", "load")})
    with pytest.raises(ConfigError, match="A baseline named 'lightgbm' is already registered"):
        register_baseline("lightgbm")(impostor)


def test_an_installed_baseline_is_a_setting_and_fits_saves_and_loads(baseline_plugin, tmp_path):
    settings = validate_params({"baselines": {"models": ["linear", baseline_plugin]}})
    assert settings.baselines is None  # partial (seed, n_jobs missing): checked, not typed
    X, y = _table()
    model = make_baseline(baseline_plugin, space=None, seed=0, n_jobs=1).fit(X, y)
    model.save(tmp_path / baseline_plugin)  # as the baselines stage
    loaded = get_baseline(baseline_plugin).load(tmp_path / baseline_plugin)  # as evaluate
    np.testing.assert_array_equal(loaded.predict(X), y)  # exact: the means of equal values


def test_an_installed_solver_is_a_setting_and_runs_a_job(solver_plugin, tmp_path):
    fe = {"solver": solver_plugin, "settings": {"stiffness_deg_per_nm": 0.25}}
    validate_params({"fe": fe})
    adapter = make_solver(solver_plugin, stiffness_deg_per_nm=0.25)
    result = simulate(adapter, FEJob(0, {}, "Flexion", (1.0, 2.0, 4.0)), tmp_path / "job")
    assert result.ok and result.solver_version == "linear-disc 1"
    np.testing.assert_array_equal(result.rom_deg, [0.25, 0.5, 1.0])  # exact in binary


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (
            {"fe": {"solver": "abaqus"}},
            r"fe\.solver: expected one of 'calculix', got 'abaqus' \(str\); to add one, decorate "
            r'a solver adapter class with @register_solver\("name"\) \(femcal\.fe\) and name it '
            r"in the entry-point group femcal\.solvers of your package \(docs: How-to > Write a "
            r"solver, surrogate or baseline plugin\)",
        ),
        (
            {"baselines": {"models": ["linear", "xgboost"]}},
            r"baselines\.models\[1\]: expected one of 'linear', .*'lightgbm', got 'xgboost' "
            r'\(str\); to add one, decorate a baseline class with @register_baseline\("name"\) '
            r"\(femcal\.surrogates\) and name it in the entry-point group femcal\.baselines",
        ),
        (
            {"baselines": {"models": ["nn"]}},
            r"baselines\.models\[0\]: expected one of .*, got 'nn' \(str\); to add one",
        ),
        ({"fe": {"solver": 3}}, r"fe\.solver: expected one of 'calculix', got 3 \(int\)"),
    ],
)
def test_an_unknown_name_lists_the_names_and_how_to_register_one(data, expected):
    with pytest.raises(ConfigError, match=expected):
        validate_params(data)


def test_a_misspelt_plugin_name_is_suggested_among_the_plugins(baseline_plugin, solver_plugin):
    with pytest.raises(
        ConfigError,
        match=r"baselines\.models\[0\]: expected one of .*'lightgbm', 'mean', got 'maen' "
        r"\(str\); did you mean 'mean'\? To add one, decorate a baseline class",
    ):
        validate_params({"baselines": {"models": ["maen"]}})
    with pytest.raises(
        ConfigError,
        match=r"fe\.solver: expected one of 'calculix', 'linear-disc', got 'linear_disk' "
        r"\(str\); did you mean 'linear-disc'\?",
    ):
        validate_params({"fe": {"solver": "linear_disk"}})


def test_the_settings_reference_words_name_the_builtins_and_the_group():
    assert describe(SOLVER) == "one of 'calculix', or a plugin's name (group femcal.solvers)"
    assert describe(BASELINE).startswith("one of 'linear', 'poly2'")
    assert describe(BASELINE).endswith("'lightgbm', or a plugin's name (group femcal.baselines)")
