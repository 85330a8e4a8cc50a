"""MLflow glue: where runs go, the registered surrogate's pyfunc flavour, champion promotion.

The default tracking and registry store is a SQLite database inside ``mlruns/`` with artifacts
beside it (MLflow 3 refuses a plain file store). ``MLFLOW_TRACKING_URI`` points a team at a
shared server instead.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, ModelRegistryError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

DEFAULT_STORE_DIR = Path("mlruns")
DEFAULT_MODEL_NAME = "ivd-rom-surrogate"
CHAMPION_ALIAS = "champion"
#: Tag on a model version holding the validation metric used for promotion.
VALIDATION_TAG = "val_mae_deg"


def default_tracking_uri(store_dir: str | Path = DEFAULT_STORE_DIR) -> str:
    """``sqlite:///<store_dir>/mlflow.db`` (absolute path), creating ``store_dir``."""
    store = Path(store_dir).resolve()
    store.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{store / 'mlflow.db'}"


def configure_tracking(
    *, tracking_uri: str | None = None, store_dir: str | Path = DEFAULT_STORE_DIR
) -> str:
    """Point MLflow at the project's store and return the URI in use.

    Precedence: the ``tracking_uri`` argument, then ``MLFLOW_TRACKING_URI``, then the local
    SQLite store in ``store_dir``. The registry follows the tracking store.
    """
    import mlflow

    uri = tracking_uri or os.environ.get("MLFLOW_TRACKING_URI") or default_tracking_uri(store_dir)
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    logger.info("MLflow tracking store: %s", uri)
    return uri


def ensure_experiment(name: str, *, store_dir: str | Path = DEFAULT_STORE_DIR) -> str:
    """Create (once) and activate the experiment ``name``; artifacts go beside a local store."""
    import mlflow

    exp = mlflow.get_experiment_by_name(name)
    if exp is None:
        artifact_location = None
        if mlflow.get_tracking_uri().startswith("sqlite:"):
            artifacts = Path(store_dir).resolve() / "artifacts"
            artifacts.mkdir(parents=True, exist_ok=True)
            artifact_location = artifacts.as_uri()
        try:
            exp_id = mlflow.create_experiment(name, artifact_location=artifact_location)
        except Exception:  # created concurrently by another worker
            exp = mlflow.get_experiment_by_name(name)
            if exp is None:
                raise
            exp_id = exp.experiment_id
    else:
        exp_id = exp.experiment_id
    mlflow.set_experiment(experiment_id=exp_id)
    return exp_id


# --------------------------------------------------------------------------- pyfunc flavour
def _loader_path(obj: Any) -> str:
    cls = type(obj)
    return f"{cls.__module__}:{cls.__qualname__}"


def _import_loader(spec: str) -> Any:
    module, _, qualname = spec.partition(":")
    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


try:  # pragma: no branch - mlflow is a hard dependency; the guard keeps import errors clear
    import mlflow.pyfunc as _pyfunc

    _PythonModel = _pyfunc.PythonModel
except ImportError as exc:  # pragma: no cover
    raise ImportError("femcal.tracking needs mlflow: pip install mlflow") from exc


class SurrogatePyfunc(_PythonModel):
    """MLflow pyfunc wrapper of a saved femcal surrogate.

    ``predict`` takes a DataFrame with columns ``load_case``, ``moment_nm`` and the parameter
    names in physical units, and returns the RoM in degrees, one value per row.
    """

    def load_context(self, context: Any) -> None:
        root = Path(context.artifacts["surrogate"])
        spec = json.loads((root / "femcal_loader.json").read_text())["loader"]
        self.surrogate = _import_loader(spec).load(root)

    def predict(self, context: Any, model_input: pd.DataFrame, params: Any = None) -> np.ndarray:
        frame = model_input.copy()
        frame["load_case"] = frame["load_case"].astype(str)
        return np.asarray(self.surrogate.predict(frame), dtype=float)


def input_example(space: ParameterSpace, n_per_case: int = 1) -> pd.DataFrame:
    """A small valid input table: box-centre parameters at 1..n moments for each load case."""
    centre = (space.lower + space.upper) / 2
    rows = []
    for lc in LOAD_CASES:
        for m in range(1, n_per_case + 1):
            rows.append({"load_case": lc, "moment_nm": float(m), **dict(zip(space.names, centre))})
    return pd.DataFrame(rows)


