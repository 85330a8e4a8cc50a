"""The loader record of a saved femcal model: which trusted class reads its folder.

A saved model folder (``artifacts/<kind>`` of a logged model, or a model folder's) holds
``femcal_loader.json``, ``{"loader": "module:QualName"}``: the class whose ``load(folder)``
rebuilds the model from data files. The class is looked up among the classes femcal trusts
for the model's kind, never imported on the file's say-so (:func:`trusted_loader`).

No MLflow here: a process that loads a model folder (``femcal calibrate`` on
``models/surrogate-large``) reads the record without importing MLflow
(:mod:`femcal.training.pyfunc` is the logged model's MLflow side).
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any

from femcal.errors import ModelRegistryError

#: The file of a saved model folder that names its loader class.
LOADER_FILE = "femcal_loader.json"
#: Model kinds: the function that returns the trusted class a loader record names
#: (``"module:function"``, imported on use).
TRUSTED_CLASSES: dict[str, str] = {
    "surrogate": "femcal.surrogates.base:trusted_surrogate_class",
    "inverse": "femcal.inverse.model:trusted_inverse_class",
}


def loader_spec(obj: Any) -> str:
    """``"module:QualName"`` of ``obj``'s class (what ``femcal_loader.json`` records)."""
    cls = type(obj)
    return f"{cls.__module__}:{cls.__qualname__}"


def write_loader(folder: Path, obj: Any) -> Path:
    """Write ``femcal_loader.json`` naming ``obj``'s class into ``folder``; returns the file."""
    file = Path(folder) / LOADER_FILE
    file.write_text(json.dumps({"loader": loader_spec(obj)}) + "\n")
    return file


def trusted_loader(file: Path, *, kind: str = "surrogate", uri: str | None = None) -> type:
    """The trusted class a ``femcal_loader.json`` names (never imported from it).

    Parameters
    ----------
    file : Path
        The ``femcal_loader.json``.
    kind : {"surrogate", "inverse"}
        The kind of model; it decides which classes are trusted (for a surrogate, those of
        femcal's surrogate registry, see :func:`femcal.surrogates.base.trusted_surrogate_class`).
    uri : str, optional
        The model URI it was downloaded from, for messages.

    Returns
    -------
    type
        The class; its ``load(folder)`` rebuilds the model from the folder's data files.

    Raises
    ------
    ModelRegistryError
        The file is not a loader record.
    UntrustedArtifactError
        It names a class femcal does not trust for ``kind``.
    """
    source = f"{file.name} of the model '{uri}'" if uri else str(file)
    try:
        record = json.loads(Path(file).read_text())
        spec = record["loader"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelRegistryError(
            f"{source}: not a femcal loader record ({type(exc).__name__}: {exc}); expected "
            '{"loader": "module:Class"}. Log the model again with femcal.tracking.log_surrogate.'
        ) from None
    if kind not in TRUSTED_CLASSES:
        raise ModelRegistryError(
            f"{source}: unknown femcal model kind {kind!r}; expected one of "
            f"{', '.join(TRUSTED_CLASSES)}."
        )
    module, function = TRUSTED_CLASSES[kind].split(":")
    return getattr(importlib.import_module(module), function)(spec, source=source)
