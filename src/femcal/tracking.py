"""MLflow glue: where runs go, the registered surrogate's pyfunc flavour, champion promotion.

The default tracking and registry store is a SQLite database inside ``mlruns/`` with artifacts
beside it (MLflow 3 refuses a plain file store). ``MLFLOW_TRACKING_URI`` points a team at a
shared server instead.

MLflow records absolute artifact locations (experiments, runs, logged models, model versions).
The default store follows its folder: every start resolves the locations that point into
another folder's store (a copied or moved project) to this one (:func:`relocate_store`).
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
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
    SQLite store in ``store_dir``. The registry follows the tracking store. When the store is
    the one in ``store_dir``, artifact locations recorded by a copy of it elsewhere are
    resolved to ``store_dir`` first (:func:`relocate_store`).
    """
    import mlflow

    uri = tracking_uri or os.environ.get("MLFLOW_TRACKING_URI") or default_tracking_uri(store_dir)
    if uri == f"sqlite:///{Path(store_dir).resolve() / 'mlflow.db'}":
        relocate_store(store_dir)
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    logger.info("MLflow tracking store: %s", uri)
    return uri


#: Columns of MLflow's SQL store that hold artifact locations: (table, column).
_LOCATION_COLUMNS: tuple[tuple[str, str], ...] = (
    ("experiments", "artifact_location"),
    ("runs", "artifact_uri"),
    ("logged_models", "artifact_location"),
    ("model_versions", "source"),
    ("model_versions", "storage_location"),
)


def _local_path(location: str) -> Path | None:
    """The local path of an artifact location (``file://`` URI or absolute path), or None."""
    from urllib.parse import unquote, urlparse

    if location.startswith("file:"):
        return Path(unquote(urlparse(location).path))
    if location.startswith("/"):
        return Path(location)
    return None


def _foreign_roots(db: sqlite3.Connection, root: Path) -> list[Path]:
    """Store folders other than ``root`` that this store's experiments keep artifacts in.

    femcal creates experiments with the artifact root ``<store>/artifacts``; a store whose
    experiments name ``<other>/artifacts``, with ``<other>`` a folder of the same name as
    ``root``, was copied or moved from ``<other>``.
    """
    found = set()
    for (location,) in db.execute("SELECT artifact_location FROM experiments"):
        path = _local_path(str(location or ""))
        if (
            path is not None
            and path.name == "artifacts"
            and path.parent.name == root.name
            and path.parent != root
        ):
            found.add(path.parent)
    return sorted(found)


def relocate_store(store_dir: str | Path = DEFAULT_STORE_DIR) -> dict[str, int]:
    """Resolve a copied or moved default store's artifact locations to its own folder.

    MLflow records absolute locations: the experiment's artifact root, every run's artifact
    URI, every logged model's and model version's location. After ``cp -r`` or ``mv`` of a
    project these still name the original folder, so runs would be written into it and
    registered models read from it. This rewrites every location under another store folder
    ``<other>`` (found from the experiments' ``<other>/artifacts`` roots) to the same place
    under ``store_dir``, in one transaction, and does nothing when all point here already.

    Parameters
    ----------
    store_dir : str or Path
        The store folder holding ``mlflow.db`` and ``artifacts/``.

    Returns
    -------
    dict of str to int
        Rewritten values per ``"table.column"`` (empty when nothing pointed elsewhere).
    """
    root = Path(store_dir).resolve()
    db_file = root / "mlflow.db"
    if not db_file.is_file():
        return {}
    counts: dict[str, int] = {}
    db = sqlite3.connect(db_file, timeout=60, isolation_level=None)
    try:
        try:
            if not _foreign_roots(db, root):  # the usual case: a read, no lock taken
                return {}
            db.execute("BEGIN IMMEDIATE")  # one writer; re-read under the lock
            olds = _foreign_roots(db, root)
        except sqlite3.OperationalError:  # not (yet) an MLflow store: nothing to resolve
            return {}
        if not olds:  # another process resolved them while this one waited for the lock
            return {}
        pairs = []
        for old in olds:
            new = root
            pairs += [(str(old), str(new)), (old.as_uri(), new.as_uri())]
        for table, column in _LOCATION_COLUMNS:
            columns = {row[1] for row in db.execute(f"PRAGMA table_info({table})")}
            if column not in columns:
                continue
            for old_prefix, new_prefix in pairs:
                n = len(old_prefix)
                cur = db.execute(
                    f"UPDATE {table} SET {column} = ? || substr({column}, ?) "
                    f"WHERE {column} = ? OR substr({column}, 1, ?) = ?",
                    (new_prefix, n + 1, old_prefix, n + 1, old_prefix + "/"),
                )
                if cur.rowcount:
                    key = f"{table}.{column}"
                    counts[key] = counts.get(key, 0) + cur.rowcount
        db.execute("COMMIT")
    finally:
        if db.in_transaction:
            db.execute("ROLLBACK")
        db.close()
    logger.warning(
        "The MLflow store %s was copied or moved from %s: %d recorded artifact locations now "
        "point into %s (%s).",
        root,
        ", ".join(map(str, olds)),
        sum(counts.values()),
        root,
        ", ".join(f"{k} {v}" for k, v in sorted(counts.items())),
    )
    return counts


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


def _trusted_loader(file: Path, *, uri: str | None = None) -> Any:
    """The registered surrogate class a ``femcal_loader.json`` names (never imported from it).

    Parameters
    ----------
    file : Path
        The ``femcal_loader.json``.
    uri : str, optional
        The model URI it was downloaded from, for messages.

    Raises
    ------
    ModelRegistryError
        The file is not a loader record.
    UntrustedArtifactError
        It names a class outside femcal's surrogate registry (see
        :func:`femcal.surrogates.base.trusted_surrogate_class`).
    """
    from femcal.surrogates.base import trusted_surrogate_class

    source = f"{file.name} of the model '{uri}'" if uri else str(file)
    try:
        record = json.loads(file.read_text())
        spec = record["loader"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelRegistryError(
            f"{source}: not a femcal loader record ({type(exc).__name__}: {exc}); expected "
            '{"loader": "module:Class"}. Log the model again with femcal.tracking.log_surrogate.'
        ) from None
    return trusted_surrogate_class(spec, source=source)


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
        self.surrogate = _trusted_loader(root / "femcal_loader.json").load(root)

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
    return _trusted_loader(candidates[0], uri=uri).load(candidates[0].parent)


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
