"""Typed, validated settings: ``params.yaml``, ``fe/params.yaml`` and femcal's environment.

Every key of both params files is described here once: its type, its allowed range or
choices and a one-line doc (the metadata of the frozen dataclasses below). A small generic
validator walks a loaded YAML mapping against them and reports every problem at once, each
with the file, the line, the dotted path of the key, what was given and what is allowed:

* an unknown key names the closest valid key (``calibrate.plot_max: unknown setting; did you
  mean calibrate.max_plots?``); a retired key names what replaced it, and so does a
  misspelling of a retired key;
* a missing required key is named, and so is an unknown key beside it that is probably the
  misspelt one;
* a wrong type or a value out of range says what was given and what is allowed (YAML
  integers are accepted for numbers; booleans are not integers).

Open maps are validated too: the model hyper-parameters of ``train.<split>.fixed`` and
``inverse.fixed`` against the keyword arguments of :class:`femcal.surrogates.nn.
NeuralSurrogate` and :class:`femcal.inverse.InverseModel`, the options of
``calibrate.options.<method>`` against the calibrator's keyword arguments, the FE adapter's
``fe.settings`` against :class:`femcal.fe.calculix.CalculixDisc`, and ``search_space``
entries against their ``{type: float|int|categorical, low, high, log, choices}`` form. The
tables are static so that validating needs no heavy import (no torch, Lightning, scikit-learn
or MLflow); ``tests/test_settings.py`` checks them against the real signatures.

:func:`check_environment` does the same for the environment variables femcal reads.

Two modes: :func:`femcal.config.load_params` (every ``femcal`` command) checks what a file
holds, and leaves missing sections and keys to the command that reads them (through
:func:`femcal.config.section`, which names them); :func:`load_settings` requires a complete
file and returns the typed :class:`Settings`.

The package, by module:

* the generic validator: :mod:`~femcal.settings._messages` (problems and their messages),
  :mod:`~femcal.settings._checks` (checks of single values) and
  :mod:`~femcal.settings._validate` (settings in dataclasses, sections, open maps, keyword
  tables);
* :mod:`~femcal.settings.values`: URLs, addresses, paths, names and moments (the URLs are
  shared with the environment);
* :mod:`~femcal.settings.keywords`: the static keyword tables and the registries' names;
* :mod:`~femcal.settings.search`: Optuna search spaces over those keywords;
* :mod:`~femcal.settings.root` and :mod:`~femcal.settings.fe`: the sections of
  ``params.yaml`` and those only ``fe/params.yaml`` has;
* :mod:`~femcal.settings.params`: the files as a whole (:class:`Settings`,
  :func:`validate_params`, :func:`load_settings`, :func:`describe_setting`);
* :mod:`~femcal.settings.env`: the environment variables (:func:`check_environment`).

Nothing here imports torch, Lightning, scikit-learn, MLflow or pandas.
"""

from femcal.settings._checks import Bool as Bool
from femcal.settings._checks import Choice as Choice
from femcal.settings._checks import Float as Float
from femcal.settings._checks import Int as Int
from femcal.settings._checks import ListOf as ListOf
from femcal.settings._checks import Nullable as Nullable
from femcal.settings._checks import Str as Str
from femcal.settings._validate import Keywords as Keywords
from femcal.settings._validate import MapOf as MapOf
from femcal.settings._validate import Section as Section
from femcal.settings._validate import setting as setting
from femcal.settings.env import ENVIRONMENT, check_environment
from femcal.settings.env import EnvVar as EnvVar
from femcal.settings.fe import FeSettings as FeSettings
from femcal.settings.fe import IdpRange as IdpRange
from femcal.settings.fe import ValidateSettings as ValidateSettings
from femcal.settings.keywords import ACTIVATIONS as ACTIVATIONS
from femcal.settings.keywords import BASELINE_MODELS as BASELINE_MODELS
from femcal.settings.keywords import BUILTIN_EFFECTS as BUILTIN_EFFECTS
from femcal.settings.keywords import (
    CALIBRATOR_OPTIONS,
    INVERSE_HYPERPARAMETERS,
    SURROGATE_HYPERPARAMETERS,
)
from femcal.settings.keywords import CALIBRATORS as CALIBRATORS
from femcal.settings.keywords import GA_DEFAULTS as _GA_DEFAULTS  # noqa: F401 (the tests')
from femcal.settings.keywords import GEOMETRY_FIELDS as GEOMETRY_FIELDS
from femcal.settings.keywords import INVERSE_FIXED as INVERSE_FIXED
from femcal.settings.keywords import MESH_PRESETS as MESH_PRESETS
from femcal.settings.keywords import SOLVER_SETTINGS as SOLVER_SETTINGS
from femcal.settings.keywords import SOLVERS as SOLVERS
from femcal.settings.keywords import SPLITS as SPLITS
from femcal.settings.keywords import SURROGATE_FIXED as SURROGATE_FIXED
from femcal.settings.params import SCHEMAS as SCHEMAS
from femcal.settings.params import (
    Settings,
    describe_setting,
    detect_schema,
    load_settings,
    validate_params,
)
from femcal.settings.root import BaselinesSettings as BaselinesSettings
from femcal.settings.root import CalibrateSettings as CalibrateSettings
from femcal.settings.root import DatasetSettings as DatasetSettings
from femcal.settings.root import DataSettings as DataSettings
from femcal.settings.root import DiagnoseSettings as DiagnoseSettings
from femcal.settings.root import EffectsSettings as EffectsSettings
from femcal.settings.root import InterpolationSettings as InterpolationSettings
from femcal.settings.root import InverseSettings as InverseSettings
from femcal.settings.root import MlflowSettings as MlflowSettings
from femcal.settings.root import MomentSettings as MomentSettings
from femcal.settings.root import PlantSettings as PlantSettings
from femcal.settings.root import TrainSettings as TrainSettings
from femcal.settings.root import TrainSplitSettings as TrainSplitSettings
from femcal.settings.search import SearchEntry as SearchEntry
from femcal.settings.search import SearchSpace as SearchSpace
from femcal.settings.values import DASK_ADDRESS as DASK_ADDRESS
from femcal.settings.values import MODEL_URI as MODEL_URI
from femcal.settings.values import NAME as NAME
from femcal.settings.values import PATH as PATH
from femcal.settings.values import SQL_URL as SQL_URL
from femcal.settings.values import dask_address_problem as dask_address_problem
from femcal.settings.values import mlflow_tracking_uri_problem as mlflow_tracking_uri_problem
from femcal.settings.values import model_uri_problem as model_uri_problem
from femcal.settings.values import sqlalchemy_url_problem as sqlalchemy_url_problem

# The public API; the names re-exported above as ``X as X`` (the keyword tables, the section
# classes, the checks) stay importable from femcal.settings for the tests and for plugins.
__all__ = [
    "CALIBRATOR_OPTIONS",
    "ENVIRONMENT",
    "INVERSE_HYPERPARAMETERS",
    "SURROGATE_HYPERPARAMETERS",
    "Settings",
    "check_environment",
    "describe_setting",
    "detect_schema",
    "load_settings",
    "validate_params",
]
