"""Typed, validated settings: ``params.yaml``, ``fe/params.yaml`` and femcal's environment.

Every key of both params files is declared once, in a pydantic model: its type with its
bounds or choices, its one-line doc (the field's description) and its default. Validating a
file reports every problem at once, each with the file, the line, the dotted key, what was
given and what is allowed; an unknown key names the closest valid one, a retired key what
replaced it (:mod:`~femcal.settings._format` turns pydantic's errors into these messages).

The package, by module:

* :mod:`~femcal.settings.values`: numbers with bounds, lists, URLs, names, paths and moments,
  and the bases :class:`~femcal.settings.values.Section` and
  :class:`~femcal.settings.values.Keywords`;
* :mod:`~femcal.settings.keywords`: the registries' names and the keyword arguments that
  ``fixed``, ``options`` and ``fe.settings`` set; :mod:`~femcal.settings.search`: Optuna
  search spaces over them;
* :mod:`~femcal.settings.root` and :mod:`~femcal.settings.fe`: the sections of
  ``params.yaml`` and those only ``fe/params.yaml`` has;
* :mod:`~femcal.settings.params`: the files as a whole (:class:`Settings`,
  :func:`validate_params`, :func:`load_settings`, :func:`describe_setting`);
* :mod:`~femcal.settings.env`: the environment variables (:class:`Environment`,
  :func:`check_environment`).

Nothing here imports torch, Lightning, scikit-learn, MLflow or pandas.
"""

from femcal.settings.env import ENVIRONMENT, Environment, check_environment
from femcal.settings.keywords import (
    BASELINE_MODELS,
    BUILTIN_EFFECTS,
    CALIBRATOR_OPTIONS,
    CALIBRATORS,
    MESH_PRESETS,
    SOLVER_SETTINGS,
    SOLVERS,
    SPLITS,
    GeometryKeywords,
    InverseKeywords,
    SurrogateKeywords,
)
from femcal.settings.params import (
    SCHEMAS,
    SECTIONS,
    Settings,
    describe_setting,
    detect_schema,
    load_settings,
    validate_params,
)

__all__ = [
    "BASELINE_MODELS",
    "BUILTIN_EFFECTS",
    "CALIBRATORS",
    "CALIBRATOR_OPTIONS",
    "ENVIRONMENT",
    "MESH_PRESETS",
    "SCHEMAS",
    "SECTIONS",
    "SOLVERS",
    "SOLVER_SETTINGS",
    "SPLITS",
    "Environment",
    "GeometryKeywords",
    "InverseKeywords",
    "Settings",
    "SurrogateKeywords",
    "check_environment",
    "describe_setting",
    "detect_schema",
    "load_settings",
    "validate_params",
]
