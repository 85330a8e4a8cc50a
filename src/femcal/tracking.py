"""MLflow glue: where runs go, logging and loading surrogates, champion promotion.

The default tracking and registry store is a SQLite database inside ``mlruns/`` with artifacts
beside it (MLflow 3 refuses a plain file store). ``MLFLOW_TRACKING_URI`` points a team at a
shared server instead.

MLflow records absolute artifact locations (experiments, runs, logged models, model versions).
The default store follows its folder: every start resolves the locations that point into
another folder's store (a copied or moved project) to this one
(:func:`femcal.tracking_store.relocate_store`).

A logged surrogate is a complete MLflow model (logged from code by
:mod:`femcal.training.pyfunc`, as the inverse model) that carries femcal's code
(``code/femcal``) and femcal's dependencies as its requirements, so ``mlflow models serve`` can
rebuild its environment. The train stage exports it to ``models/surrogate-<split>``
(:func:`export_model`), the folder DVC versions: :func:`open_model` and :func:`load_surrogate`
take that folder as well as a registry URI, and :class:`ModelSource` names what was loaded
(content hash, registered version) for the runs that use it. Loading a folder imports no
MLflow (the loader record is read by :mod:`femcal.training.loader`): ``femcal calibrate``
leaves MLflow to its tracking process.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, ModelRegistryError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace
from femcal.tracking_store import DEFAULT_STORE_DIR, local_path, relocate_store
from femcal.training.loader import LOADER_FILE, trusted_loader

logger = logging.getLogger(__name__)

DEFAULT_MODEL_NAME = "ivd-rom-surrogate"
CHAMPION_ALIAS = "champion"
#: Tag on a model version holding the validation metric used for promotion.
VALIDATION_TAG = "val_mae_deg"
#: femcal's training record in an exported model folder (the registered name and version, and
#: whether it became the champion): not part of the MLflow model, so left out of the folder's
#: content hash (:func:`folder_sha256`).
RECORD_FILE = "mlflow.json"
#: The run that logged an exported model (tracking URI, run id, logged model URI): provenance of
#: one machine's store, listed in ``.dvcignore`` so a model rebuilt from the same inputs hashes
#: as ``dvc.lock`` says.
RUN_FILE = ".mlflow-run.json"
#: What an ``MLmodel`` file says about the run, the time and the machine that logged it, left
#: out of an exported folder (:func:`portable_mlmodel`).
_RUN_KEYS = ("artifact_path", "model_id", "model_uuid", "run_id", "utc_time_created")
#: MLflow's note of the registered name and version, rewritten by every registry download.
_REGISTRY_NOTE = "registered_model_meta"


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


def _sqlite_folder(uri: str, *, default: Path) -> Path:
    """The folder of a ``sqlite:///path/mlflow.db`` store (``default`` for an in-memory one)."""
    path = uri[len("sqlite:///") :] if uri.startswith("sqlite:///") else ""
    return Path(path).resolve().parent if path and path != ":memory:" else default.resolve()


