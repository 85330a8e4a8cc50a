"""Typed, validated settings: ``params.yaml``, ``fe/params.yaml`` and femcal's environment.

Every key is declared once (type with bounds or choices, one-line doc, default); a file's
problems are reported at once, each with the file, line, dotted key, what was given and the fix
(an unknown key names the closest valid one). Modules: ``values`` (value types, the
environment, bases), ``keywords`` (registries' names, keyword arguments, search spaces),
``root`` and ``fe`` (the sections), ``params`` (the files), ``_format`` (the messages).
Nothing here imports torch, Lightning, scikit-learn, MLflow or pandas.
"""

from importlib import import_module
from typing import Any

#: Public name -> its module, imported on first use (PEP 562: the sections load when read).
_HOME = {
    **dict.fromkeys(("ENVIRONMENT", "check_environment"), "values"),
    **dict.fromkeys(("BASELINE_MODELS", "BUILTIN_EFFECTS", "CALIBRATOR_OPTIONS"), "keywords"),
    **dict.fromkeys(("CALIBRATORS", "MESH_PRESETS", "SOLVERS", "SPLITS"), "keywords"),
    **dict.fromkeys(("InverseKeywords", "SurrogateKeywords"), "keywords"),
    **dict.fromkeys(("SCHEMAS", "SECTIONS", "Settings", "describe_setting"), "params"),
    **dict.fromkeys(("detect_schema", "load_settings", "validate_params"), "params"),
    **dict.fromkeys(("closest", "describe", "fields_of", "keys_of", "unwrap"), "_format"),
    "SOLVER_SETTINGS": "fe",
}


def __getattr__(name: str) -> Any:
    if name not in _HOME:
        raise AttributeError(f"module 'femcal.settings' has no attribute {name!r}")
    return getattr(import_module(f"femcal.settings.{_HOME[name]}"), name)


__all__ = sorted(_HOME)
