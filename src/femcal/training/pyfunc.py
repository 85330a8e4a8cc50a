"""The MLflow "model from code" mechanism of every femcal model (surrogates, inverse model).

A logged model holds its saved folder under ``artifacts/<kind>`` (``config.json``,
``weights.pt`` and ``femcal_loader.json``, which names the class that reads the folder), the
entry point ``pyfunc_model.py`` (this package's, which sets :class:`FemcalPyfunc` as the
model), femcal's code under ``code/femcal`` and femcal's dependencies as requirements. Nothing
is pickled: loading reads data files, and the loader class must be one femcal trusts
(:func:`trusted_loader`).

Kinds (the artifact's name):

* ``"surrogate"`` - input: a DataFrame with ``load_case``, ``moment_nm`` and the parameter
  columns; output: RoM in degrees, shape (n,);
* ``"inverse"`` - input: a DataFrame with the RoM columns ``'<load case>@<moment>'``;
  output: a DataFrame of the parameters in physical units, n rows.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mlflow.pyfunc
import numpy as np
import pandas as pd

from femcal.errors import ModelRegistryError
from femcal.training.loader import (  # noqa: F401 - their home before loader.py
    LOADER_FILE,
    TRUSTED_CLASSES,
    loader_spec,
    trusted_loader,
    write_loader,
)

#: femcal's dependencies a logged model does not need: the pipeline's tools.
PIPELINE_ONLY_REQUIREMENTS = frozenset({"dvc", "optuna", "distributed", "dask"})
#: What loading a logged model imports: always among its requirements, with femcal's other
#: declared dependencies (:func:`model_requirements`).
MODEL_REQUIREMENTS = (
    "torch",
    "pytorch-lightning",
    "mlflow",
    "numpy",
    "pandas",
    "scikit-learn",
    "scipy",
    "threadpoolctl",
    "lightgbm",
    "skops",
    "matplotlib",
    "pyyaml",
    "tqdm",
)
#: The entry point MLflow runs when it loads a femcal model.
ENTRY_POINT = Path(__file__).with_name("pyfunc_model.py")


def femcal_code(dest: Path) -> Path:
    """Copy the femcal package (its sources, no ``__pycache__``) to ``dest/femcal``.

    A logged model carries this copy (MLflow ``code_paths``): a process that loads the model
    without femcal installed (``mlflow models serve`` in a fresh environment) imports it from
    there. Returns ``dest/femcal``.
    """
    package = Path(__file__).resolve().parent.parent
    target = Path(dest) / "femcal"
    shutil.copytree(
        package, target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    )
    return target


def model_requirements() -> list[str]:
    """The pip requirements of a logged femcal model: femcal's dependencies, pinned.

    :data:`MODEL_REQUIREMENTS` and every other dependency femcal declares (not its extras),
    at the installed version (a local label such as torch's ``+cpu`` dropped: the index
    decides the build), except the pipeline's tools (:data:`PIPELINE_ONLY_REQUIREMENTS`),
    which loading a model never imports. femcal itself is not a requirement: the model
    carries its code (:func:`femcal_code`).
    """
    from importlib import metadata

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    try:
        declared = [Requirement(r) for r in metadata.requires("femcal") or []]
    except metadata.PackageNotFoundError:  # pragma: no cover - run from a source tree
        declared = []
    reqs: dict[str, str] = {}
    for req in [*(Requirement(r) for r in MODEL_REQUIREMENTS), *declared]:
        name = canonicalize_name(req.name)
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue  # an extra (dev tools)
        if name in PIPELINE_ONLY_REQUIREMENTS or name in reqs:
            continue
        try:
            installed = metadata.version(req.name)
        except metadata.PackageNotFoundError:  # pragma: no cover - declared, not installed
            reqs[name] = str(req)
            continue
        reqs[name] = f"{req.name}=={installed.split('+', 1)[0]}"
    return list(reqs.values())


def _predict_rom(model: Any, frame: pd.DataFrame) -> np.ndarray:
    frame = frame.copy()
    frame["load_case"] = frame["load_case"].astype(str)
    return np.asarray(model.predict(frame), dtype=float)


def _predict_frame(model: Any, frame: pd.DataFrame) -> pd.DataFrame:
    return model.predict_frame(frame)


_PREDICT: dict[str, Callable[[Any, pd.DataFrame], Any]] = {
    "surrogate": _predict_rom,
    "inverse": _predict_frame,
}


class FemcalPyfunc(mlflow.pyfunc.PythonModel):
    """MLflow pyfunc wrapper of a saved femcal model (its one artifact names the kind).

    ``predict`` takes a DataFrame: for a surrogate the columns ``load_case``, ``moment_nm``
    and the parameter names in physical units, returning the RoM in degrees, shape (n,); for
    an inverse model the RoM columns, returning the parameters as a DataFrame (n rows).
    """

    def load_context(self, context: Any) -> None:
        kinds = [k for k in context.artifacts if k in _PREDICT]
        if len(kinds) != 1:
            raise ModelRegistryError(
                f"A femcal model has one artifact named after its kind ({', '.join(_PREDICT)}); "
                f"this one has {sorted(context.artifacts)}."
            )
        self.kind = kinds[0]
        root = Path(context.artifacts[self.kind])
        self.model = trusted_loader(root / LOADER_FILE, kind=self.kind).load(root)

    def predict(self, context: Any, model_input: pd.DataFrame, params: Any = None) -> Any:
        return _PREDICT[self.kind](self.model, model_input)


def log_model_from_code(
    model: Any,
    *,
    kind: str,
    example: pd.DataFrame,
    name: str = "model",
) -> Any:
    """Log a fitted femcal model (with ``save(dir)`` and ``load(dir)``) as an MLflow pyfunc.

    The model is logged "from code" (:data:`ENTRY_POINT`, no pickle) with its saved folder
    and ``femcal_loader.json`` under ``artifacts/<kind>``, femcal's code under
    ``code/femcal`` and femcal's dependencies as its requirements
    (:func:`model_requirements`), so that ``mlflow models serve`` with its
    default environment manager can rebuild it where femcal is not installed.

    Parameters
    ----------
    model : object
        The fitted model; ``save(folder)`` writes it, its class's ``load(folder)`` reads it.
    kind : {"surrogate", "inverse"}
        What the pyfunc's ``predict`` does (see the module's docstring).
    example : DataFrame
        A valid input; with the model's prediction on it, it gives the signature.
    name : str
        The logged model's name in the active run.

    Returns
    -------
    mlflow.models.model.ModelInfo
        Its ``model_uri`` can be registered, and exported to a folder
        (:func:`femcal.tracking.export_model`).
    """
    import mlflow
    from mlflow.models import infer_signature

    if kind not in _PREDICT:
        raise ModelRegistryError(f"Unknown femcal model kind {kind!r}; use {', '.join(_PREDICT)}.")
    signature = infer_signature(example, _PREDICT[kind](model, example))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / kind
        model.save(root)
        write_loader(root, model)
        return mlflow.pyfunc.log_model(
            name=name,
            python_model=str(ENTRY_POINT),
            artifacts={kind: str(root)},
            signature=signature,
            input_example=example,
            pip_requirements=model_requirements(),
            code_paths=[str(femcal_code(Path(tmp)))],
        )