def ensure_experiment(name: str, *, store_dir: str | Path = DEFAULT_STORE_DIR) -> str:
    """Create (once) and activate the experiment ``name``; artifacts go beside a local store.

    With a SQLite store (the default ``<store_dir>/mlflow.db``, or any ``sqlite:///`` URI in
    ``MLFLOW_TRACKING_URI``) the artifacts go to ``artifacts/`` beside the database file, so a
    store elsewhere never writes into the project's ``mlruns/``.
    """
    import mlflow

    exp = mlflow.get_experiment_by_name(name)
    if exp is None:
        artifact_location = None
        uri = mlflow.get_tracking_uri()
        if uri.startswith("sqlite:"):
            artifacts = _sqlite_folder(uri, default=Path(store_dir)) / "artifacts"
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
def __getattr__(name: str) -> Any:
    """``SurrogatePyfunc``: the pyfunc class of the surrogates logged before
    :mod:`femcal.training.pyfunc` (their ``pyfunc_model.py`` imports it from here); they still
    load. Imported on use: loading a model folder needs no MLflow."""
    if name == "SurrogatePyfunc":
        from femcal.training.pyfunc import FemcalPyfunc

        return FemcalPyfunc
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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

    The model is logged "from code" (:func:`femcal.training.pyfunc.log_model_from_code`, no
    pickle) with the saved surrogate (weights and JSON) and its ``femcal_loader.json`` under
    ``artifacts/surrogate``, femcal's code under ``code/femcal`` and femcal's dependencies as
    its requirements (:func:`~femcal.training.pyfunc.model_requirements`), so that
    ``mlflow models serve`` with its default environment manager can rebuild it where femcal
    is not installed.

    Returns
    -------
    mlflow.models.model.ModelInfo
        Its ``model_uri`` can be registered, and exported to a folder (:func:`export_model`).
    """
    from femcal.training.pyfunc import log_model_from_code

    return log_model_from_code(surrogate, kind="surrogate", example=input_example(space), name=name)


def portable_mlmodel(text: str) -> str:
    """An ``MLmodel`` file without what names the run, the time and the machine that logged it.

    Left out: ``run_id``, ``model_id``, ``model_uuid``, ``utc_time_created``,
    ``artifact_path`` and each artifact's source ``uri``; ``model_code_path`` is cut to its
    file name (MLflow loads the code file of that name inside the model folder). What loads
    and serves the model (flavors, signature, input example, environment) is kept as is.

    Parameters
    ----------
    text : str
        The YAML of an ``MLmodel`` file.

    Returns
    -------
    str
        The same model's YAML, equal for two trainings of the same weights.
    """
    import yaml

    data = yaml.safe_load(text)
    if not isinstance(data, dict):
        return text
    for key in _RUN_KEYS:
        data.pop(key, None)
    for flavor in (data.get("flavors") or {}).values():
        if not isinstance(flavor, dict):
            continue
        for artifact in (flavor.get("artifacts") or {}).values():
            if isinstance(artifact, dict):
                artifact.pop("uri", None)
        if isinstance(flavor.get("model_code_path"), str):
            flavor["model_code_path"] = os.path.basename(flavor["model_code_path"])
    return yaml.safe_dump(data, default_flow_style=False)


def export_model(
    model_uri: str,
    dest: str | Path,
    *,
    record: Mapping[str, Any] | None = None,
    run: Mapping[str, Any] | None = None,
) -> Path:
    """Write a logged MLflow model into the folder ``dest``, file for file.

    The folder is what the train stage leaves in ``models/`` for DVC: ``mlflow.pyfunc.
    load_model(dest)``, ``mlflow models serve -m dest`` and :func:`load_surrogate` take it,
    and its content hash (:func:`folder_sha256`) equals the registered model's. Its
    ``MLmodel`` is :func:`portable_mlmodel`'s: two trainings of the same weights write the
    same files, whichever run, machine or time logged them.

    Parameters
    ----------
    model_uri : str
        The logged model (``ModelInfo.model_uri``, ``models:/NAME@ALIAS``, ...).
    dest : str or Path
        The folder to create; it must not exist or be empty.
    record : mapping, optional
        femcal's training record (registered name and version, promoted), written as
        :data:`RECORD_FILE` beside the model files.
    run : mapping, optional
        The run that logged it (tracking URI, run id, model URI), written as
        :data:`RUN_FILE` (left out of DVC's hashes by ``.dvcignore``).

    Returns
    -------
    Path
        ``dest``.
    """
    import mlflow

    dest = Path(dest)
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise ModelRegistryError(
            f"Cannot export the model '{model_uri}' to {dest}: it exists and is not an empty "
            "folder. Remove it, or give another destination."
        )
    dest.mkdir(parents=True, exist_ok=True)
    mlflow.artifacts.download_artifacts(artifact_uri=model_uri, dst_path=str(dest))
    mlmodel = dest / "MLmodel"
    if mlmodel.is_file():
        mlmodel.write_text(portable_mlmodel(mlmodel.read_text()))
    for name, content in ((RECORD_FILE, record), (RUN_FILE, run)):
        if content is not None:
            (dest / name).write_text(json.dumps(dict(content), indent=2, default=str) + "\n")
    return dest


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


def register_run_model(
    model_uri: str,
    register_as: str | None,
    *,
    val_metric: float,
    tags: dict[str, str] | None = None,
) -> tuple[str | None, bool]:
    """Register a model logged by the active run when ``register_as`` names it.

    :func:`register_and_promote`, then the run is tagged ``registered_version`` and
    ``promoted``.

    Returns
    -------
    version : str or None
        The new model version (None when ``register_as`` is empty).
    promoted : bool
        Whether the champion alias now points to it.
    """
    if not register_as:
        return None, False
    import mlflow

    version, promoted = register_and_promote(
        model_uri, name=register_as, val_metric=val_metric, tags=tags
    )
    mlflow.set_tags({"registered_version": version, "promoted": str(promoted)})
    return version, promoted


def champion_version(name: str = DEFAULT_MODEL_NAME, *, alias: str = CHAMPION_ALIAS) -> Any | None:
    """The model version holding ``alias``, or None when the model or alias does not exist."""
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    try:
        return MlflowClient().get_model_version_by_alias(name, alias)
    except MlflowException:
        return None


#: A URI with a scheme of two or more characters (``models:/``, ``runs:/``, ``s3://``) is
#: MLflow's to resolve; anything else (and ``file:``) is a folder on this machine.
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]+:")


def is_local_model(uri: str) -> bool:
    """Whether ``uri`` names a folder on this machine (``models/surrogate-large``, ``file:``)."""
    return uri.startswith("file:") or not _SCHEME.match(uri)


def folder_sha256(path: str | Path) -> str:
    """SHA-256 over a model folder's files: their relative paths and contents, sorted.

    Left out: ``__pycache__`` (written when a process imports the model's code), femcal's
    records (:data:`RECORD_FILE`, :data:`RUN_FILE`) and MLflow's ``registered_model_meta``
    (which a registry download rewrites); ``MLmodel`` counts as :func:`portable_mlmodel`
    writes it. So a folder exported from a registered model hashes like the registered model
    itself, and two trainings of the same weights hash alike.
    """
    root = Path(path)
    digest = hashlib.sha256()
    files = sorted(
        (f.relative_to(root).as_posix(), f)
        for f in root.rglob("*")
        if f.is_file()
        and "__pycache__" not in f.relative_to(root).parts
        and f.suffix != ".pyc"
        and f.relative_to(root).as_posix() not in (RECORD_FILE, RUN_FILE, _REGISTRY_NOTE)
    )
    for rel, file in files:
        content = hashlib.sha256()
        if rel == "MLmodel":
            content.update(portable_mlmodel(file.read_text()).encode())
        else:
            with open(file, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    content.update(block)
        digest.update(f"{rel}\0{content.hexdigest()}\n".encode())
    return digest.hexdigest()


@dataclass(frozen=True)
class ModelSource:
    """A model resolved to a folder on this machine, and what it is.

    Attributes
    ----------
    uri : str
        What was asked for: a folder (``models/surrogate-large``) or an MLflow model URI.
    path : Path
        The folder holding the model's files (the folder itself, or MLflow's download).
    sha256 : str
        Its content hash (:func:`folder_sha256`).
    version : str or None
        ``"NAME/VERSION"`` of the registered model: resolved in the registry for a
        ``models:/`` URI, read from the folder's training record (:data:`RECORD_FILE`) for a
        folder; None when unknown or not registered.
    """

    uri: str
    path: Path
    sha256: str
    version: str | None = None

    def tags(self, role: str) -> dict[str, str]:
        """MLflow run tags ``femcal.<role>.uri/.sha256/.version`` naming this model."""
        return {
            f"femcal.{role}.uri": self.uri,
            f"femcal.{role}.sha256": self.sha256,
            f"femcal.{role}.version": self.version or "unknown",
        }


def _recorded_version(folder: Path) -> str | None:
    """``"NAME/VERSION"`` from a model folder's training record, or None."""
    record = folder / RECORD_FILE
    if not record.is_file():
        return None
    try:
        data = json.loads(record.read_text())
        name, version = data.get("registered_model"), data.get("version")
    except (OSError, ValueError, AttributeError) as exc:
        logger.warning("%s is not a femcal training record (%s); version unknown.", record, exc)
        return None
    return f"{name}/{version}" if name and version else None


def open_model(uri: str | os.PathLike[str]) -> ModelSource:
    """Resolve a model folder or an MLflow model URI to a local folder, with its provenance.

    Parameters
    ----------
    uri : str or path-like
        A folder written by the train stage (``models/surrogate-large``, relative to the
        working directory, or ``file:``; a ``pathlib.Path`` too), or an MLflow model URI
        (``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/...``), downloaded from the
        tracking store.

    Raises
    ------
    ModelRegistryError
        The folder does not exist or is a file, or the URI cannot be resolved in the store.
    """
    uri = os.fspath(uri)
    if is_local_model(uri):
        path = local_path(uri) if uri.startswith("file:") else Path(uri)
        if path is None or not path.exists():
            raise ModelRegistryError(
                f"The model folder '{uri}' does not exist (looked in {Path.cwd()}). Fetch it "
                f"with `dvc pull {uri}` (a teammate) or build it with `dvc repro` (the train "
                "stage), or give a registry URI such as models:/ivd-rom-surrogate@champion."
            )
        if not path.is_dir():
            raise ModelRegistryError(
                f"The model '{uri}' is a file; give the model's folder (e.g. "
                "models/surrogate-large, written by `femcal train`) or a registry URI such as "
                "models:/ivd-rom-surrogate@champion."
            )
        return ModelSource(uri, path, folder_sha256(path), _recorded_version(path))
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri))
    except MlflowException as exc:
        raise ModelRegistryError(
            f"Could not load the model '{uri}' from the MLflow store "
            f"{mlflow.get_tracking_uri()}: {exc.message}. Run `dvc repro train` to register one, "
            "set MLFLOW_TRACKING_URI to the team's server, or give the DVC-versioned folder "
            "(models/surrogate-large)."
        ) from None
    info = resolve_model_version(uri)
    version = f"{info['name']}/{info['version']}" if info else None
    return ModelSource(uri, local, folder_sha256(local), version)


