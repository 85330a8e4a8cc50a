"""Typed, validated settings: ``params.yaml``, ``fe/params.yaml`` and femcal's environment.

Every key of both params files is declared once, in a pydantic model: its type with its
bounds or choices, its one-line doc (the field's description) and its default. Validating a
file reports every problem at once, each with the file, the line, the dotted key, what was
given and what is allowed; an unknown key names the closest valid one, a retired key what
replaced it (:mod:`~femcal.settings._format` turns pydantic's errors into these messages).

Modules: :mod:`~femcal.settings.values` (value types, the bases of sections and keyword
tables), :mod:`~femcal.settings.keywords` (registries' names, keyword arguments, search
spaces), :mod:`~femcal.settings.root` and :mod:`~femcal.settings.fe` (the sections),
:mod:`~femcal.settings.params` (the files as a whole) and :mod:`~femcal.settings.env` (the
environment variables). Nothing here imports torch, Lightning, scikit-learn, MLflow or pandas.
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
