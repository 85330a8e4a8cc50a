"""The inverse model in MLflow: logged as a pyfunc, loaded from a folder or the registry.

Models logged by femcal before :mod:`femcal.inverse` existed run their own entry point, which
imports ``femcal.calibration.inverse.InverseModel``; that name is kept for them.
:func:`load_inverse` reads only the saved folder's data in any case.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, ModelRegistryError
from femcal.inverse.model import FORMAT, InverseModel
from femcal.training.pyfunc import log_model_from_code

#: Registered model name and URI used by default.
DEFAULT_INVERSE_NAME = "ivd-inverse"
DEFAULT_INVERSE_URI = f"models:/{DEFAULT_INVERSE_NAME}@champion"


def log_inverse(model: InverseModel, *, name: str = "model") -> Any:
    """Log a fitted :class:`InverseModel` (with a space) as an MLflow pyfunc model.

    The pyfunc takes a DataFrame with the columns :meth:`InverseModel.rom_columns` and
    returns the parameters in physical units. The model is logged "from code" as every femcal
    model (:func:`femcal.training.pyfunc.log_model_from_code`): MLflow stores the saved model
    folder under ``artifacts/inverse`` and the shared entry point, not a pickle, with femcal's
    code and dependencies as for a surrogate.

    Returns
    -------
    mlflow.models.model.ModelInfo
    """
    model.check_fitted()
    if model.space is None:
        raise ConfigError("Only an InverseModel with a parameter space can be logged.")
    centre = np.exp(model.input_loc_) if model.log_input else model.input_loc_
    example = pd.DataFrame(centre[None, :], columns=model.rom_columns())
    return log_model_from_code(model, kind="inverse", example=example, name=name)


def load_inverse(uri: str | os.PathLike[str] = DEFAULT_INVERSE_URI) -> InverseModel:
    """Load an inverse model as an :class:`InverseModel` (weights and JSON only).

    Parameters
    ----------
    uri : str or path-like
        The folder the train-inverse stage writes (``models/inverse``), or an MLflow model
        URI: ``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/...``.

    Raises
    ------
    ModelRegistryError
        The folder does not exist, the URI cannot be resolved in the current store, or neither
        holds an inverse model.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    from femcal.tracking import is_local_model, open_model

    uri = os.fspath(uri)
    if is_local_model(uri):
        model = find_inverse(open_model(uri).path)
        if model is None:
            raise ModelRegistryError(
                f"'{uri}' is not a femcal inverse model (no saved InverseModel in it); rebuild "
                "it with `dvc repro train-inverse` or fetch it with `dvc pull`."
            )
        return model
    with tempfile.TemporaryDirectory() as tmp:
        try:
            local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=tmp))
        except MlflowException as exc:
            raise ModelRegistryError(
                f"Could not load the inverse model '{uri}' from the MLflow store "
                f"{mlflow.get_tracking_uri()}: {exc.message}. Run `dvc repro train-inverse` to "
                "train and register one, or set MLFLOW_TRACKING_URI to the team's server."
            ) from None
        model = find_inverse(local)
        if model is not None:
            return model
    raise ModelRegistryError(
        f"'{uri}' is not a femcal inverse model (no saved InverseModel in its artifacts); "
        "run `dvc repro train-inverse` to register one."
    )


def find_inverse(folder: Path) -> InverseModel | None:
    """The saved InverseModel in a model folder (``artifacts/inverse`` or any ``config.json`` of
    its format outside ``code/``), or None.

    Only data is read (JSON and weights); the folder's own code is never run.
    """
    for config in sorted(folder.rglob("config.json")):
        if config.relative_to(folder).parts[0] == "code":
            continue
        try:
            fmt = json.loads(config.read_text()).get("format")
        except (ValueError, OSError, AttributeError):
            continue
        if fmt == FORMAT:
            return InverseModel.load(config.parent)
    return None