def load_surrogate(
    uri: str | os.PathLike[str] | ModelSource = f"models:/{DEFAULT_MODEL_NAME}@{CHAMPION_ALIAS}",
) -> Any:
    """Load a surrogate as the femcal object (with ``torch_module()`` for gradients).

    Only data is read: the ``femcal_loader.json`` must name a class of femcal's surrogate
    registry, which loads its weights with ``torch.load(weights_only=True)`` (and JSON); the
    model's own code (``pyfunc_model.py``, ``code/``) is never run.

    Parameters
    ----------
    uri : str, path-like or ModelSource
        A model folder (``models/surrogate-large``) or an MLflow model URI:
        ``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/...`` (see
        :func:`open_model`), or a source :func:`open_model` returned.
    """
    source = uri if isinstance(uri, ModelSource) else open_model(uri)
    preferred = source.path / "artifacts" / "surrogate" / LOADER_FILE
    candidates = [preferred]
    if not preferred.is_file():  # a model logged by an earlier femcal: anywhere but code/
        candidates = sorted(
            f
            for f in source.path.rglob(LOADER_FILE)
            if f.relative_to(source.path).parts[0] != "code"
            and f.relative_to(source.path).parts[:2] != ("artifacts", "inverse")
        )
    if not candidates:
        raise ModelRegistryError(
            f"'{source.uri}' is not a femcal surrogate (no femcal_loader.json in "
            f"{source.path}). A folder written by `femcal train` before the models became "
            "MLflow models holds config.json and weights.pt only: rebuild it with `dvc repro` "
            "(the train stage) or pull a newer one with `dvc pull`."
        )
    return trusted_loader(candidates[0], uri=source.uri).load(candidates[0].parent)


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