def log_surrogate(surrogate: Any, space: ParameterSpace, *, name: str = "model") -> Any:
    """Log a fitted surrogate (one with ``save(dir)`` and ``load(dir)``) as an MLflow pyfunc model.

    Returns
    -------
    mlflow.models.model.ModelInfo
        Its ``model_uri`` can be registered.
    """
    import mlflow
    from mlflow.models import infer_signature

    example = input_example(space)
    signature = infer_signature(example, np.asarray(surrogate.predict(example), dtype=float))
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "surrogate"
        surrogate.save(root)
        (root / "femcal_loader.json").write_text(
            json.dumps({"loader": _loader_path(surrogate)}) + "\n"
        )
        info = mlflow.pyfunc.log_model(
            name=name,
            python_model=str(Path(__file__).with_name("pyfunc_model.py")),
            artifacts={"surrogate": str(root)},
            signature=signature,
            input_example=example,
            pip_requirements=_pip_requirements(),
        )
    return info


def _pip_requirements() -> list[str]:
    from importlib.metadata import version

    pkgs = ["torch", "pytorch-lightning", "numpy", "pandas", "scikit-learn", "mlflow"]
    reqs = []
    for p in pkgs:
        try:
            reqs.append(f"{p}=={version(p)}")
        except Exception:  # pragma: no cover - not installed
            reqs.append(p)
    return reqs


def register_and_promote(
    model_uri: str,
    *,
    name: str = DEFAULT_MODEL_NAME,
    val_metric: float,
    alias: str = CHAMPION_ALIAS,
    tags: dict[str, str] | None = None,
) -> tuple[str, bool]:
    """Register ``model_uri`` as a new version of ``name``; move ``alias`` to it if it wins.

    The alias moves only when ``val_metric`` (lower is better) beats the value stored on the
    current alias holder, or when nothing holds the alias yet.

    Returns
    -------
    version : str
        The new model version.
    promoted : bool
        Whether the alias now points to it.
    """
    import mlflow
    from mlflow import MlflowClient

    if not np.isfinite(val_metric):
        raise ConfigError(
            f"Cannot register a model with a non-finite validation metric: {val_metric}."
        )
    client = MlflowClient()
    mv = mlflow.register_model(model_uri, name, tags=tags)
    client.set_model_version_tag(name, mv.version, VALIDATION_TAG, repr(float(val_metric)))
    current = champion_version(name, alias=alias)
    promoted = False
    if current is None:
        promoted = True
    else:
        try:
            best = float(current.tags.get(VALIDATION_TAG, "inf"))
        except ValueError:
            best = float("inf")
        promoted = val_metric < best
    if promoted:
        client.set_registered_model_alias(name, alias, mv.version)
        logger.info(
            "%s version %s is the new %s (%s=%.5f)",
            name,
            mv.version,
            alias,
            VALIDATION_TAG,
            val_metric,
        )
    else:
        logger.info(
            "%s version %s registered; %s stays at version %s (%s %.5f <= %.5f)",
            name,
            mv.version,
            alias,
            current.version,
            VALIDATION_TAG,
            best,
            val_metric,
        )
    return str(mv.version), promoted


def champion_version(name: str = DEFAULT_MODEL_NAME, *, alias: str = CHAMPION_ALIAS) -> Any | None:
    """The model version holding ``alias``, or None when the model or alias does not exist."""
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    try:
        return MlflowClient().get_model_version_by_alias(name, alias)
    except MlflowException:
        return None


def load_surrogate(uri: str = f"models:/{DEFAULT_MODEL_NAME}@{CHAMPION_ALIAS}") -> Any:
    """Load a registered surrogate as the femcal object (with ``torch_module()`` for gradients).

    Parameters
    ----------
    uri : str
        An MLflow model URI: ``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/...``.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri))
    except MlflowException as exc:
        raise ModelRegistryError(
            f"Could not load the model '{uri}' from the MLflow store "
            f"{mlflow.get_tracking_uri()}: {exc.message}. Run `dvc repro train` to register one, "
            "or set MLFLOW_TRACKING_URI to the team's server."
        ) from None
    candidates = list(local.rglob("femcal_loader.json"))
    if not candidates:
        raise ModelRegistryError(f"'{uri}' is not a femcal surrogate (no femcal_loader.json).")
    root = candidates[0].parent
    spec = json.loads(candidates[0].read_text())["loader"]
    return _import_loader(spec).load(root)


def resolve_model_version(uri: str) -> dict[str, str] | None:
    """Name and version behind a ``models:/NAME@ALIAS`` or ``models:/NAME/VERSION`` URI.

    Returns
    -------
    dict or None
        ``{"name", "version", "uri"}``; None for other URIs (``runs:/...``) or when the alias
        or version does not exist.
    """
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    if not uri.startswith("models:/"):
        return None
    ref = uri[len("models:/") :]
    client = MlflowClient()
    try:
        if "@" in ref:
            name, alias = ref.split("@", 1)
            mv = client.get_model_version_by_alias(name, alias)
        else:
            name, version = ref.rsplit("/", 1)
            mv = client.get_model_version(name, version)
    except (MlflowException, ValueError):
        return None
    return {"name": mv.name, "version": str(mv.version), "uri": uri}
